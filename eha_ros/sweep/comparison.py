"""The in-loop comparison (:mod:`eha_ros.evaluation`) as two sweeps, and its results rebuilt
from their datasets in the shape :func:`eha_ros.evaluation.summarise` reads.

* noise-free: scenarios x wear points, every model, ``compare: yardstick`` (hf's yardstick,
  bounds and the features' spread per case), hf and the dynamic surrogates also at
  ``large_dts``;
* with noise: scenarios x seeds 0 .. n-1, ``compare: yardstick`` with noise on: each model at
  seed k against hf at seed k, hf at seed k against hf at seed k + 1 (hf's seed-to-seed
  spread) and hf with the discharge coefficient + 0.1 % against hf, same seed.

Both give the numbers :func:`~eha_ros.evaluation.noise_free` and
:func:`~eha_ros.evaluation.with_noise` give (the same runs, the same arithmetic); used by
``bench/inloop.py`` and ``eha-campaign``.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from eha_ros.evaluation import mean_sem, model_result

from .engine import cluster

__all__ = ['wear_inputs', 'noise_free_spec', 'noise_spec', 'run_comparison', 'noise_free_results',
           'noise_results']

_WEAR = ('overlap_supply_m', 'overlap_return_m', 'radial_clearance_m')


def wear_inputs(wear, base) -> dict:
    """Plant inputs of a wear point of :data:`eha_ros.evaluation.WEAR_POINTS` (``None``: the
    nominal valve, written out)."""
    if wear is None:
        return {n: float(getattr(base, n)) for n in _WEAR}
    return {'overlap_supply_m': wear[0], 'overlap_return_m': wear[0],
            'radial_clearance_m': wear[1]}


def noise_free_spec(scenarios, wear_points: dict, models, large_dts=(), signals=(),
                    split_dts=(), converged_dt=None) -> dict:
    from eha_ros.physics import default_params
    base = default_params()
    spec = {'procedure': 'scenario', 'scenario': list(scenarios), 'models': ['hf'] + [
        m for m in models if m != 'hf'], 'noise': False, 'compare': 'yardstick',
            'cases': [wear_inputs(w, base) for w in wear_points.values()]}
    spec.update((k, v) for k, v in (('large_dts', [float(d) for d in large_dts]),
                                    ('split_dts', [float(d) for d in split_dts]),
                                    ('signals', list(signals))) if v)
    if converged_dt is not None:
        spec['converged_dt'] = float(converged_dt)
    return spec


def noise_spec(scenarios, models, seeds: int) -> dict:
    return {'procedure': 'scenario', 'scenario': list(scenarios),
            'models': ['hf'] + [m for m in models if m != 'hf'], 'noise': True,
            'seeds': int(seeds), 'compare': 'yardstick'}


def _wear_name(row, wear_points, base) -> str:
    for name, w in wear_points.items():
        if all(row[k] == v for k, v in wear_inputs(w, base).items()):
            return name
    raise KeyError('a row matches no wear point')


def noise_free_results(table, wear_points: dict, keep_signals: bool = False) -> dict:
    """``{'<scenario>/<wear>': result}`` with each result as :func:`evaluation.noise_free`
    returns it (without the yardstick's per-run errors, which the dataset does not keep)."""
    from eha_ros.evaluation import DT_S
    from eha_ros.physics import default_params
    from eha_ros.sweep.procedures import FEATURES
    base = default_params()
    feats = [f for f, _ in FEATURES]
    points = {}
    for r in table.to_pylist():
        points.setdefault(r['point_id'], []).append(r)
    out = {}
    for rows in points.values():
        hf = next(r for r in rows if r['model'] == 'hf' and r['dt_s'] == DT_S)
        key = f'{hf["scenario"]}/{_wear_name(hf, wear_points, base)}'
        if hf['status'] != 'ok':
            raise RuntimeError(f'in-loop comparison {key}: hf failed: {hf["error"]}')
        f_ref = {f: hf[f] for f in feats}
        spread = {f: hf[f'spread_{f}'] for f in feats}
        res = {'yardstick': {'jack': hf['yardstick_jack'], 'p12': hf['yardstick_p12'],
                             'sets_bound': {'jack': 2 * hf['yardstick_jack'] > 0.01,
                                            'p12': 2 * hf['yardstick_p12'] > 0.05}},
               'bound': {'jack': hf['bound_jack'], 'p12': hf['bound_p12']},
               'hf_features': f_ref, 'feature_spread': spread,
               'hf_cost_s_per_s': hf['wall_cost_s_per_s'], 'models': {}}
        if hf.get('converged_settled') is not None:
            res['converged'] = {
                'hf': _converged(hf), 'settled': hf['converged_settled'],
                'check': {'jack': hf['converged_check_jack'], 'p12': hf['converged_check_p12']}}
        if keep_signals:
            res['signals'] = {'hf': _signals(hf)}
        for r in rows:
            if r is hf:
                continue
            name = r['model'] if r['dt_s'] == DT_S and '@' not in r['model'] \
                else f'{r["model"]}@dt={r["dt_s"]:g}'
            if r['status'] != 'ok':
                res['models'][name] = {'error': r['error']}
                continue
            res['models'][name] = model_result(
                r['jack_rel_error'], r['p12_rel_error'], r['meets_bounds'],
                {k: r[k] for k in feats}, f_ref, spread, r['wall_cost_s_per_s'])
            if 'converged' in res:
                res['models'][name]['converged'] = _converged(r)
            if keep_signals and '@' not in name:
                res['signals'][name] = _signals(r)
        out[key] = res
    return out


def _converged(row) -> dict:
    """A row's errors against the converged hf, as :func:`evaluation.noise_free` gives them."""
    return {'jack': row['converged_jack'], 'p12': row['converged_p12'],
            'meets': row['meets_bounds_converged']}


def _signals(row) -> dict:
    return {k[len('signal_'):]: np.asarray(v) for k, v in row.items()
            if k.startswith('signal_') and v is not None}


def noise_results(table, models) -> dict:
    """``{scenario: result}`` with each result as :func:`evaluation.with_noise` returns it."""
    rows = table.to_pylist()
    out = {}
    for sc in dict.fromkeys(r['scenario'] for r in rows):
        mine = [r for r in rows if r['scenario'] == sc]
        hf = sorted((r for r in mine if r['model'] == 'hf'), key=lambda r: r['seed'])
        bad = [r for r in hf if r['status'] != 'ok']
        if bad:
            raise RuntimeError(f'in-loop comparison {sc} with noise: hf failed: '
                               f'{bad[0]["error"]}')
        spread = [{'jack': r['seed_spread_jack'], 'p12': r['seed_spread_p12']} for r in hf]
        same = [{'jack': r['cd_plus_0p1pct_jack'], 'p12': r['cd_plus_0p1pct_p12']} for r in hf]
        res = {'seeds': len(hf), 'hf_seed_to_seed': mean_sem(spread),
               'hf_cd_plus_0.1%_same_seed': mean_sem(same), 'models': {}}
        limit = {q: 1.5 * res['hf_seed_to_seed'][q] for q in ('jack', 'p12')}
        for m in models:
            if m == 'hf':
                continue
            mr = sorted((r for r in mine if r['model'] == m), key=lambda r: r['seed'])
            failed = [r for r in mr if r['status'] != 'ok']
            if failed:
                res['models'][m] = {'error': failed[0]['error']}
                continue
            e = mean_sem([{'jack': r['jack_rel_error'], 'p12': r['p12_rel_error']}
                          for r in mr])
            e['meets'] = bool(e['jack'] <= limit['jack'] and e['p12'] <= limit['p12'])
            res['models'][m] = e
        out[sc] = res
    return out


def run_comparison(folder, scenarios, wear_points: dict, models, noise_models=(),
                   seeds: int = 0, large_dts=(), signals=(), split_dts=(), converged_dt=None,
                   **engine) -> dict:
    """Run both sweeps into ``folder/noise_free`` and ``folder/noise`` (resumed where they
    hold results) and return ``{'noise_free': ..., 'noise': ..., 'sweeps': summaries}``.
    ``engine``: :func:`.engine.run_sweep`'s ``workers`` (one LocalCluster for both sweeps),
    ``in_process``, ``warm`` (default true) and ``progress``."""
    from . import parse_spec, read_dataset, run_sweep
    folder = Path(folder)
    nf = parse_spec(noise_free_spec(scenarios, wear_points, models, large_dts, signals,
                                    split_dts, converged_dt),
                    source='in-loop comparison, noise off')
    specs = [('noise_free', nf)]
    if noise_models and seeds > 0:
        specs.append(('noise', parse_spec(noise_spec(scenarios, noise_models, seeds),
                                          source='in-loop comparison, noise on')))
    sweeps = {}
    workers = engine.pop('workers', None)
    engine.setdefault('warm', True)
    in_process = engine.get('in_process', False)
    with contextlib.nullcontext() if in_process else cluster(workers) as client:
        for name, spec in specs:
            d = folder / name
            sweeps[name] = run_sweep(spec, d, client=client,
                                     resume=d.is_dir() and any(d.iterdir()), **engine)
    return {'noise_free': noise_free_results(read_dataset(folder / 'noise_free'), wear_points,
                                             keep_signals=bool(signals)),
            'noise': noise_results(read_dataset(folder / 'noise'), noise_models)
            if len(specs) > 1 else {}, 'sweeps': sweeps}
