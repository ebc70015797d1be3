"""Data, training and build of the neural-network fluid surrogates ``nn`` and ``nn2`` (the
reference's sections 5.4.2 and 6.3.1); inference is :mod:`.nn` (numpy and numba only).

Data
    ``nn`` is trained on DB2 and DB3 together (same wear grid; DB3's flows are the narrow
    range): trained on DB2 alone it is as good on DB2's flows but twice as bad on DB3's.
    Whole maps (``(overlap, clearance)`` pairs inside the wear grid) are held out for
    validation and testing, the same pairs in both databases.  ``nn2`` is trained on DB5 with
    every 7th flow curve held out for testing (the next one for validation).

Training (torch through :func:`.networks.fit_network`, imported inside the functions only)
    Levenberg-Marquardt (as MATLAB's ``trainlm``) and Adam followed by L-BFGS, both on the mean
    squared error of the normalised output (a loss weighted by ``1 / ||map||^2``, the metric's
    own weighting, was measured and not kept: it trades DB2's accuracy for DB3's at a loss
    overall).  :func:`train_fluid_network` trains with both and keeps the one with the lower
    validation error; the metadata holds both results.

Error metric (the reference's, :func:`.base.relative_error`): the relative error in
Euclidean norm over a map, ``||P_pred - P_true||_2 / ||P_true||_2`` with the map all spool
positions x flows of one wear pair.

Build: ``python -m eha_ros.training.nn`` (:func:`build_artefacts`; about an hour on two
cores).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import fluid_hash, transient_map
from eha_ros.surrogates.nn import (ASINH, INPUT_NAMES, INPUT_UNITS, SPOOL_GRID_DENSITY,
                                   fit_inputs, fit_output, mlp_numpy, pack, transform_inputs)
from eha_ros.training.database import Database, get_database, heldout_maps, map_errors
from eha_ros.training.networks import Split, fit_network, history_stops, map_split

__all__ = ['network_map_errors', 'db_maps', 'train_fluid_network', 'build_artefacts',
           'NN_SETTINGS', 'NN2_SETTINGS']


# --- data and errors ------------------------------------------------------------------------

def _points(db: Database, pairs, weights: bool = False):
    """Raw inputs ``(N, 4)`` and P12 ``(N,)`` of the maps ``pairs`` of ``db``; with
    ``weights``, also ``1 / ||map||^2`` per point (so that a weighted squared error sums the
    squared relative errors of the maps, the reference's metric)."""
    xs, q = np.meshgrid(db.xs_m, db.q_m3_s, indexing='ij')
    xs, q = xs.ravel(), q.ravel()
    raw = np.concatenate([np.stack([xs, q, np.full_like(xs, db.overlap_m[i]),
                                    np.full_like(xs, db.clearance_m[j])], axis=1)
                          for i, j in pairs])
    ys = [db.p12_pa[:, :, i, j].ravel() for i, j in pairs]
    if not weights:
        return raw, np.concatenate(ys)
    return raw, np.concatenate(ys), np.concatenate([np.full(xs.size, 1.0 / np.sum(y ** 2))
                                                    for y in ys])


def network_map_errors(data, maps) -> np.ndarray:
    """Relative error in Euclidean norm (:func:`.base.relative_error`) of each map of ``maps``
    (see :func:`.database.heldout_maps`) for the packed network ``data``."""
    return map_errors(lambda *a: mlp_numpy(data, *a), maps)


def db_maps(db: Database, pairs):
    """The maps ``pairs`` of ``db`` in the form :func:`map_errors` takes."""
    return [(db.xs_m, db.q_m3_s, float(db.overlap_m[i]), float(db.clearance_m[j]),
             db.p12_pa[:, :, i, j]) for i, j in pairs]


def _summary(errs) -> dict:
    errs = np.asarray(errs)
    return {'mean': float(errs.mean()), 'max': float(errs.max()), 'n_maps': int(errs.size)}


# --- training a fluid network end to end -----------------------------------------------------

#: Settings of the shipped 4-input network (the reference's architecture).  Stopping is by
#: epoch/iteration counts (the time limits are only a safeguard), so a build is reproducible.
NN_SETTINGS = {
    'hidden': [21, 15, 3], 'transforms': ['linear', 'linear', 'linear', 'linear'],
    'databases': ['DB2', 'DB3'], 'n_test': 10, 'n_val': 6, 'split_seed': 1, 'seed': 0,
    'map_weighting': False,
    'lm': {'epochs': 1000, 'subsample': 20000, 'resample_every': 100, 'max_fail': 200,
           'time_limit_s': 3600.0},
    'adam_lbfgs': {'adam_steps': 20000, 'batch': 4096, 'lr': 1e-2, 'lr_final': 1e-4,
                   'lbfgs_iters': 1500, 'time_limit_s': 3600.0},
}

#: Settings of the shipped 2-input network (nominal wear, DB5).
NN2_SETTINGS = {
    'hidden': [21, 15, 3], 'transforms': ['linear', 'linear'], 'databases': ['DB5'],
    'seed': 0, 'q_test_every': 7, 'map_weighting': False,
    'lm': {'epochs': 1000, 'subsample': 20000, 'resample_every': 0, 'max_fail': 200,
           'time_limit_s': 3600.0},
    'adam_lbfgs': {'adam_steps': 20000, 'batch': 4096, 'lr': 1e-2, 'lr_final': 1e-4,
                   'lbfgs_iters': 1500, 'time_limit_s': 3600.0},
}


def _fit_model(raw: Split, columns: tuple, **net):
    """Normalise ``raw`` (the plant's inputs and P12 [Pa]) on its training split, with
    ``columns`` the inputs' ``(sources, transforms, scales)`` (:func:`fit_inputs`), then build
    and train one network (:func:`fit_network`, keywords ``net``); returns ``(data, history,
    wall_s, model)``."""
    inputs = fit_inputs(raw.x, *columns)
    output = fit_output(raw.y)
    val = raw.x_val is not None
    model, hist, wall = fit_network(Split(
        transform_inputs(inputs, raw.x), (raw.y - output[0]) / output[1],
        transform_inputs(inputs, raw.x_val) if val else None,
        (raw.y_val - output[0]) / output[1] if val else None, raw.w, raw.w_val), **net)
    data = pack(model.sizes, inputs, output, model.theta.detach().numpy())
    return data, hist, wall, model


def train_fluid_network(*, n_inputs: int = 4, settings: dict | None = None,
                        algorithms=('lm', 'adam_lbfgs'), params: PlantParams | None = None,
                        threads: int = 2, n_offgrid: int = 8, verbose: bool = False):
    """Train the 4-input (``n_inputs=4``, DB2/DB3 settings :data:`NN_SETTINGS`) or 2-input
    (``n_inputs=2``, DB5, :data:`NN2_SETTINGS`) network with each algorithm, keep the one with
    the lower validation error and return ``(data, meta)``.

    4 inputs: whole maps are held out (test and validation pairs of the wear grid, the same in
    every database used); errors are reported on the held-out maps of each database and on
    ``n_offgrid`` fresh maps at random wear.  2 inputs: every ``q_test_every``-th flow curve
    of DB5 is held out for testing (the ones next to them for validation); errors on the
    held-out curves and on a fresh nominal map at flows between the database's.
    """
    p = params if params is not None else default_params()
    st = dict(NN_SETTINGS if n_inputs == 4 else NN2_SETTINGS)
    st.update(settings or {})
    dbs = {name: get_database(name, p) for name in st['databases']}
    scales = [p.spool_stroke_m / math.sinh(SPOOL_GRID_DENSITY), None, None, None][:n_inputs]
    if n_inputs == 4:
        first = next(iter(dbs.values()))
        train, val, test = map_split(first.overlap_m.size, first.clearance_m.size,
                                     n_test=st['n_test'], n_val=st['n_val'],
                                     seed=st['split_seed'])
        raw_tr, y_tr, w_tr = (np.concatenate(a) for a in zip(
            *(_points(db, train, weights=True) for db in dbs.values())))
        raw_val, y_val, w_val = (np.concatenate(a) for a in zip(
            *(_points(db, val, weights=True) for db in dbs.values())))
        split = {'train_maps': len(train), 'val_pairs': val, 'test_pairs': test}
        eval_sets = {f'{name}_test': db_maps(db, test) for name, db in dbs.items()}
        val_maps = [m for db in dbs.values() for m in db_maps(db, val)]
        for name, db in dbs.items():
            q_max = float(np.max(np.abs(db.q_m3_s)))
            eval_sets[f'offgrid_q{q_max:.1e}'] = heldout_maps(
                n_offgrid, q_max_m3_s=q_max, n_q=db.q_m3_s.size, seed=100, params=p)
    else:
        db = dbs['DB5']
        n_q = db.q_m3_s.size
        every = st['q_test_every']
        test_q = np.arange(every // 2, n_q, every)
        val_q = np.clip(test_q + 1, 0, n_q - 1)
        train_q = np.setdiff1d(np.arange(n_q), np.concatenate([test_q, val_q]))
        sub = (lambda cols: Database(db.xs_m, db.q_m3_s[cols], db.overlap_m, db.clearance_m,
                                     db.p12_pa[:, cols], db.meta))
        raw_tr, y_tr, w_tr = _points(sub(train_q), [(0, 0)], weights=True)
        raw_val, y_val, w_val = _points(sub(val_q), [(0, 0)], weights=True)
        split = {'train_flows': int(train_q.size), 'val_flows': val_q.tolist(),
                 'test_flows': test_q.tolist()}
        eval_sets = {'DB5_test': db_maps(sub(test_q), [(0, 0)])}
        val_maps = db_maps(sub(val_q), [(0, 0)])
        q_mid = 0.5 * (db.q_m3_s[1:] + db.q_m3_s[:-1])[::4]
        fresh = transient_map(db.xs_m[:, None], q_mid[None, :], params=p)['p12_pa']
        eval_sets['offgrid_flows'] = [(db.xs_m, q_mid, p.overlap_supply_m,
                                       p.radial_clearance_m, fresh)]
    sources = list(range(n_inputs))
    results = {}
    weighted = st['map_weighting']
    for alg in algorithms:
        data, hist, wall, _ = _fit_model(
            Split(raw_tr, y_tr, raw_val, y_val, w_tr if weighted else None,
                  w_val if weighted else None), (sources, st['transforms'], scales),
            hidden=st['hidden'], algorithm=alg, seed=st['seed'], settings=st[alg],
            threads=threads)
        errs = {k: _summary(network_map_errors(data, v)) for k, v in eval_sets.items()}
        val_err = _summary(network_map_errors(data, val_maps))
        results[alg] = {'data': data, 'hist': hist, 'wall_s': wall, 'errors': errs,
                        'val': val_err}
        if verbose:
            print(json.dumps({'algorithm': alg, 'wall_s': round(wall, 1), 'val': val_err,
                              'errors': errs, 'stop': hist.get('stop')}), flush=True)
    winner = min(results, key=lambda a: results[a]['val']['mean'])
    res = results[winner]
    inputs = res['data'][1]
    meta = {
        'kind': 'mlp', 'format': 1,
        'inputs': [{'name': INPUT_NAMES[int(r[0])], 'unit': INPUT_UNITS[int(r[0])],
                    'transform': 'asinh(x/scale)' if r[1] == ASINH else 'x/scale',
                    'scale': r[2], 'mid': r[3], 'half': r[4]} for r in inputs],
        'inputs_used': [INPUT_NAMES[s] for s in sources],
        'normalisation': 'z = (transform(x) - mid) / half, min-max to [-1, 1] on the '
                         'training split; P12 = mid + half * y',
        'output': {'name': 'p12_pa', 'unit': 'Pa', 'mid': float(res['data'][2][0]),
                   'half': float(res['data'][2][1])},
        'architecture': {'d_in': n_inputs, 'd_hidden': st['hidden'], 'd_out': 1,
                         'activation': 'tanh', 'output_activation': 'linear',
                         'n_weights': int(res['data'][3].size)},
        'training': {'algorithm': winner, 'settings': st[winner], 'seed': st['seed'],
                     'loss': ('squared error of the normalised output weighted by '
                              '1/||map||^2 (sum of squared relative map errors)'
                              if st['map_weighting'] else
                              'mean squared error of the normalised output'),
                     'time_s': round(res['wall_s'], 1), 'threads': threads,
                     **history_stops(res['hist']), 'databases': st['databases'],
                     'database_hashes': {k: db.meta['fluid_hash'] for k, db in dbs.items()},
                     'split': split},
        'comparison': {alg: {'time_s': round(r['wall_s'], 1), 'val': r['val'],
                             'errors': r['errors'], **history_stops(r['hist']),
                             'settings': st[alg]}
                       for alg, r in results.items()},
        'winner_rule': 'lower mean relative map error on the validation maps',
        'errors': res['errors'],
        'metric': '||P_pred - P_true||_2 / ||P_true||_2 per map (all XS x Q of one wear pair)',
        'valid_range': {'xs_m': [float(raw_tr[:, 0].min()), float(raw_tr[:, 0].max())],
                        'q_m3_s': [float(raw_tr[:, 1].min()), float(raw_tr[:, 1].max())]},
        'fluid_hash': fluid_hash(p),
    }
    if n_inputs == 2:
        meta['nominal_wear'] = {'overlap_m': p.overlap_supply_m,
                                'clearance_m': p.radial_clearance_m}
        meta['note'] = 'ignores the overlap and clearance arguments (nominal wear)'
    return res['data'], meta


def build_artefacts(params: PlantParams | None = None, out_dir: Path | None = None,
                    threads: int = 2, verbose: bool = False) -> list[Path]:
    """Train and save ``nn.npz`` (4 inputs) and ``nn2.npz`` (2 inputs) in
    :func:`models_dir` (or ``out_dir``); returns their paths."""
    out = Path(out_dir) if out_dir is not None else models_dir('surrogates')
    paths = []
    for name, n_in in (('nn', 4), ('nn2', 2)):
        data, meta = train_fluid_network(n_inputs=n_in, params=params, threads=threads,
                                         verbose=verbose)
        path = out / f'{name}.npz'
        save_artefact(path, data, meta)
        paths.append(path)
    return paths


if __name__ == '__main__':
    for _p in build_artefacts(verbose=True):
        print(_p)
