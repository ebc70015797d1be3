"""Accuracy and speed of the neural-network surrogates (``nn``: 4 inputs, ``nn2``: 2 inputs)
and of the diagnostic network (``diag``), from the shipped artefacts.

Accuracy, on maps held out of training (whole wear pairs) and on freshly generated maps:
    nn, nn2   relative error in Euclidean norm of each map, ``||P_pred - P_true|| / ||P_true||``
              (map = all XS x Q of one wear pair), mean and max;
    diag      error per parameter in % of its range (WEAR_RANGES), clean and with 1 % Gaussian
              noise on the pressures, per curve and per map (median of the map's curves).
Speed: scalar kernel call as the plant makes it (from an njit loop over 1e6 varied inputs), a
Python-level scalar call, batch throughput.  Training: times and the LM vs Adam + L-BFGS
comparison recorded in the artefacts; scikit-learn's ``MLPRegressor`` (same hidden sizes)
trained here on the same split for comparison.

    python bench/surrogates_nn.py [--sklearn-iter 200] [--no-sklearn] [--smoke]

``--smoke`` runs the same code on tiny sets (2 fresh maps, 2,000 calls, 2 scikit-learn
iterations): a check that the bench runs, no figure.
"""

import argparse
import json
import math
import time

import numpy as np

from eha_ros.physics import default_params
from eha_ros.health import valve_test
from eha_ros.surrogates import nn
from eha_ros.training import nn as nn_train
from eha_ros.training import valve_test as valve_test_training
from eha_ros.training.database import heldout_maps
from eha_ros.surrogates.base import relative_error
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.training.database import get_database


#: Sizes of a ``--smoke`` run; the full bench's are the defaults of the functions.
SMOKE = {'calls': 2000, 'maps': 2, 'sklearn_iter': 2}


def _summary(errs):
    errs = np.asarray(errs)
    return {'mean_pct': round(float(errs.mean()) * 100, 4),
            'max_pct': round(float(errs.max()) * 100, 4), 'n_maps': int(errs.size)}


def _timing(s, n=1_000_000, seed=0):
    """Per-call time [us] of the kernel from an njit loop, of a Python scalar call, and the
    batch throughput [points/s] of ``p12`` on arrays."""
    p = default_params()
    rng = np.random.default_rng(seed)
    xs = rng.uniform(-p.spool_stroke_m, p.spool_stroke_m, n)
    q = rng.uniform(-6e-5, 6e-5, n)
    lap = rng.uniform(-2e-6, 6e-6, n)
    clr = rng.uniform(1e-6, 6e-6, n)
    nn._kernel_loop(s.kernel, s.data, xs[:10], q[:10], lap[:10], clr[:10])  # compile
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        nn._kernel_loop(s.kernel, s.data, xs, q, lap, clr)
        best = min(best, time.perf_counter() - t0)
    m = min(20000, n)
    s.p12(0.0, 0.0, 0.0, 3e-6)
    t0 = time.perf_counter()
    for i in range(m):
        s.p12(float(xs[i]), float(q[i]), float(lap[i]), float(clr[i]))
    py = (time.perf_counter() - t0) / m
    s.p12(xs[:10], q[:10], lap[:10], clr[:10])
    bt = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        s.p12(xs, q, lap, clr)
        bt = min(bt, time.perf_counter() - t0)
    return {'kernel_njit_loop_us': round(best / n * 1e6, 4),
            'python_scalar_call_us': round(py * 1e6, 2),
            'batch_points_per_s': round(n / bt)}


def _nn_accuracy(s, n_maps=12):
    """Held-out DB maps (the split in the artefact) and fresh maps at random wear."""
    meta = s.meta
    out = {}
    if meta['architecture']['d_in'] == 4:
        test = [tuple(t) for t in meta['training']['split']['test_pairs']]
        for name in meta['training']['databases']:
            db = get_database(name)
            out[f'{name}_held_out'] = _summary(
                nn_train.network_map_errors(s.data, nn_train.db_maps(db, test)))
        for q_max in (6e-5, 1.5e-5):
            maps = heldout_maps(n_maps, q_max_m3_s=q_max, n_q=15, seed=4242)
            out[f'fresh_random_wear_q{q_max:.1e}'] = _summary(
                nn_train.network_map_errors(s.data, maps))
    else:
        db = get_database('DB5')
        cols = np.array(meta['training']['split']['test_flows'])
        out['DB5_held_out_flows'] = _summary(nn_train.network_map_errors(s.data, [
            (db.xs_m, db.q_m3_s[cols], db.overlap_m[0], db.clearance_m[0],
             db.p12_pa[:, cols, 0, 0])]))
        # a fresh nominal map at flows between the database's
        from eha_ros.physics.maps import transient_map
        q_mid = 0.5 * (db.q_m3_s[1:] + db.q_m3_s[:-1])[::4]
        fresh = transient_map(db.xs_m[:, None], q_mid[None, :])['p12_pa']
        out['fresh_flows_between_grid'] = _summary(nn_train.network_map_errors(s.data, [
            (db.xs_m, q_mid, db.overlap_m[0], db.clearance_m[0], fresh)]))
    return out


def _sklearn(meta, max_iter, seed=0):
    """scikit-learn MLPRegressor (same hidden sizes, tanh, adam) on the 4-input split."""
    from sklearn.neural_network import MLPRegressor
    tr = meta['training']
    test = [tuple(t) for t in tr['split']['test_pairs']]
    val = [tuple(t) for t in tr['split']['val_pairs']]
    dbs = {name: get_database(name) for name in tr['databases']}
    first = next(iter(dbs.values()))
    train = [(i, j) for i in range(first.overlap_m.size) for j in range(first.clearance_m.size)
             if (i, j) not in set(test) | set(val)]
    raw, y = zip(*(nn_train._points(db, train) for db in dbs.values()))
    raw, y = np.concatenate(raw), np.concatenate(y)
    inputs = nn.fit_inputs(raw, [0, 1, 2, 3], ['linear'] * 4)
    output = nn.fit_output(y)
    reg = MLPRegressor(hidden_layer_sizes=tuple(meta['architecture']['d_hidden']),
                       activation='tanh', solver='adam', max_iter=max_iter, batch_size=512,
                       learning_rate_init=1e-3, tol=1e-7, n_iter_no_change=20,
                       random_state=seed)
    t0 = time.perf_counter()
    reg.fit(nn.transform_inputs(inputs, raw), (y - output[0]) / output[1])
    wall = time.perf_counter() - t0
    errs = {}
    for name, db in dbs.items():
        e = []
        for xs, q, lap, clr, p12 in nn_train.db_maps(db, test):
            g = np.stack([a.ravel() for a in np.broadcast_arrays(
                xs[:, None], q[None, :], lap, clr)], axis=1)
            pred = output[0] + output[1] * reg.predict(nn.transform_inputs(inputs, g))
            e.append(relative_error(pred, p12.ravel()))
        errs[f'{name}_held_out'] = _summary(e)
    return {'train_time_s': round(wall, 1), 'iterations': int(reg.n_iter_),
            'max_iter': max_iter, 'errors': errs}


def _diag(seed=0, n_maps=20, n_calls=2000):
    m = valve_test.load_diagnostic()
    keys = ('algorithm', 'time_s', 'adam_steps', 'lbfgs_iters', 'noise_augmentation')
    out = {'architecture': m.meta['architecture'],
           'training': {k: m.meta['training'][k] for k in keys},
           'held_out_recorded': m.meta['errors'], 'alternatives': m.meta.get('alternatives')}
    maps = heldout_maps(n_maps, q_max_m3_s=6e-5, n_q=15, seed=9090)
    curves = np.concatenate([p12.T for *_, p12 in maps])
    q = np.concatenate([mq for _, mq, *_ in maps])
    wear = np.concatenate([np.tile([clr, lap], (mq.size, 1)) for _, mq, lap, clr, _ in maps])
    idx = np.repeat(np.arange(len(maps)), maps[0][1].size)
    out['fresh_random_wear'] = {
        'clean': valve_test_training.wear_errors(m, curves, q, wear, idx),
        'noise_1pct': valve_test_training.wear_errors(m, curves, q, wear, idx, noise_level=0.01,
                                                      seed=seed),
        'noise_1pct_rms': valve_test_training.wear_errors(
            m, curves, q, wear, idx, noise_level=0.01, noise='rms', seed=seed)}
    one = curves[0]
    valve_test.estimate_wear(one, q[0])
    n = n_calls
    t0 = time.perf_counter()
    for _ in range(n):
        valve_test.estimate_wear(one, q[0])
    t_one = (time.perf_counter() - t0) / n
    big = np.tile(curves, (50, 1))
    qb = np.tile(q, 50)
    t0 = time.perf_counter()
    valve_test.estimate_wear_batch(big, qb)
    out['speed'] = {'estimate_wear_call_us': round(t_one * 1e6, 1),
                    'batch_curves_per_s': round(big.shape[0] / (time.perf_counter() - t0))}
    return out


def run(sklearn_iter: int = 200, with_sklearn: bool = True, smoke: bool = False) -> dict:
    """All figures as one dict (see the module docstring); ``smoke``: the sizes of
    :data:`SMOKE`."""
    res = {'smoke': smoke}
    if smoke:
        sklearn_iter = SMOKE['sklearn_iter']
    sizes = ({'n_maps': SMOKE['maps']}, {'n': SMOKE['calls']}) if smoke else ({}, {})
    for name in ('nn', 'nn2'):
        s = load_surrogate(name)
        meta = s.meta
        r = {'architecture': meta['architecture'],
             'inputs': [(i['name'], i['transform']) for i in meta['inputs']],
             'training': {k: meta['training'][k] for k in ('algorithm', 'time_s', 'epochs',
                                                           'stop', 'databases')},
             'lm_vs_adam_lbfgs': meta['comparison'],
             'accuracy': _nn_accuracy(s, **sizes[0]), 'speed': _timing(s, **sizes[1])}
        if 'alternatives' in meta:
            r['alternatives'] = meta['alternatives']
        if name == 'nn' and with_sklearn:
            r['sklearn_mlpregressor'] = _sklearn(meta, sklearn_iter)
        res[name] = r
    res['diag'] = _diag(**({'n_maps': SMOKE['maps'], 'n_calls': 20} if smoke else {}))
    return res


if __name__ == '__main__':
    ap = argparse.ArgumentParser()
    ap.add_argument('--sklearn-iter', type=int, default=200)
    ap.add_argument('--no-sklearn', action='store_true')
    ap.add_argument('--smoke', action='store_true',
                    help='the same code on tiny sets: a check, no figure')
    a = ap.parse_args()
    print(json.dumps({'benchmark': 'surrogates_nn',
                      **run(a.sklearn_iter, not a.no_sklearn, a.smoke)}))
