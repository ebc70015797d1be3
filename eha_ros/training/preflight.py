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

Build: ``nice python -m eha_ros.training.preflight`` (data about 4 min on 2 cores, training a
few minutes) writes ``faults.npz``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.health.preflight import (_BY_NAME, FAULT_NAMES, FAULTS, FAULTS_FILE, FaultModel,
                                      preflight_features)
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import fluid_hash
from eha_ros.physics.params import replace

__all__ = ['FAULT_SETTINGS', 'draw_wear', 'apply_wear', 'cases', 'combination_cases',
           'generate', 'train_faults', 'calibrate', 'recalibrate', 'build_artefact']

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
    w = dict(wear)
    if 'overlap_supply_m' in w:
        w['overlap_return_m'] = w['overlap_supply_m']
    for part in ('spool', 'jack'):
        key = f'{part}_static_friction_n'
        if key in w:
            w[f'{part}_dynamic_friction_n'] = FRICTION_RATIO * w[key]
    return replace(params, **w)


def _one_case(args):
    from eha_ros.physics.maintenance import run_preflight
    params, wear, seed = args
    return preflight_features(run_preflight(apply_wear(params, wear), seed=seed))


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


def generate(case_list, params: PlantParams | None = None, workers: int = 2,
             progress=None) -> tuple[np.ndarray, np.ndarray]:
    """Features ``(n, 770)`` and targets ``(n, len(FAULTS))`` of the pre-flight check on the
    high-fidelity plant for ``case_list`` (from :func:`cases`)."""
    p = params if params is not None else default_params()
    jobs = [(p, w, s) for w, s in case_list]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        first = _one_case(jobs[0])  # compile here once, not in every worker
        with mp.get_context('fork').Pool(workers) as pool:
            feats = [first]
            for k, f in enumerate(pool.imap(_one_case, jobs[1:], chunksize=8), start=1):
                feats.append(f)
                if progress and (k + 1) % 200 == 0:
                    progress(f'{k + 1}/{len(jobs)} cases')
    else:
        feats = [_one_case(j) for j in jobs]
    y = np.array([[w[name] for name in FAULT_NAMES] for w, _ in case_list])
    return np.array(feats), y


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


def build_artefact(out: Path | None = None, settings: dict | None = None, workers: int = 2,
                   progress=print) -> FaultModel:
    """Generate the data, train, save ``models/faults.npz``."""
    s = dict(FAULT_SETTINGS, **(settings or {}))
    p = default_params()
    t0 = time.perf_counter()
    x, y = generate(cases(s['n_train'], s['seed_train'], s['degrade_probability']), p,
                    workers, progress)
    xv, yv = generate(cases(s['n_val'], s['seed_val'], s['degrade_probability']), p,
                      workers, progress)
    t_data = time.perf_counter() - t0
    model = train_faults(x, y, xv, yv, s, threads=workers)
    recalibrate(model, xv, yv, *generate(combination_cases(s['n_cal'], s['seed_cal']), p,
                                         workers, progress))
    model.meta['data_s'] = round(t_data, 1)
    model.meta['train_s'] = round(time.perf_counter() - t0 - t_data, 1)
    model.meta['fluid_hash'] = fluid_hash(p)
    out = Path(out) if out is not None else models_dir('health') / FAULTS_FILE
    save_artefact(out, model.data(), model.meta)
    progress(f'{out}: validation error % of range '
             f'{model.meta["validation_mean_abs_error_pct"]}, within 2 sigma '
             f'{model.meta["validation_within_2sigma"]}')
    return model


if __name__ == '__main__':
    build_artefact()
