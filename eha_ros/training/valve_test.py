"""Train the valve-test network (:mod:`eha_ros.health.valve_test`) and write ``diag.npz``.

Training (torch, imported inside the training functions)
    On DB4 (900 maps x 15 flows), whole maps held out: every curve of a held-out
    ``(overlap, clearance)`` pair is out of training (90 test and 45 validation pairs from the
    interior of the wear grid).  Noise augmentation: two noisy copies of every training curve
    with the noise model below (validation on clean and noisy curves).

Noise model
    ``P_noisy = P (1 + 0.01 n)``, ``n`` standard normal, independent per point: 1 % of each
    pressure's magnitude (``noise='relative'``, the default).  ``noise='rms'`` instead adds 1 %
    of the curve's RMS to every point (harsher near null, where P12 is small).

Errors are reported in % of each parameter's range (:data:`WEAR_RANGES`).

Build: ``python -m eha_ros.training.valve_test`` (:func:`build_artefact`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.health.valve_test import (OUTPUT_NAMES, OUTPUT_UNITS, DiagnosticModel,
                                       canonical_curves, read_diagnostic)
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import WEAR_RANGES, fluid_hash
from eha_ros.training.database import Database, get_database
from eha_ros.training.networks import Split, fit_network, history_stops, map_split, minmax

__all__ = ['DIAG_SETTINGS', 'DIAG_THESIS_SETTINGS', 'add_noise', 'curves_from_maps',
           'wear_errors', 'train_diagnostic', 'build_artefact']

#: Settings of the shipped diagnostic network: two hidden layers of 64, Adam then L-BFGS.
#: Stopping is by step counts (the time limit is only a safeguard): a build is reproducible.
DIAG_SETTINGS = {
    'hidden': [64, 64], 'database': 'DB4', 'n_test': 90, 'n_val': 45, 'split_seed': 2,
    'seed': 0, 'symmetric': True, 'noise_copies': 2, 'noise_level': 0.01, 'noise': 'relative',
    'algorithm': 'adam_lbfgs',
    'adam_lbfgs': {'adam_steps': 50000, 'batch': 512, 'lr': 3e-3, 'lr_final': 1e-5,
                   'lbfgs_iters': 5000, 'time_limit_s': 3600.0},
    'lm': {'epochs': 150, 'subsample': 15000, 'resample_every': 50, 'max_fail': 60,
           'time_limit_s': 3600.0},
}


#: The reference's configuration (one hidden layer of 10, Levenberg-Marquardt), trained
#: alongside for comparison; its errors are recorded in the shipped artefact's metadata.
DIAG_THESIS_SETTINGS = {'hidden': [10], 'algorithm': 'lm'}


def add_noise(p12, level: float, rng: np.random.Generator, noise: str = 'relative'):
    """Gaussian noise on curves ``(..., n_xs)``: ``'relative'``, standard deviation ``level``
    times each pressure's magnitude; ``'rms'``, ``level`` times the RMS of each curve."""
    p12 = np.asarray(p12, dtype=float)
    n = rng.standard_normal(p12.shape)
    if noise == 'relative':
        return p12 * (1.0 + level * n)
    if noise == 'rms':
        rms = np.sqrt(np.mean(p12 ** 2, axis=-1, keepdims=True))
        return p12 + level * rms * n
    raise ValueError(f'unknown noise model {noise!r}')


def curves_from_maps(db: Database, pairs):
    """Curves ``(n, 133)``, flows ``(n,)``, true wear ``(n, 2)`` (clearance, overlap) and map
    index ``(n,)`` for the maps ``pairs`` (``(i_overlap, j_clearance)``) of ``db``."""
    n_q = db.q_m3_s.size
    return (np.concatenate([db.p12_pa[:, :, i, j].T for i, j in pairs]),
            np.tile(db.q_m3_s, len(pairs)),
            np.concatenate([np.tile([db.clearance_m[j], db.overlap_m[i]], (n_q, 1))
                            for i, j in pairs]),
            np.repeat(np.arange(len(pairs)), n_q))


#: The spans of the wear ranges [m] (clearance, overlap): the errors are in % of them.
_RANGES = np.array([np.diff(WEAR_RANGES['radial_clearance_m'])[0],
                    np.diff(WEAR_RANGES['overlap_m'])[0]])


def wear_errors(model: DiagnosticModel, curves, q, wear, map_index, *, noise_level=0.0,
                noise='relative', seed=0) -> dict:
    """Errors in % of each parameter's range (:data:`WEAR_RANGES`), per curve and per map
    (median of the map's curves): mean, max and RMS for clearance and overlap."""
    rng = np.random.default_rng(seed)
    x = add_noise(curves, noise_level, rng, noise) if noise_level else curves
    est = model.forward(x, q)
    err = np.abs(est - wear) / _RANGES * 100.0
    maps = np.unique(map_index)
    est_map = np.stack([np.median(est[map_index == m], axis=0) for m in maps])
    true_map = np.stack([wear[map_index == m][0] for m in maps])
    err_map = np.abs(est_map - true_map) / _RANGES * 100.0
    out = {}
    for k, name in enumerate(('clearance', 'overlap')):
        for tag, e in (('curve', err[:, k]), ('map', err_map[:, k])):
            out[f'{name}_{tag}'] = {'mean': float(e.mean()), 'max': float(e.max()),
                                    'rms': float(np.sqrt(np.mean(e ** 2)))}
    out['n_curves'] = int(est.shape[0])
    out['n_maps'] = int(maps.size)
    return out


def _half(curves, q, wear):
    """The curves at non-negative flow, the zero-flow curve (which may be stored at a flow of
    -1e-21) included, in the canonical form of :func:`canonical_curves`."""
    keep = q >= -1e-9 * np.max(np.abs(q))
    c, qc = canonical_curves(curves[keep], q[keep])
    return c, qc, wear[keep]


def _train_one(x_tr, y_tr, x_va, y_va, *, hidden, algorithm, seed, settings, threads):
    """Fit normalisation on the training split, train (:func:`.networks.fit_network`), return
    ``(weights, in_norm, out_norm, history, wall_s)``."""
    in_norm, out_norm = minmax(x_tr), minmax(y_tr)
    net, hist, wall = fit_network(Split(
        (x_tr - in_norm[0]) / in_norm[1], (y_tr - out_norm[0]) / out_norm[1],
        (x_va - in_norm[0]) / in_norm[1], (y_va - out_norm[0]) / out_norm[1]),
        hidden=hidden, algorithm=algorithm, seed=seed, settings=settings, threads=threads)
    weights = [(w.detach().numpy().copy(), b.detach().numpy().copy()) for w, b in net.layers()]
    return weights, in_norm, out_norm, hist, wall


def train_diagnostic(*, settings: dict | None = None, params: PlantParams | None = None,
                     threads: int = 2, verbose: bool = False) -> DiagnosticModel:
    """Train the diagnostic network on DB4 with whole maps held out; returns the model with
    its metadata (held-out errors clean and noisy, per curve and per map)."""
    p = params if params is not None else default_params()
    st = dict(DIAG_SETTINGS)
    st.update(settings or {})
    db = get_database(st['database'], p)
    train, val, test = map_split(db.overlap_m.size, db.clearance_m.size, n_test=st['n_test'],
                                 n_val=st['n_val'], seed=st['split_seed'])
    rng = np.random.default_rng(st['seed'])
    c_tr, q_tr, w_tr, _ = curves_from_maps(db, train)
    c_va, q_va, w_va, i_va = curves_from_maps(db, val)
    if st['symmetric']:
        # train on the non-negative half (the negative flows are its mirror image)
        c_tr, q_tr, w_tr = _half(c_tr, q_tr, w_tr)
        c_va, q_va, w_va = _half(c_va, q_va, w_va)
    c_te, q_te, w_te, i_te = curves_from_maps(db, test)
    copies = [c_tr] + [add_noise(c_tr, st['noise_level'], rng, st['noise'])
                       for _ in range(st['noise_copies'])]
    x_tr = np.concatenate([np.concatenate([c, q_tr[:, None]], axis=1) for c in copies])
    y_tr = np.tile(w_tr, (len(copies), 1))
    x_va = np.concatenate([np.concatenate([c, q_va[:, None]], axis=1)
                           for c in (c_va, add_noise(c_va, st['noise_level'], rng, st['noise']))])
    y_va = np.tile(w_va, (2, 1))
    alg = st['algorithm']
    weights, in_norm, out_norm, hist, wall = _train_one(
        x_tr, y_tr, x_va, y_va, hidden=st['hidden'], algorithm=alg, seed=st['seed'],
        settings=st[alg], threads=threads)
    meta = {
        'kind': 'diag', 'format': 1,
        'symmetric': bool(st['symmetric']),
        'inputs': {'names': ['p12_pa'] * db.xs_m.size + ['q_m3_s'],
                   'description': 'P12 [Pa] at the 133 spool positions of data_1 (xs_m, m), '
                                  'then the imposed flow [m^3/s]'},
        'outputs': {'names': list(OUTPUT_NAMES), 'units': list(OUTPUT_UNITS)},
        'normalisation': 'per input and output: z = (x - mid) / half, min-max to [-1, 1] '
                         'on the training split (data_2: inputs [mid; half], data_3: outputs '
                         '[mid; half])',
        'architecture': {'d_in': int(in_norm.shape[1]), 'd_hidden': st['hidden'],
                         'd_out': 2, 'activation': 'tanh', 'output_activation': 'linear',
                         'n_weights': int(sum(w.size + b.size for w, b in weights))},
        'training': {'algorithm': alg, 'settings': st[alg], 'seed': st['seed'],
                     'database': st['database'],
                     'database_hash': db.meta['fluid_hash'],
                     'noise_augmentation': {'copies': st['noise_copies'],
                                            'level': st['noise_level'], 'model': st['noise']},
                     'time_s': round(wall, 1), 'threads': threads, **history_stops(hist),
                     'split': {'train_maps': len(train), 'val_pairs': val,
                               'test_pairs': test}},
        'noise_model': 'relative: P (1 + level n), n ~ N(0, 1) per point',
        'combine': 'median over the curves of a map; spread: their standard deviation',
        'fluid_hash': fluid_hash(p),
    }
    model = DiagnosticModel(db.xs_m.copy(), in_norm, out_norm, weights, meta)
    errs = {'clean': wear_errors(model, c_te, q_te, w_te, i_te),
            'noise_1pct': wear_errors(model, c_te, q_te, w_te, i_te,
                                      noise_level=0.01, seed=123),
            'noise_1pct_rms': wear_errors(model, c_te, q_te, w_te, i_te, noise_level=0.01,
                                          noise='rms', seed=123)}
    meta['errors'] = errs
    meta['errors_unit'] = '% of each parameter range (WEAR_RANGES), held-out maps'
    if verbose:
        print(json.dumps({'hidden': st['hidden'], 'algorithm': alg, 'wall_s': round(wall, 1),
                          'stop': hist.get('stop'), 'errors': errs}), flush=True)
    return model


def build_artefact(params: PlantParams | None = None, out_dir: Path | None = None,
                   threads: int = 2, verbose: bool = False) -> Path:
    """Train the diagnostic network and save ``diag.npz`` in :func:`models_dir` (or
    ``out_dir``)."""
    model = train_diagnostic(params=params, threads=threads, verbose=verbose)
    ref = train_diagnostic(settings=DIAG_THESIS_SETTINGS, params=params, threads=threads,
                           verbose=verbose)
    model.meta['alternatives'] = {'thesis_10_lm': {
        'architecture': ref.meta['architecture'],
        'training': {k: v for k, v in ref.meta['training'].items() if k != 'split'},
        'errors': ref.meta['errors']}}
    path = (Path(out_dir) if out_dir is not None else models_dir('health')) / 'diag.npz'
    save_artefact(path, model.data(), model.meta)
    read_diagnostic.clear()
    return path


if __name__ == '__main__':
    print(build_artefact(verbose=True))
