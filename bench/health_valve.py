"""The valve test under drift: the settled test read by the valve fit at the measured
conditions, beside the reference's 10 ms transient read by the diagnostic network, on sets
drawn from streams used neither to build nor to calibrate either (``config/test_bench.yaml``
states the envelopes).  Every case runs through the sweep engine (``eha_ros.sweep``).

Sets
    ``clean``: random valves (wear uniform over its ranges), nominal conditions (the bench's
    sensor errors from each seed).  ``noise_1pct``: the same valves, 1 % relative noise on
    every pressure.  ``drift``: random valves with supply pressure +-5 %, return pressure,
    fluid temperature over its service range, bulk modulus -20/+10 %, Khsv up to 0.2 and jack
    leakage up to 10x drawn uniformly.  ``nominal_drift``: the nominal valve with that drift
    and different seeds (false alarms).  ``beyond``: drifted valves with one condition beyond
    the envelope (``beyond`` in ``config/test_bench.yaml``).  ``fleet``: random valves with
    that drift and every nuisance of ``config/tolerances.yaml`` drawn over its range (the
    unit-to-unit tolerances and the fluid's condition), from a stream of its own.

Per set and procedure: mean and max error in % of each range, 2-sigma coverage, items that
read OK with a 2-sigma interval excluding the truth, mismatch flags (the reference's: its
residual beyond ``residual_error_pa``), and the confusion table of the true level against the
reported one; on ``fleet``, the share of each estimate's mean square error that each drawn
parameter explains (a linear fit on the fleet itself), and a control: the same fit on each
unit's steady map (``steady_readings``: what the hold's unsettled readings cost); on
``clean``, the same control with the fit's laminar-factor prior centred on the nominal valve
(``steady_readings_nominal_prior``: what the unobservable leakage gain costs a valve that
is nominal in its tolerances).

    python bench/health_valve.py [--workers 2] [--quick] [--smoke] [--sets fleet,...]

``--smoke``: one valve per set (two ``beyond`` values), in process: a check that the bench
runs, no figure.
"""

import argparse
import json
import os
import time

if __name__ in ('__main__', '__mp_main__'):   # the sweep's workers import this again
    os.environ.setdefault('NUMBA_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from eha_ros.graph import LEVEL_NAMES  # noqa: E402
from eha_ros.health.thresholds import HealthEstimate, HealthThresholds, classify  # noqa: E402
from eha_ros.physics.maps import WEAR_RANGES  # noqa: E402
from eha_ros.physics.tolerances import error_shares  # noqa: E402
from eha_ros.training.valve_fit import drifted_cases, run_cases  # noqa: E402

#: Streams of the sets (the calibration uses 32; 31 before the fleet).
STREAMS = {'clean': 201, 'drift': 202, 'nominal_drift': 203, 'beyond': 204, 'fleet': 205}
SPANS = np.array([np.diff(WEAR_RANGES['radial_clearance_m'])[0],
                  np.diff(WEAR_RANGES['overlap_m'])[0]])
CANNOT = 3


def _level(c, o, lim) -> int:
    if c >= lim.clearance_error_m or o <= lim.overlap_error_m:
        return 2
    if c >= lim.clearance_warn_m or o <= lim.overlap_warn_m:
        return 1
    return 0


def figures(table, cases, procedure, lim, shares: bool = False) -> dict:
    """The figures of one set and procedure (module docstring); ``shares``: and the share of
    each estimate's mean square error on the assessed valves each drawn parameter explains
    (:func:`eha_ros.physics.tolerances.error_shares`, a linear fit on the set itself)."""
    col = {k: np.array(table.column(k).to_pylist()) for k in (
        'status', 'est_radial_clearance_m', 'est_radial_clearance_std_m', 'est_overlap_m',
        'est_overlap_std_m', 'pressure_residual_pa', 'mismatch')}
    ok = col['status'] == 'ok'
    from eha_ros.physics import default_params
    p = default_params()
    truth = np.array([[c.get('radial_clearance_m', p.radial_clearance_m),
                       c.get('overlap_supply_m', p.overlap_supply_m)] for c in cases])
    est = np.stack([col['est_radial_clearance_m'], col['est_overlap_m']], axis=1).astype(float)
    std = np.stack([col['est_radial_clearance_std_m'], col['est_overlap_std_m']],
                   axis=1).astype(float)
    if procedure == 'settled':
        mismatch = col['mismatch'].astype(bool)
    else:   # the reference's only test of fit: its residual against the limit
        mismatch = col['pressure_residual_pa'].astype(float) > lim.residual_error_pa
    err = np.abs(est - truth) / SPANS * 100.0
    inside = np.abs(est - truth) <= 2.0 * std
    levels, true_levels = [], []
    for k in range(len(cases)):
        true_levels.append(_level(*truth[k], lim))
        if not ok[k]:
            levels.append(2)
            continue
        if mismatch[k]:
            levels.append(CANNOT)
            continue
        h = HealthEstimate(est[k, 0], std[k, 0], est[k, 1], std[k, 1],
                           float(col['pressure_residual_pa'][k]), 0, procedure)
        levels.append(classify(h, lim)[0])
    levels, true_levels = np.array(levels), np.array(true_levels)
    confusion = {}
    for t in range(3):
        row = {LEVEL_NAMES[r]: int(np.sum((true_levels == t) & (levels == r)))
               for r in range(4)}
        if sum(row.values()):
            confusion[f'true_{LEVEL_NAMES[t]}'] = row
    assessed = ok & ~mismatch
    out = {'cases': len(cases), 'errors': int((~ok).sum()),
           'mismatch_flagged': int(mismatch[ok].sum()),
           'mismatch_rate': round(float(mismatch[ok].mean()), 3) if ok.any() else None,
           'confusion': confusion,
           'alarms': int(np.sum(np.isin(levels, (1, 2, CANNOT)))),
           'ok_excluding_truth': int(np.sum((levels == 0)[:, None] & ~inside & ok[:, None]))}
    for j, name in enumerate(('clearance', 'overlap')):
        for tag, m in (('all', ok), ('assessed', assessed)):
            if m.any():
                out[f'{name}_{tag}'] = {
                    'mean_error_pct': round(float(err[m, j].mean()), 3),
                    'max_error_pct': round(float(err[m, j].max()), 3),
                    'within_2sigma': round(float(inside[m, j].mean()), 3), 'n': int(m.sum())}
    if shares and assessed.any():
        units = [c for c, a in zip(cases, assessed) if a]
        try:
            s = error_shares((est - truth)[assessed] / SPANS, units)
            out['error_shares_assessed'] = {'clearance': s[0], 'overlap': s[1]}
        except ValueError as exc:
            out['error_shares_assessed'] = None
            out['error_shares_not_computed'] = str(exc)
    return out


#: Cases per set: (clean and noisy valves, drifted, nominal drifted, per beyond value, beyond
#: values: None for every one of the bench's, fleet).
SIZES = {'full': (40, 200, 24, 10, None, 200), 'quick': (12, 40, 8, 3, None, 40),
         'smoke': (1, 1, 1, 1, 2, 1)}
SETS = ('clean', 'noise_1pct', 'drift', 'nominal_drift', 'beyond', 'fleet')


def sets(size: str = 'full') -> dict:
    """``{set: (cases, noise)}`` with the counts of ``SIZES[size]``."""
    n, n_drift, n_nominal, per, n_beyond, n_fleet = SIZES[size]
    clean = drifted_cases(n, STREAMS['clean'], drift=False)
    out = {'clean': (clean, 0.0), 'noise_1pct': (clean, 0.01),
           'drift': (drifted_cases(n_drift, STREAMS['drift']), 0.0),
           'nominal_drift': (drifted_cases(n_nominal, STREAMS['nominal_drift'],
                                           wear=False), 0.0)}
    from eha_ros.physics import default_params
    from eha_ros.physics.bench import load_bench
    p = default_params()
    b = load_bench()
    beyond, k = [], 0
    for name, entry in b.beyond.items():
        values = ([f * getattr(p, name) for f in entry['factors']] if 'factors' in entry
                  else list(entry['values']))
        for v in values:
            beyond += [dict(c, _beyond=f'{name}={v:.4g}') for c in drifted_cases(
                per, STREAMS['beyond'] + 1000 * k, overrides={name: v})]
            k += 1
    out['beyond'] = (beyond[:None if n_beyond is None else n_beyond * per], 0.0)
    out['fleet'] = (drifted_cases(n_fleet, STREAMS['fleet'], fleet=True), 0.0)
    return out


def steady_readings(table, cases, lim, laminar_prior=None) -> dict:
    """The control of the settled fleet set: the same valve fit, at the same measured
    conditions, on each unit's steady map (:func:`eha_ros.physics.maps.steady_map` of its
    true parameters: the readings a hold long enough to settle every point would give), in
    this process.  The difference to the set's figures is what the hold's unsettled
    readings cost; ``fit_s``: the seconds each estimate took.  ``laminar_prior``: the fit's
    prior on the laminar factor (default the fleet's; the clean set's control centres it on
    the nominal valve: what the unobservable leakage gain costs a valve that is nominal in its
    tolerances)."""
    from eha_ros.health.valve_fit import ValveFitEstimator
    from eha_ros.physics import default_params
    from eha_ros.physics.bench import Conditions
    from eha_ros.physics.maintenance import valve_test_schedule
    from eha_ros.physics.maps import spool_grid, steady_map
    from eha_ros.physics.params import replace
    import pyarrow as pa
    sch = valve_test_schedule('settled')
    est = ValveFitEstimator(replace(default_params(), noise_std_a=0.0),
                            laminar_prior=laminar_prior)
    rows, fit_s = [], []
    for k, c in enumerate(cases):
        p = replace(default_params(), **{n: v for n, v in c.items() if n != 'seed'})
        grid = spool_grid(sch['n_points'], p.spool_stroke_m)
        if table.column('status')[k].as_py() != 'ok':   # no measured conditions: as the set
            rows.append({'status': 'error', 'error': 'the test did not run'})
            continue
        cond = Conditions(*(float(table.column(f'measured_{n}')[k].as_py()) for n in (
            'supply_pressure_pa', 'return_pressure_pa', 'fluid_temperature_k')))
        curves = [(q, grid, steady_map(grid, np.full(grid.size, q), params=p)['p12_pa'])
                  for q in sch['flows_m3_s']]
        t0 = time.perf_counter()
        try:
            h = est.estimate(curves, cond)
            fit_s.append(time.perf_counter() - t0)
        except ValueError as exc:   # too few points in band: as the sweep reports it
            rows.append({'status': 'error', 'error': str(exc)})
            continue
        rows.append({'status': 'ok', 'est_radial_clearance_m': h.radial_clearance_m,
                     'est_radial_clearance_std_m': h.radial_clearance_std_m,
                     'est_overlap_m': h.overlap_m, 'est_overlap_std_m': h.overlap_std_m,
                     'pressure_residual_pa': h.pressure_residual_pa,
                     'mismatch': bool(h.mismatch)})
    cols = ('status', 'est_radial_clearance_m', 'est_radial_clearance_std_m', 'est_overlap_m',
            'est_overlap_std_m', 'pressure_residual_pa', 'mismatch')
    t = pa.table({n: [r.get(n, np.nan if n != 'status' else 'error') for r in rows]
                  for n in cols})
    out = figures(t, cases, 'settled', lim)
    out.pop('confusion', None)
    out['note'] = ('control: the fit on each unit\'s steady map, not a test a bench runs'
                   + ('' if laminar_prior is None else
                      f'; laminar prior (log10 mean, std) = {tuple(laminar_prior)}'))
    if fit_s:   # the valve fit's own cost, one estimate at a time in this process
        out['fit_s'] = {'mean': round(float(np.mean(fit_s)), 3),
                        'max': round(float(np.max(fit_s)), 3), 'n': len(fit_s)}
    return out


def valve_drift(workers: int = 2, size: str = 'full', progress=None, only=SETS) -> dict:
    """The figures of the sets ``only`` (module docstring) of ``SIZES[size]``, both
    procedures."""
    lim = HealthThresholds.load()
    out = {}
    for name, (cases, noise) in sets(size).items():
        if name not in only:
            continue
        clean = [{k: v for k, v in c.items() if k != '_beyond'} for c in cases]
        out[name] = {}
        for procedure in ('settled', 'reference'):
            t = time.perf_counter()
            table = run_cases(clean, procedure, noise, workers=workers)
            out[name][procedure] = figures(table, clean, procedure, lim,
                                           shares=name == 'fleet')
            out[name][procedure]['wall_s'] = round(time.perf_counter() - t, 1)
            if name == 'fleet' and procedure == 'settled':
                out[name]['steady_readings'] = steady_readings(table, clean, lim)
            if name == 'clean' and procedure == 'settled':
                from eha_ros.health.valve_fit import unit_priors
                out[name]['steady_readings_nominal_prior'] = steady_readings(
                    table, clean, lim, (0.0, unit_priors()['laminar'][1]))
            if name == 'beyond':
                mis = np.array(table.column('mismatch').to_pylist(), dtype=bool)
                if procedure == 'reference':
                    mis = np.array(table.column('pressure_residual_pa').to_pylist(),
                                   dtype=float) > lim.residual_error_pa
                kinds = {}
                for c, m in zip(cases, mis):
                    kinds.setdefault(c['_beyond'], []).append(bool(m))
                out[name][procedure]['hit_rate_by_kind'] = {
                    k: round(float(np.mean(v)), 3) for k, v in kinds.items()}
        if progress:
            progress(json.dumps({name: out[name]}))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--workers', type=int, default=None,
                    help='sweep workers (1: in process; default 2, with --smoke 1)')
    ap.add_argument('--quick', action='store_true', help='fewer cases')
    ap.add_argument('--smoke', action='store_true',
                    help='one or two valves per set: a check, no figure')
    ap.add_argument('--sets', default=','.join(SETS),
                    help=f'comma-separated sets to run (default all: {",".join(SETS)})')
    args = ap.parse_args()
    only = tuple(x for x in args.sets.split(',') if x)
    bad = [x for x in only if x not in SETS]
    if bad or not only:
        ap.error(f'--sets: unknown set {bad[0]!r} (known: {", ".join(SETS)})' if bad
                 else '--sets: name at least one set')
    if args.workers is None:
        args.workers = 1 if args.smoke else 2
    if args.workers < 1:
        ap.error(f'--workers {args.workers} must be at least 1')
    size = 'smoke' if args.smoke else 'quick' if args.quick else 'full'
    t0 = time.perf_counter()
    out = {'benchmark': 'health_valve', 'smoke': args.smoke, 'size': size, 'sets': list(only),
           'load_before': [round(x, 2) for x in os.getloadavg()]}
    out.update(valve_drift(args.workers, size,
                           progress=lambda line: print(line, flush=True), only=only))
    out['load_after'] = [round(x, 2) for x in os.getloadavg()]
    out['wall_s'] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
