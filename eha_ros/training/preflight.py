"""Generate the pre-flight data and train the pre-flight network
(:mod:`eha_ros.health.preflight`); write ``faults.npz``.

Data (:func:`generate`)
    The pre-flight check on the high-fidelity plant (:func:`eha_ros.physics.maintenance.
    run_preflight`, 1 us step) at wear points drawn independently per case from a seeded
    stream: half with every parameter uniform over its range, half with each degraded with
    probability 0.3 and nominal otherwise (so the nominal valve is well covered); the torque
    motor's noise seed drawn too.  Dynamic frictions follow their breakaway values at the
    nominal ratio.  Training, validation and the benchmark's test cases come from different
    streams.

The 3,000 checks run as a sweep (:mod:`eha_ros.sweep`, one single-threaded worker process per
core).  Build: ``nice python -m eha_ros.training.preflight`` (data about 4 min on 2 cores,
training a few minutes) writes ``faults.npz``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.health.preflight import (_BY_NAME, FAULT_NAMES, FAULTS, FAULTS_FILE,
                                      FaultModel)
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import fluid_hash
from eha_ros.physics.params import replace

__all__ = ['FAULT_SETTINGS', 'draw_wear', 'apply_wear', 'wear_changes', 'cases',
           'combination_cases', 'data_sets', 'generate', 'generate_sets', 'train_faults',
           'calibrate', 'recalibrate', 'build_artefact']

#: Dynamic friction over breakaway friction for the drawn cases (the parameters' nominal).
FRICTION_RATIO = 0.5


FAULT_SETTINGS = {
    'n_train': 2400, 'n_val': 400, 'seed_train': 11, 'seed_val': 12, 'members': 4,
    'n_cal': 200, 'seed_cal': 13,
    'hidden': [128, 64], 'warmup_steps': 1500, 'nll_steps': 2500, 'lr': 2e-3,
    'weight_decay': 1e-4, 'degrade_probability': 0.3,
}


def draw_wear(rng: np.random.Generator, sparse: bool, p_degrade: float = 0.3) -> dict:
    """Plant parameters of one case: every fault uniform over its range, or (``sparse``) each
    degraded with probability ``p_degrade`` and nominal otherwise."""
    out = {}
    for f in FAULTS:
        u = rng.uniform(f.lo, f.hi)
        flip = rng.uniform() < p_degrade
        out[f.name] = float(u if (not sparse or flip) else f.nominal)
    return out


def apply_wear(params: PlantParams, wear: dict) -> PlantParams:
    """``params`` with the faults of ``wear`` (names of :data:`FAULTS`; frictions set their
    dynamic values at :data:`FRICTION_RATIO`, the overlap both edges)."""
    return replace(params, **wear_changes(wear))


def cases(n: int, stream: int, p_degrade: float = 0.3):
    """``n`` (wear, noise seed) cases of stream ``stream``: case ``i`` from its own generator
    ``default_rng([stream, i])``, sparse for odd ``i``."""
    out = []
    for i in range(n):
        rng = np.random.default_rng([stream, i])
        wear = draw_wear(rng, sparse=bool(i % 2), p_degrade=p_degrade)
        out.append((wear, int(rng.integers(0, 2 ** 31 - 1))))
    return out


def combination_cases(n: int, stream: int):
    """``n`` cases as maintenance finds them: two or three of the five faults (alternately)
    uniform over their ranges, the others nominal, clearance and overlap uniform; case ``i``
    from ``default_rng([stream, i])``."""
    out = []
    for i in range(n):
        rng = np.random.default_rng([stream, i])
        wear = {f.name: f.nominal for f in FAULTS}
        for name in ('radial_clearance_m', 'overlap_supply_m'):
            f = _BY_NAME[name]
            wear[name] = float(rng.uniform(f.lo, f.hi))
        for j in rng.choice(5, size=2 + i % 2, replace=False):
            f = FAULTS[j]
            wear[f.name] = float(rng.uniform(f.lo, f.hi))
        out.append((wear, int(rng.integers(0, 2 ** 31 - 1))))
    return out


def wear_changes(wear: dict) -> dict:
    """The plant parameters :func:`apply_wear` sets for ``wear`` (names and values)."""
    w = dict(wear)
    if 'overlap_supply_m' in w:
        w['overlap_return_m'] = w['overlap_supply_m']
    for part in ('spool', 'jack'):
        key = f'{part}_static_friction_n'
        if key in w:
            w[f'{part}_dynamic_friction_n'] = FRICTION_RATIO * w[key]
    return w


def generate(case_list, params: PlantParams | None = None, workers: int = 2,
             progress=None, out=None) -> tuple[np.ndarray, np.ndarray]:
    """Features ``(n, 770)`` and targets ``(n, len(FAULTS))`` of the pre-flight check on the
    high-fidelity plant for ``case_list`` (from :func:`cases`); see :func:`generate_sets`."""
    return generate_sets({'cases': case_list}, params, workers, progress, out)['cases']


def generate_sets(sets: dict, params: PlantParams | None = None, workers: int = 2,
                  progress=None, out=None) -> dict:
    """``{name: (features, targets)}`` for ``{name: case_list}``: every case of every set run
    as one sweep (:mod:`eha_ros.sweep`: ``workers`` single-threaded processes, in this
    process for one; one cluster, each worker compiling the plant once).  ``out``: the
    sweep's dataset folder, kept and resumed if it holds these cases; a temporary one
    otherwise.  ``progress``: show the sweep's progress bar."""
    import tempfile

    from eha_ros.physics import params_to_dict
    from eha_ros.sweep import SweepError, parse_spec, read_dataset, run_sweep
    p = params if params is not None else default_params()
    every = [c for case_list in sets.values() for c in case_list]
    raw = {'procedure': 'preflight_check', 'models': ['hf'], 'noise': True, 'metrics': [],
           'signals': ['preflight_features'],
           'cases': [{**wear_changes(w), 'seed': int(seed)} for w, seed in every]}
    spec = parse_spec(raw, source='pre-flight data', base=params_to_dict(p))
    ids = [pt.cases[0].case_id for pt in spec.points()]
    with tempfile.TemporaryDirectory(prefix='eha-preflight-') as tmp:
        folder = Path(out) if out is not None else Path(tmp) / 'sweep'
        resume = folder.is_dir() and any(folder.iterdir())
        run_sweep(spec, folder, workers=workers, in_process=workers <= 1, resume=resume,
                  progress=bool(progress))
        t = read_dataset(folder).select(['case_id', 'status', 'error',
                                         'signal_preflight_features'])
    row = {c: k for k, c in enumerate(t.column('case_id').to_pylist())}
    status = t.column('status').to_pylist()
    bad = [i for i in ids if status[row[i]] != 'ok']
    if bad:
        raise SweepError(f'pre-flight data: {len(bad)} cases did not run, first: '
                         f'{t.column("error")[row[bad[0]]]}')
    col = t.column('signal_preflight_features').combine_chunks()
    feats = col.flatten().to_numpy().reshape(len(col), -1)
    x = feats[[row[i] for i in ids]]
    out_sets, k = {}, 0
    for name, case_list in sets.items():
        y = np.array([[w[n] for n in FAULT_NAMES] for w, _ in case_list])
        out_sets[name] = (x[k:k + len(case_list)], y)
        k += len(case_list)
    return out_sets


def _train_member(x, y, xv, yv, hidden, seed, s):
    import torch
    torch.manual_seed(seed)
    k = y.shape[1]
    layers, d = [], x.shape[1]
    for h in hidden:
        layers += [torch.nn.Linear(d, h), torch.nn.Tanh()]
        d = h
    layers.append(torch.nn.Linear(d, 2 * k))
    net = torch.nn.Sequential(*layers).double()
    xt, yt = torch.as_tensor(x), torch.as_tensor(y)
    opt = torch.optim.Adam(net.parameters(), lr=s['lr'], weight_decay=s['weight_decay'])
    steps = s['warmup_steps'] + s['nll_steps']
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=s['lr'] * 0.02)
    for step in range(steps):
        opt.zero_grad()
        o = net(xt)
        mu, lv = o[:, :k], o[:, k:].clamp(-30, 10)
        if step < s['warmup_steps']:
            loss = ((mu - yt) ** 2).mean()
        else:
            loss = (0.5 * (lv + (mu - yt) ** 2 / lv.exp())).mean()
        loss.backward()
        opt.step()
        sched.step()
    out = []
    for m in net:
        if isinstance(m, torch.nn.Linear):
            out.append((m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy()))
    return out


def calibrate(model: FaultModel, x, y) -> FaultModel:
    """Per parameter, the factor (at least 1) on the ensemble's deviation that puts 95 % of
    the cases ``(x, y)`` (SI targets) within 2 sigma; stored in ``model.calibration``."""
    lo = np.array([f.lo for f in FAULTS])
    span = np.array([f.span for f in FAULTS])
    model.calibration = np.ones(len(FAULTS))
    mu, sd = model.predict_normalised(x)
    ratio = np.abs(mu - (y - lo) / span) / sd
    model.calibration = np.maximum(1.0, np.quantile(ratio, 0.95, axis=0) / 2.0)
    return model


def train_faults(x, y, xv, yv, settings: dict | None = None, threads: int = 2) -> FaultModel:
    """Train the ensemble on ``(x, y)`` and calibrate its deviations on ``(xv, yv)``
    (targets in SI, as :func:`generate` returns them)."""
    import torch
    torch.set_num_threads(threads)
    s = dict(FAULT_SETTINGS, **(settings or {}))
    lo = np.array([f.lo for f in FAULTS])
    span = np.array([f.span for f in FAULTS])
    in_mean = x.mean(axis=0)
    in_std = np.maximum(x.std(axis=0), 1e-12 + 1e-9 * np.abs(in_mean))
    z, zv = (x - in_mean) / in_std, (xv - in_mean) / in_std
    u, uv = (y - lo) / span, (yv - lo) / span
    members = [_train_member(z, u, zv, uv, s['hidden'], seed, s)
               for seed in range(s['members'])]
    model = calibrate(FaultModel(in_mean, in_std, members, np.ones(len(FAULTS)), {}), xv, yv)
    mu, sd = model.predict_normalised(xv)
    model.meta = {'outputs': list(FAULT_NAMES), 'hidden': list(s['hidden']),
                  'settings': s,
                  'validation_mean_abs_error_pct': dict(zip(
                      FAULT_NAMES, np.round(100 * np.mean(np.abs(mu - uv), axis=0), 3).tolist())),
                  'validation_within_2sigma': dict(zip(
                      FAULT_NAMES, np.round(np.mean(np.abs(mu - uv) <= 2 * sd, axis=0),
                                            3).tolist())),
                  'calibration': dict(zip(FAULT_NAMES, np.round(model.calibration,
                                                                3).tolist())),
                  'ranges': {f.name: [f.lo, f.hi] for f in FAULTS}}
    return model


def recalibrate(model: FaultModel, xv, yv, xc, yc) -> FaultModel:
    """Calibrate on the validation cases and on ``n_cal`` combination cases
    (:func:`combination_cases`, stream ``seed_cal``), each on its own, and keep the larger
    factor: the deviations must hold both on the training distribution and on the 2-3-fault
    combinations maintenance meets."""
    c_val = calibrate(model, xv, yv).calibration
    c_comb = calibrate(model, xc, yc).calibration
    model.calibration = np.maximum(c_val, c_comb)
    lo = np.array([f.lo for f in FAULTS])
    span = np.array([f.span for f in FAULTS])
    mu, sd = model.predict_normalised(xc)
    u = (yc - lo) / span
    model.meta['calibration'] = dict(zip(FAULT_NAMES, np.round(model.calibration, 3).tolist()))
    model.meta['calibration_set'] = {'cases': int(len(xc)) + int(len(xv)),
                                     'combination_cases': int(len(xc))}
    model.meta['combination_within_2sigma'] = dict(zip(
        FAULT_NAMES, np.round(np.mean(np.abs(mu - u) <= 2 * sd, axis=0), 3).tolist()))
    mu, sd = model.predict_normalised(xv)
    model.meta['validation_within_2sigma'] = dict(zip(
        FAULT_NAMES, np.round(np.mean(np.abs(mu - (yv - lo) / span) <= 2 * sd, axis=0),
                              3).tolist()))
    return model


def data_sets(settings: dict | None = None) -> dict:
    """The training, validation and calibration cases (``{'train', 'val', 'cal'}``)."""
    s = dict(FAULT_SETTINGS, **(settings or {}))
    return {'train': cases(s['n_train'], s['seed_train'], s['degrade_probability']),
            'val': cases(s['n_val'], s['seed_val'], s['degrade_probability']),
            'cal': combination_cases(s['n_cal'], s['seed_cal'])}


def build_artefact(out: Path | None = None, settings: dict | None = None, workers: int = 2,
                   progress=print, data: Path | None = None) -> FaultModel:
    """Generate the data (one sweep; ``data``: keep its dataset there, resumed if present),
    train, save ``models/faults.npz``."""
    s = dict(FAULT_SETTINGS, **(settings or {}))
    p = default_params()
    t0 = time.perf_counter()
    d = generate_sets(data_sets(s), p, workers, progress, data)
    (x, y), (xv, yv), (xc, yc) = d['train'], d['val'], d['cal']
    t_data = time.perf_counter() - t0
    model = train_faults(x, y, xv, yv, s, threads=workers)
    recalibrate(model, xv, yv, xc, yc)
    model.meta['data_s'] = round(t_data, 1)
    model.meta['train_s'] = round(time.perf_counter() - t0 - t_data, 1)
    model.meta['fluid_hash'] = fluid_hash(p)
    out = Path(out) if out is not None else models_dir('health') / FAULTS_FILE
    save_artefact(out, model.data(), model.meta)
    progress(f'{out}: validation error % of range '
             f'{model.meta["validation_mean_abs_error_pct"]}, within 2 sigma '
             f'{model.meta["validation_within_2sigma"]}')
    return model


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog='python -m eha_ros.training.preflight',
                                 description='pre-flight data and fault network')
    ap.add_argument('--workers', type=int, default=2, help='sweep workers (1: in process)')
    ap.add_argument('--data', type=Path, default=None,
                    help='keep the data sweep here (resumed if it holds some of it)')
    args = ap.parse_args(argv)
    build_artefact(workers=args.workers, data=args.data)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
