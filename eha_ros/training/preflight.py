"""Generate the pre-flight data and train the pre-flight network
(:mod:`eha_ros.health.preflight`); write ``faults.npz``.

Data (:func:`cases`, :func:`generate_sets`)
    The pre-flight check on the high-fidelity plant (:func:`eha_ros.physics.maintenance.
    run_preflight`, 1 us step).  Case ``i`` of stream ``s`` draws from its own generator
    ``default_rng([s, i])``, independently:

    * the five faults of :data:`~eha_ros.health.preflight.FAULTS`: every one uniform over its
      range (even ``i``), or each degraded with probability 0.3 and nominal otherwise (odd
      ``i``, so the nominal valve is well covered); dynamic frictions follow their breakaway
      values at the nominal ratio (:data:`FRICTION_RATIO`) unless the fleet draws them;
    * the drift no bench measures (domain randomisation): every entry of the test bench's
      ``nuisance`` (:mod:`eha_ros.physics.bench`, ``config/test_bench.yaml``) uniform over its
      range, and the spool's radial clearance and overlap (both edges equal) uniform over
      :data:`VALVE_NUISANCE` (the valve test reads those);
    * the unit of a fleet (``fleet``, the build's default): then every other nuisance of
      ``config/tolerances.yaml`` uniform over its range, the dynamic frictions as a ratio of
      the case's breakaway frictions (:func:`eha_ros.physics.tolerances.draw_unit`, drawn
      after the case's seed);
    * the true test conditions uniform over the bench's ``service`` envelope: supply and
      return pressure, and the fluid temperature (viscosity and density by the fluid law);
    * the noise seed, which also seeds the bench's measurement of the conditions
      (:func:`eha_ros.physics.bench.measure_conditions`, :data:`CONDITION_READINGS` readings,
      averaged): the network's last three inputs.

    Training, validation, calibration, the OOD limit and the benchmark
    (``bench/health_preflight.py``) use different streams.

Training and calibration (:func:`build_artefact`)
    The ensemble on the training stream; per fault a deviation factor (at least 1) such that
    95 % of the validation cases and 95 % of the 2-3-fault combination cases (each set on its
    own, the larger factor kept) lie within 2 sigma; the out-of-distribution model
    (:class:`~eha_ros.health.preflight.OodModel`: ridge estimates of every drawn parameter
    fitted on the training stream, their deviations and penalties on the validation stream;
    the principal subspace of the training inputs), its limit from a further drifted stream
    (``ood``), on which the calibrated deviations are checked too.

The checks run as sweeps (:mod:`eha_ros.sweep`, one single-threaded worker process per core),
one per set, in blocks of :data:`BLOCK` cases.  Build: ``nice python -m
eha_ros.training.preflight --data DIR`` writes ``faults.npz``; ``DIR`` keeps the sweeps, and a
rerun reads what they already hold.  The 49,600 checks (48,000 training, 600 validation, 400
combinations, 600 OOD) took 2,750 s on 2 workers over three runs, each resuming the last
(7,600 in 347 s, 18,000 more in 1,299 s, 24,000 more in 1,103 s; sharing the 2 cores with
other jobs, load average 1-3); training took 219 s.  On the held-out OOD stream, each doubling
of the training set still lowers the errors: 1,500 / 3,000 / 6,000 / 24,000 / 48,000 training
checks gave filter clogging 6.8 / 6.1 / 5.5 / 4.9 / 4.6 % of range.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.health.preflight import (CONDITION_READINGS, FAULT_NAMES, FAULTS, FAULTS_FILE,
                                      N_INPUTS, RING_COLUMNS, FaultModel, NetEnvelope,
                                      OodModel, Subspace, load_faults)
from eha_ros.mlp import mlp_forward
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.bench import (CONDITIONS, load_bench, mean_conditions,
                                   measure_conditions)
from eha_ros.physics.maps import fluid_hash
from eha_ros.physics.params import replace
from eha_ros.physics.tolerances import draw_unit, load_tolerances

# Run as a script, this module is the main module the sweep's spawned workers import again
# before their single-thread settings apply: numba's pool must start with the same setting.
if __name__ in ('__main__', '__mp_main__'):
    os.environ.setdefault('NUMBA_NUM_THREADS', '1')

__all__ = ['FAULT_SETTINGS', 'VALVE_NUISANCE', 'BLOCK', 'draw_wear', 'inner_service',
           'draw_drift', 'apply_wear', 'wear_changes', 'cases', 'combination_cases', 'case_params',
           'case_conditions', 'data_sets', 'generate', 'generate_sets', 'train_faults',
           'calibrate', 'recalibrate', 'envelope_parameters', 'envelope_targets', 'fit_ood',
           'build_artefact']

#: Dynamic friction over breakaway friction for the drawn cases (the parameters' nominal).
FRICTION_RATIO = 0.5
#: Valve geometry drawn as nuisance (the valve test reads it): ``name -> (lo, hi)`` [m]; the
#: overlap sets both edges.
VALVE_NUISANCE = {'radial_clearance_m': (1e-6, 6e-6), 'overlap_supply_m': (-2e-6, 6e-6)}
#: Cases per sweep of a set (a set of more runs as several sweeps, each resumable).
BLOCK = 1000

FAULT_SETTINGS = {
    'n_train': 48000, 'seed_train': 21, 'n_val': 600, 'seed_val': 22,
    'n_cal': 400, 'seed_cal': 23, 'n_ood': 600, 'seed_ood': 24,
    'members': 4, 'hidden': [128, 64], 'batch': 256, 'warmup_epochs': 40, 'nll_epochs': 80,
    'lr': 1e-3, 'weight_decay': 1e-4, 'degrade_probability': 0.3,
    'ood_subspaces': [[0, N_INPUTS, 0.99], list(RING_COLUMNS) + [0.9999]],
    'ood_quantile': 0.995, 'ood_margin': 1.25,
    'ridge_lambdas': [0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0], 'fleet': True,
    'ood_net': {'hidden': [256, 256], 'epochs': 40, 'batch': 256, 'lr': 1e-3,
                'weight_decay': 1e-5, 'seed': 31},
}
#: Settings the OOD model alone depends on: ``--ood-only`` may change them on a built network.
OOD_SETTINGS = ('ood_subspaces', 'ood_quantile', 'ood_margin', 'ridge_lambdas', 'ood_net')


def draw_wear(rng: np.random.Generator, sparse: bool, p_degrade: float = 0.3) -> dict:
    """The five faults of one case: every one uniform over its range, or (``sparse``) each
    degraded with probability ``p_degrade`` and nominal otherwise."""
    out = {}
    for f in FAULTS:
        u = rng.uniform(f.lo, f.hi)
        flip = rng.uniform() < p_degrade
        out[f.name] = float(u if (not sparse or flip) else f.nominal)
    return out


def inner_service(bench=None) -> dict:
    """The service envelope less each sensor's calibration error and three noise
    deviations: true conditions in it are measured within the envelope."""
    b = bench or load_bench()
    return {name: (lo + m, hi - m) for name, (lo, hi) in b.service.items()
            for m in (b.sensors[name].bias + 3 * b.sensors[name].noise_std,)}


def draw_drift(rng: np.random.Generator, bench=None, params: PlantParams | None = None,
               inner: bool = False) -> dict:
    """Plant parameters of the unmeasured drift and the true test conditions of one case:
    each bench nuisance and :data:`VALVE_NUISANCE` entry uniform over its range, supply and
    return pressure and the fluid temperature uniform over the service envelope (``inner``:
    over :func:`inner_service`)."""
    b = bench or load_bench()
    p = params or default_params()
    service = inner_service(b) if inner else b.service
    out = {name: float(rng.uniform(*b.nuisance_range(name, p))) for name in b.nuisance}
    out.update({name: float(rng.uniform(*r)) for name, r in VALVE_NUISANCE.items()})
    out.update({name: float(rng.uniform(*service[name])) for name in CONDITIONS})
    return out


def apply_wear(params: PlantParams, wear: dict) -> PlantParams:
    """``params`` with the plant parameters of ``wear`` (frictions set their dynamic values
    at :data:`FRICTION_RATIO`, the overlap both edges)."""
    return replace(params, **wear_changes(wear))


def wear_changes(wear: dict) -> dict:
    """The plant parameters :func:`apply_wear` sets for ``wear`` (names and values): the
    overlap both edges, and a dynamic friction not given at :data:`FRICTION_RATIO` of its
    breakaway friction."""
    w = dict(wear)
    if 'overlap_supply_m' in w:
        w['overlap_return_m'] = w['overlap_supply_m']
    for part in ('spool', 'jack'):
        key = f'{part}_static_friction_n'
        if key in w and f'{part}_dynamic_friction_n' not in w:
            w[f'{part}_dynamic_friction_n'] = FRICTION_RATIO * w[key]
    return w


def cases(n: int, stream: int, p_degrade: float = 0.3, drift: bool = True,
          inner: bool = False, fleet: bool = False):
    """``n`` cases of stream ``stream`` as ``(plant changes, seed)``: case ``i`` from its
    own generator ``default_rng([stream, i])``, sparse for odd ``i``; with ``drift`` the
    nuisances and conditions drawn too (:func:`draw_drift`, ``inner``), nominal
    otherwise; ``fleet``: the unit of a fleet (module docstring), drawn after the case's seed
    so that the other draws are those of the case without the fleet."""
    return _draw_cases(n, stream, lambda rng, i: draw_wear(rng, bool(i % 2), p_degrade),
                       drift, inner, fleet)


def combination_cases(n: int, stream: int, drift: bool = True, fleet: bool = False):
    """``n`` cases as maintenance finds them: two or three of the five faults (alternately)
    uniform over their ranges, the others nominal; with ``drift`` the nuisances and
    conditions drawn (:func:`draw_drift`); ``fleet``: as :func:`cases`; case ``i`` from
    ``default_rng([stream, i])``."""
    def wear(rng, i):
        w = {f.name: f.nominal for f in FAULTS}
        for j in rng.choice(len(FAULTS), size=2 + i % 2, replace=False):
            w[FAULTS[j].name] = float(rng.uniform(FAULTS[j].lo, FAULTS[j].hi))
        return w
    return _draw_cases(n, stream, wear, drift, False, fleet)


def _draw_cases(n: int, stream: int, draw_faults, drift: bool, inner: bool, fleet: bool):
    """The cases of :func:`cases` and :func:`combination_cases`, the faults of case ``i``
    from ``draw_faults(rng, i)``."""
    b, p = load_bench(), default_params()
    out = []
    for i in range(n):
        rng = np.random.default_rng([stream, i])
        wear = draw_faults(rng, i)
        if drift:
            wear.update(draw_drift(rng, b, p, inner))
        seed = int(rng.integers(0, 2 ** 31 - 1))
        out.append((draw_unit(rng, wear, p) if fleet else wear, seed))
    return out


def case_params(case, params: PlantParams | None = None) -> PlantParams:
    """Plant parameters of a case ``(changes, seed)``."""
    return apply_wear(params if params is not None else default_params(), case[0])


def case_conditions(case, params: PlantParams | None = None):
    """The measured conditions of a case: the mean of :data:`CONDITION_READINGS` bench
    readings seeded by the case's seed."""
    return mean_conditions(measure_conditions(case_params(case, params), case[1],
                                              CONDITION_READINGS))


def generate(case_list, params: PlantParams | None = None, workers: int = 2,
             progress=None, out=None) -> tuple[np.ndarray, np.ndarray]:
    """Network inputs ``(n, N_INPUTS)`` and targets ``(n, len(FAULTS))`` of the pre-flight
    check on the high-fidelity plant for ``case_list`` (from :func:`cases`); see
    :func:`generate_sets`."""
    return generate_sets({'cases': case_list}, params, workers, progress, out)['cases']


def generate_sets(sets: dict, params: PlantParams | None = None, workers: int = 2,
                  progress=None, out=None, stats: dict | None = None) -> dict:
    """``{name: (inputs, targets)}`` for ``{name: case_list}``: the inputs are the check's
    features (:func:`~eha_ros.health.preflight.preflight_features`) followed by the case's
    measured conditions (:func:`case_conditions`).  Each set runs as sweeps of at most
    :data:`BLOCK` cases (:mod:`eha_ros.sweep`: ``workers`` single-threaded processes, in
    this process for one).  ``out``: a folder holding one sweep dataset per set and block
    (``name-k``), kept and resumed; temporary ones otherwise.  ``progress``: show the
    sweeps' progress bars.  ``stats``: gets ``worker_s``, the workers' time running the checks
    (when they ran, also in an earlier run resumed here)."""
    import tempfile

    from eha_ros.physics import params_to_dict
    from eha_ros.sweep import SweepError, parse_spec, read_dataset, run_sweep
    p = params if params is not None else default_params()
    out_sets = {}
    with tempfile.TemporaryDirectory(prefix='eha-preflight-') as tmp:
        root = Path(out) if out is not None else Path(tmp)
        for name, case_list in sets.items():
            feats = []
            for k in range(0, len(case_list), BLOCK):
                block = case_list[k:k + BLOCK]
                raw = {'procedure': 'preflight_check', 'models': ['hf'], 'noise': True,
                       'metrics': [], 'signals': ['preflight_features'],
                       'cases': [{**wear_changes(w), 'seed': int(seed)} for w, seed in block]}
                spec = parse_spec(raw, source=f'pre-flight data {name}',
                                  base=params_to_dict(p))
                ids = [pt.cases[0].case_id for pt in spec.points()]
                folder = root / f'{name}-{k // BLOCK}'
                resume = folder.is_dir() and any(folder.iterdir())
                if progress and not resume:
                    progress(f'{folder}: {len(block)} pre-flight checks')
                run_sweep(spec, folder, workers=workers, in_process=workers <= 1,
                          resume=resume, progress=bool(progress))
                t = read_dataset(folder).select(['case_id', 'status', 'error', 'wall_s',
                                                 'signal_preflight_features'])
                if stats is not None:
                    stats['worker_s'] = stats.get('worker_s', 0.0) + float(np.nansum(
                        np.array(t.column('wall_s').to_pylist(), dtype=float)))
                row = {c: j for j, c in enumerate(t.column('case_id').to_pylist())}
                status = t.column('status').to_pylist()
                bad = [i for i in ids if status[row[i]] != 'ok']
                if bad:
                    raise SweepError(f'pre-flight data {name}: {len(bad)} cases did not run, '
                                     f'first: {t.column("error")[row[bad[0]]]}')
                col = t.column('signal_preflight_features').combine_chunks()
                f = col.flatten().to_numpy().reshape(len(col), -1)
                feats.append(f[[row[i] for i in ids]])
            cond = np.array([case_conditions(c, p).array() for c in case_list])
            x = np.hstack([np.vstack(feats), cond])
            y = np.array([[w[n] for n in FAULT_NAMES] for w, _ in case_list])
            out_sets[name] = (x, y)
    return out_sets


def data_sets(settings: dict | None = None) -> dict:
    """The cases of the build: ``train``, ``val`` (drifted, as training), ``cal`` (drifted
    2-3-fault combinations) and ``ood`` (drifted, as training: the OOD limit)."""
    s = dict(FAULT_SETTINGS, **(settings or {}))
    pd, fl = s['degrade_probability'], bool(s['fleet'])
    return {'train': cases(s['n_train'], s['seed_train'], pd, fleet=fl),
            'val': cases(s['n_val'], s['seed_val'], pd, fleet=fl),
            'cal': combination_cases(s['n_cal'], s['seed_cal'], fleet=fl),
            'ood': cases(s['n_ood'], s['seed_ood'], pd, fleet=fl)}


def _train_member(x, y, hidden, seed, s):
    """One member: Adam on mini-batches of ``batch`` cases, ``warmup_epochs`` of mean squared
    error on the means, then ``nll_epochs`` of Gaussian negative log-likelihood; cosine
    learning-rate decay to 2 % (float32; the weights returned as float64)."""
    import torch
    torch.manual_seed(seed)
    k = y.shape[1]
    layers, d = [], x.shape[1]
    for h in hidden:
        layers += [torch.nn.Linear(d, h), torch.nn.Tanh()]
        d = h
    layers.append(torch.nn.Linear(d, 2 * k))
    net = torch.nn.Sequential(*layers).float()
    xt = torch.as_tensor(x, dtype=torch.float32)
    yt = torch.as_tensor(y, dtype=torch.float32)
    n, bs = len(xt), int(s['batch'])
    per_epoch = -(-n // bs)
    epochs = s['warmup_epochs'] + s['nll_epochs']
    opt = torch.optim.Adam(net.parameters(), lr=s['lr'], weight_decay=s['weight_decay'])
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs * per_epoch,
                                                       eta_min=s['lr'] * 0.02)
    for epoch in range(epochs):
        order = torch.randperm(n)
        for j in range(per_epoch):
            idx = order[j * bs:(j + 1) * bs]
            opt.zero_grad()
            o = net(xt[idx])
            mu, lv = o[:, :k], o[:, k:].clamp(-30, 10)
            if epoch < s['warmup_epochs']:
                loss = ((mu - yt[idx]) ** 2).mean()
            else:
                loss = (0.5 * (lv + (mu - yt[idx]) ** 2 / lv.exp())).mean()
            loss.backward()
            opt.step()
            sched.step()
    return [(m.weight.detach().double().numpy().T.copy(), m.bias.detach().double().numpy().copy())
            for m in net if isinstance(m, torch.nn.Linear)]


def _normalised(y):
    lo = np.array([f.lo for f in FAULTS])
    span = np.array([f.span for f in FAULTS])
    return (y - lo) / span


def _figures(model: FaultModel, x, y) -> dict:
    """Mean absolute error in % of each range and the fraction within 2 sigma."""
    mu, sd = model.predict_normalised(x)
    err = np.abs(mu - _normalised(y))
    return {'mean_abs_error_pct': dict(zip(FAULT_NAMES, np.round(100 * err.mean(axis=0),
                                                                 3).tolist())),
            'within_2sigma': dict(zip(FAULT_NAMES, np.round(np.mean(err <= 2 * sd, axis=0),
                                                            3).tolist()))}


def calibrate(model: FaultModel, x, y) -> np.ndarray:
    """Per fault, the factor (at least 1) on the ensemble's uncalibrated deviation that puts
    95 % of the cases ``(x, y)`` (SI targets) within 2 sigma."""
    keep = model.calibration
    model.calibration = np.ones(len(FAULTS))
    mu, sd = model.predict_normalised(x)
    model.calibration = keep
    ratio = np.abs(mu - _normalised(y)) / sd
    return np.maximum(1.0, np.quantile(ratio, 0.95, axis=0) / 2.0)


def train_faults(x, y, settings: dict | None = None, threads: int = 1) -> FaultModel:
    """Train the ensemble on inputs ``x`` (:func:`generate_sets`) and SI targets ``y``
    (uncalibrated, no OOD model yet) on ``threads`` torch threads (small batches: more
    threads than free cores slow it down many times)."""
    import torch
    torch.set_num_threads(threads)
    s = dict(FAULT_SETTINGS, **(settings or {}))
    in_mean = x.mean(axis=0)
    in_std = np.maximum(x.std(axis=0), 1e-12 + 1e-9 * np.abs(in_mean))
    z = (x - in_mean) / in_std
    members = [_train_member(z, _normalised(y), s['hidden'], seed, s)
               for seed in range(s['members'])]
    return FaultModel(in_mean, in_std, members, np.ones(len(FAULTS)),
                      {'outputs': list(FAULT_NAMES), 'hidden': list(s['hidden'])})


def recalibrate(model: FaultModel, sets: dict) -> FaultModel:
    """Calibrate on each held-out set of ``{name: (x, y)}`` on its own and keep the largest
    factor per fault: the deviations must hold on every one."""
    factors = {name: calibrate(model, x, y) for name, (x, y) in sets.items()}
    model.calibration = np.max(np.array(list(factors.values())), axis=0)
    model.meta['calibration'] = dict(zip(FAULT_NAMES, np.round(model.calibration,
                                                               3).tolist()))
    model.meta['calibration_sets'] = {name: dict(zip(FAULT_NAMES, np.round(f, 3).tolist()))
                                      for name, f in factors.items()}
    return model


def envelope_parameters(bench=None, fleet: bool = False) -> tuple:
    """Names and ``(lo, hi)`` ranges of every parameter the data is drawn over: the faults,
    the bench's nuisances, :data:`VALVE_NUISANCE` and the service conditions; ``fleet``: and
    every other nuisance of the tolerances but the dynamic frictions (a ratio of the
    breakaway friction, whose range moves with it)."""
    b, p = bench or load_bench(), default_params()
    ranges = {f.name: (f.lo, f.hi) for f in FAULTS}
    ranges.update({n: b.nuisance_range(n, p) for n in b.nuisance})
    ranges.update(VALVE_NUISANCE)
    ranges.update({n: tuple(b.service[n]) for n in CONDITIONS})
    if fleet:
        for n, t in load_tolerances().items():
            if t.klass == 'nuisance' and not t.ratio_of and n not in ranges:
                ranges[n] = t.bounds(p)
    return tuple(ranges), np.array(list(ranges.values()), dtype=float)


def envelope_targets(case_list, bench=None, fleet: bool = False) -> np.ndarray:
    """The parameters of :func:`envelope_parameters` of each case, normalised to their
    ranges."""
    b, p = bench or load_bench(), default_params()
    names, ranges = envelope_parameters(b, fleet)
    rows = [[w.get(n, getattr(p, n)) for n in names] for w, _ in case_list]
    return (np.array(rows) - ranges[:, 0]) / (ranges[:, 1] - ranges[:, 0])


def _fit_subspace(z, start: int, stop: int, variance: float) -> Subspace:
    """The principal subspace of ``z[:, start:stop]`` holding ``variance`` of its variance."""
    zz = z[:, start:stop]
    w, v = np.linalg.eigh(zz.T @ zz / len(zz))
    w, v = w[::-1], v[:, ::-1]
    k = int(np.searchsorted(np.cumsum(w) / np.sum(w), variance) + 1)
    basis = v[:, :k].T.copy()
    t = zz @ basis.T
    r2 = np.maximum(np.sum(zz ** 2, axis=1) - np.sum(t ** 2, axis=1), 0.0)
    return Subspace(start, stop, basis, np.maximum(w[:k], 1e-12), float(np.mean(r2)))


def _train_envelope_net(z, u, s: dict, threads: int = 2) -> list:
    """The :class:`~eha_ros.health.preflight.NetEnvelope` network: an MLP (``silu``) from
    the standardised inputs ``z`` to the normalised parameters ``u``, Adam on mean squared
    error with cosine decay (settings ``ood_net``); weights as float64 ``[(W, b), ...]``."""
    import torch
    torch.set_num_threads(threads)
    torch.manual_seed(int(s['seed']))
    layers, d = [], z.shape[1]
    for h in s['hidden']:
        layers += [torch.nn.Linear(d, h), torch.nn.SiLU()]
        d = h
    layers.append(torch.nn.Linear(d, u.shape[1]))
    net = torch.nn.Sequential(*layers).float()
    zt = torch.as_tensor(z, dtype=torch.float32)
    ut = torch.as_tensor(u, dtype=torch.float32)
    opt = torch.optim.Adam(net.parameters(), lr=s['lr'], weight_decay=s['weight_decay'])
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, int(s['epochs']))
    bs = int(s['batch'])
    for _ in range(int(s['epochs'])):
        order = torch.randperm(len(zt))
        for j in range(0, len(zt), bs):
            idx = order[j:j + bs]
            opt.zero_grad()
            ((net(zt[idx]) - ut[idx]) ** 2).mean().backward()
            opt.step()
        sched.step()
    return [(m.weight.detach().double().numpy().T.copy(), m.bias.detach().double().numpy().copy())
            for m in net if isinstance(m, torch.nn.Linear)]


def fit_ood(model: FaultModel, x, u, xv, uv, x_limit, settings: dict | None = None
            ) -> FaultModel:
    """The OOD model (:class:`~eha_ros.health.preflight.OodModel`) from the training inputs
    ``x`` with their normalised parameters ``u`` (:func:`envelope_targets`): per parameter
    the ridge penalty of ``ridge_lambdas`` with the smallest residual deviation on the
    validation set ``(xv, uv)``, and the 99 % quantile of its absolute error there as the
    parameter's scale; per entry ``(start, stop, variance)`` of ``ood_subspaces`` the
    principal subspace of those training input columns holding that fraction of their
    variance.  Each test's limit: the ``ood_quantile`` of its scores on the held-out inputs
    ``x_limit`` times ``ood_margin``; the subspace scores are scaled to the envelope's."""
    s = dict(FAULT_SETTINGS, **(settings or {}))
    names, _ = envelope_parameters(fleet=bool(s['fleet']))
    z, zv = model.standardise(x), model.standardise(xv)
    u_mean = u.mean(axis=0)
    left, sv, vt = np.linalg.svd(z, full_matrices=False)
    proj = left.T @ (u - u_mean)
    best_w = np.zeros((z.shape[1], u.shape[1]))
    sigmas = np.full(u.shape[1], np.inf)
    lambdas = np.zeros(u.shape[1])
    for lam in s['ridge_lambdas']:
        w = vt.T @ ((sv / (sv ** 2 + lam))[:, None] * proj)
        sd = np.std(zv @ w + u_mean - uv, axis=0)
        better = sd < sigmas
        best_w[:, better], sigmas[better], lambdas[better] = w[:, better], sd[better], lam
    scales = np.quantile(np.abs(zv @ best_w + u_mean - uv), 0.99, axis=0)
    ood = OodModel(np.vstack([best_w, u_mean]), scales, [], np.inf)
    zl = model.standardise(x_limit)
    env = ood.envelope(zl)
    ood.limit = float(np.quantile(env, s['ood_quantile']) * s['ood_margin'])
    tests = []
    for start, stop, var in s['ood_subspaces']:
        t = _fit_subspace(z, int(start), int(stop), var)
        t.scale = ood.limit / float(np.quantile(t.score(zl), s['ood_quantile'])
                                    * s['ood_margin'])
        ood.subspaces.append(t)
        tests.append({'columns': [t.start, t.stop], 'explained_variance': var,
                      'components': int(len(t.variances)), 'residual_ms': t.residual_ms,
                      'scale': t.scale})
    net_meta = None
    if s.get('ood_net'):   # the same envelope, estimated by a network
        weights = _train_envelope_net(z, u, s['ood_net'])
        res = mlp_forward(weights, zv, 'silu') - uv
        ood.net = NetEnvelope(weights, np.quantile(np.abs(res), 0.99, axis=0))
        ood.net.scale = ood.limit / float(np.quantile(ood.net.score(zl), s['ood_quantile'])
                                          * s['ood_margin'])
        net_meta = dict(s['ood_net'], activation='silu', scale=ood.net.scale,
                        sigma=dict(zip(names, np.round(np.std(res, axis=0), 4).tolist())))
    model.ood = ood
    held = ood.score(zl)
    model.meta['ood'] = {
        'parameters': list(names), 'ridge_lambda': dict(zip(names, lambdas.tolist())),
        'sigma': dict(zip(names, np.round(sigmas, 4).tolist())),
        'scale': dict(zip(names, np.round(scales, 4).tolist())),
        'subspaces': tests, 'limit': ood.limit, 'quantile': s['ood_quantile'],
        'margin': s['ood_margin'], 'limit_cases': int(len(x_limit)),
        'held_out_score_quantiles': {str(q): round(float(np.quantile(held, q)), 3)
                                     for q in (0.5, 0.9, 0.99, 0.995, 1.0)},
        'held_out_flagged': round(float(np.mean(held > ood.limit)), 4)}
    if net_meta:
        model.meta['ood']['net'] = net_meta
    return model


def _envelope(settings: dict) -> dict:
    """What the data was drawn over (for the artefact's ``meta``)."""
    b, p = load_bench(), default_params()
    return {'faults': {f.name: [f.lo, f.hi] for f in FAULTS},
            'nuisance': {n: list(b.nuisance_range(n, p)) for n in b.nuisance},
            'valve_nuisance': {n: list(r) for n, r in VALVE_NUISANCE.items()},
            'service': {n: list(b.service[n]) for n in b.service},
            'degrade_probability': settings['degrade_probability'],
            'friction_ratio': FRICTION_RATIO if not settings['fleet'] else
            {n: [t.lo, t.hi] for n, t in load_tolerances().items() if t.ratio_of},
            'fleet': ([n for n, t in load_tolerances().items() if t.klass == 'nuisance']
                      if settings['fleet'] else [])}


def build_artefact(out: Path | None = None, settings: dict | None = None, workers: int = 2,
                   progress=print, data: Path | None = None) -> FaultModel:
    """Generate the data (``data``: keep the sweeps there, resumed if present), train,
    calibrate, fit the OOD model, save ``models/faults.npz``."""
    s = dict(FAULT_SETTINGS, **(settings or {}))
    p = default_params()
    t0 = time.perf_counter()
    sets = data_sets(s)
    stats = {}
    d = generate_sets(sets, p, workers, progress, data, stats)
    t_data = time.perf_counter() - t0
    x, y = d['train']
    model = train_faults(x, y, s)
    t_train = time.perf_counter() - t0 - t_data
    env = _envelope(s)
    model.meta.update(
        inputs=f'preflight_features ({x.shape[1] - 3}) + measured conditions '
               f'(mean of {CONDITION_READINGS} bench readings)',
        conditions=['supply_pressure_pa', 'return_pressure_pa', 'fluid_temperature_k'],
        condition_readings=CONDITION_READINGS, settings=s,
        sizes={k: int(len(v[0])) for k, v in d.items()},
        streams={k: s[f'seed_{k}'] for k in ('train', 'val', 'cal', 'ood')},
        ranges=env['faults'], **{k: v for k, v in env.items() if k != 'faults'})
    recalibrate(model, {'val': d['val'], 'cal': d['cal']})
    fl = bool(s['fleet'])
    fit_ood(model, x, envelope_targets(sets['train'], fleet=fl), d['val'][0],
            envelope_targets(sets['val'], fleet=fl), d['ood'][0], s)
    model.meta['held_out'] = {k: _figures(model, *d[k]) for k in ('val', 'cal', 'ood')}
    model.meta['held_out']['ood']['note'] = 'the OOD-limit stream: calibration never saw it'
    model.meta['data_s'] = round(t_data, 1)   # running the sweeps, or reading them (--data)
    model.meta['checks_worker_s'] = round(stats.get('worker_s', 0.0), 1)
    model.meta['train_s'] = round(t_train, 1)
    model.meta['fluid_hash'] = fluid_hash(p)
    out = Path(out) if out is not None else models_dir('health') / FAULTS_FILE
    save_artefact(out, model.data(), model.meta)
    progress(f'{out}: held-out (ood stream) error % of range '
             f'{model.meta["held_out"]["ood"]["mean_abs_error_pct"]}, within 2 sigma '
             f'{model.meta["held_out"]["ood"]["within_2sigma"]}, OOD limit '
             f'{model.ood.limit:.3g}')
    return model


def refit_ood(data: Path | None = None, out: Path | None = None, settings: dict | None = None,
              workers: int = 2, progress=print) -> FaultModel:
    """Fit the OOD model of the shipped network again, on the data of its build (``data``:
    the build's sweeps, read where present; the rest run), and save it with the members and
    the calibration unchanged.  Refused when the network was built with other settings than
    these (:data:`OOD_SETTINGS` may differ)."""
    import copy
    s = dict(FAULT_SETTINGS, **(settings or {}))
    model = copy.copy(load_faults())
    model.meta = copy.deepcopy(model.meta)
    built = model.meta.get('settings', {})
    other = sorted(k for k in set(s) | set(built) if k not in OOD_SETTINGS
                   and built.get(k) != s.get(k))
    if other:
        raise ValueError(f'pre-flight OOD refit: the shipped network was built with other '
                         f'settings ({", ".join(other)}): rebuild it whole')
    p = default_params()
    sets = data_sets(s)
    d = generate_sets(sets, p, workers, progress, data)
    fl = bool(s['fleet'])
    fit_ood(model, d['train'][0], envelope_targets(sets['train'], fleet=fl), d['val'][0],
            envelope_targets(sets['val'], fleet=fl), d['ood'][0], s)
    model.meta['settings'] = s
    out = Path(out) if out is not None else models_dir('health') / FAULTS_FILE
    save_artefact(out, model.data(), model.meta)
    progress(f'{out}: OOD model refitted, limit {model.ood.limit:.3g}, held-out flagged '
             f'{model.meta["ood"]["held_out_flagged"]}')
    return model


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog='python -m eha_ros.training.preflight',
                                 description='pre-flight data and fault network')
    ap.add_argument('--workers', type=int, default=2, help='sweep workers (1: in process)')
    ap.add_argument('--data', type=Path, default=None,
                    help='keep the data sweeps here (resumed if they hold some of it)')
    ap.add_argument('--ood-only', action='store_true',
                    help='fit only the OOD model of the shipped network again (on --data)')
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error(f'--workers {args.workers} must be at least 1')
    if args.ood_only:
        try:
            refit_ood(args.data, workers=args.workers)
        except ValueError as exc:
            print(f'error: {exc}', file=sys.stderr)
            return 2
        return 0
    build_artefact(workers=args.workers, data=args.data)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
