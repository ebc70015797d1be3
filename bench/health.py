"""Health monitoring figures: valve test, pre-flight faults, in-service coverage, realtime.

Prints one JSON object:

``valve_test``
    The diagnostic network on the valve test's three curves (transient maps of the
    high-fidelity valve) at 4 named and 12 random valves (seeded, interior of the wear ranges):
    error in % of each range, clean and with 1 % relative noise (3 noise seeds), and how
    often the truth lies within the stated 2 sigma.
``preflight``
    The pre-flight network on the high-fidelity plant's pre-flight check at cases drawn from
    streams used neither for training nor validation: ``combinations`` (2-3 simultaneous
    faults among the five, the rest nominal, clearance and overlap random): per fault the mean
    error in % of its range and the fraction within 2 sigma; ``single`` (one fault between its
    error limit and the end of its range): isolation (the most degraded item - largest
    estimate over its warn limit, in units of the warn distance from nominal - is the injected
    one) and the confusion table injected -> flagged (items graded WARN/ERROR; ``none``);
    ``nominal`` (20 noise seeds): false alarms.
``in_service``
    4 valves x the reference's 9 scenarios x 3 noise seeds (physics-only closed loop, 1 kHz
    controller, the monitor's last 1 s window): how often both wear parameters lie within
    2 sigma, false alarms on the nominal valve, detections on the worn ones, and how many
    estimates were labelled separable while their error exceeded 2 sigma.
``valve_test_drift`` (``bench/health_valve.py``; ``--no-drift`` skips)
    The settled valve test beside the reference's under drift: clean, 1 % noise, drifted
    within the envelope, nominal valves with drift, beyond the envelope.
``preflight_drift`` (``bench/health_preflight.py``, where present; ``--no-drift`` skips)
    The pre-flight network under nuisance drift.
``realtime`` (``--realtime-s S``, default 20; 0 skips)
    The graph in realtime at 1 kHz, every node its own process, health monitor on: in-service
    estimates published against those scheduled (one every ``update_period_s`` of received
    state time).

    python bench/health.py [--realtime-s 20] [--quick] [--no-drift] [--workers 2] [--smoke]

``--quick`` runs fewer cases; ``--smoke`` the fewest that pass through every section
(:data:`SIZES`; of the drifted sets, in process, only the first of each module: every set is
run by ``health_valve.py --smoke`` and ``health_preflight.py --smoke``; 1 s realtime): a check
that the bench runs, no figure.
"""

import argparse
import json
import os
import time

import numpy as np

from eha_ros.graph import LEVEL_NAMES, REFERENCE_SCENARIOS as SCENARIOS
from eha_ros.physics import default_params, get_scenario, simulate
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, transient_map
from eha_ros.physics.params import replace
from eha_ros.physics.maintenance import run_preflight
from eha_ros.health.posterior import InServiceEstimator
from eha_ros.health.preflight import CONDITION_READINGS, FAULTS, load_faults
from eha_ros.physics.bench import mean_conditions, measure_conditions
from eha_ros.health.thresholds import HealthThresholds, classify, classify_fault
from eha_ros.health.valve_test import ValveTestEstimator
from eha_ros.training.preflight import apply_wear, combination_cases
from eha_ros.training.valve_test import add_noise

VALVES = {'nominal': (2.5e-6, 1e-6), 'clearance_4p5': (4.5e-6, 1e-6),
          'underlap_1': (2.5e-6, -1e-6), 'worn': (4.5e-6, -0.5e-6)}
FIVE = FAULTS[:5]
#: Streams of the benchmark's cases (the network's data used 21-24).
STREAM_COMBOS, STREAM_SINGLE, STREAM_NOMINAL, STREAM_VALVES = 101, 102, 103, 104

#: Cases per section and size: random valves of the valve test, pre-flight combinations,
#: single-fault rounds, nominal runs, in-service valves, scenarios and seeds.
SIZES = {'full': {'valves': 12, 'combinations': 80, 'single_rounds': 8, 'nominal': 20,
                  'in_service_valves': None, 'scenarios': None, 'seeds': (1, 2, 3)},
         'quick': {'valves': 4, 'combinations': 20, 'single_rounds': 3, 'nominal': 20,
                   'in_service_valves': None, 'scenarios': None, 'seeds': (1,)},
         'smoke': {'valves': 1, 'combinations': 2, 'single_rounds': 1, 'nominal': 2,
                   'in_service_valves': 2, 'scenarios': 1, 'seeds': (1,)}}


def bench_valve_test(p0, size):
    net = ValveTestEstimator(p0)
    flows = get_scenario('valve_test').valve_test_flows_m3_s
    xs = spool_grid(133, p0.spool_stroke_m)
    (l0, l1), (c0, c1) = WEAR_RANGES['overlap_m'], WEAR_RANGES['radial_clearance_m']
    rng = np.random.default_rng(STREAM_VALVES)
    valves = list(VALVES.values()) + [
        (rng.uniform(c0 + 0.05 * (c1 - c0), c1 - 0.05 * (c1 - c0)),
         rng.uniform(l0 + 0.05 * (l1 - l0), l1 - 0.05 * (l1 - l0)))
        for _ in range(size['valves'])]
    rows = {'clean': [], 'noise_1pct': []}
    for clr, lap in valves:
        p = replace(p0, radial_clearance_m=clr, overlap_supply_m=lap, overlap_return_m=lap)
        curves = [(q, xs, transient_map(xs, q, params=p)['p12_pa']) for q in flows]
        cases = [('clean', curves)] + [
            ('noise_1pct', [(q, x, add_noise(c[None, :], 0.01, np.random.default_rng(s))[0])
                            for q, x, c in curves]) for s in range(3)]
        for label, cv in cases:
            e = net.estimate(cv)
            rows[label].append((100 * abs(e.radial_clearance_m - clr) / (c1 - c0),
                                100 * abs(e.overlap_m - lap) / (l1 - l0),
                                abs(e.radial_clearance_m - clr) <= 2 * e.radial_clearance_std_m
                                and abs(e.overlap_m - lap) <= 2 * e.overlap_std_m))
    out = {'valves': len(valves)}
    for label, r in rows.items():
        a = np.array(r, dtype=float)
        out[label] = {'clearance_max_error_pct': round(a[:, 0].max(), 3),
                      'clearance_mean_error_pct': round(a[:, 0].mean(), 3),
                      'overlap_max_error_pct': round(a[:, 1].max(), 3),
                      'overlap_mean_error_pct': round(a[:, 1].mean(), 3),
                      'within_2sigma': round(a[:, 2].mean(), 3), 'cases': len(r)}
    return out


def _severity(name, value, lim):
    """Estimate over its warn limit, in units of the warn distance from nominal."""
    f = next(f for f in FAULTS if f.name == name)
    fl = lim.fault(name)
    if fl.absolute:
        return abs(value) / fl.warn
    return (value - f.nominal) / (fl.warn - f.nominal)


def _estimate(model, params, seed):
    """The network on the plant's pre-flight check at the conditions the bench measures."""
    cond = mean_conditions(measure_conditions(params, seed, CONDITION_READINGS))
    return model.estimate(run_preflight(params, seed=seed), cond)


def bench_preflight(p0, lim, size):
    model = load_faults()
    nominal = {f.name: f.nominal for f in FAULTS}
    out = {}
    # 2-3 simultaneous faults (the others nominal, clearance and overlap random)
    errs, inside = [], []
    for wear, seed in combination_cases(size['combinations'], STREAM_COMBOS, drift=False):
        est = _estimate(model, apply_wear(p0, wear), seed)
        errs.append([abs(est.values[f.name] - wear[f.name]) / f.span for f in FIVE])
        inside.append([abs(est.values[f.name] - wear[f.name]) <= 2 * est.stds[f.name]
                       for f in FIVE])
    errs, inside = np.array(errs), np.array(inside)
    out['combinations'] = {
        'cases': len(errs),
        'mean_error_pct_of_range': {f.name: round(100 * errs[:, j].mean(), 2)
                                    for j, f in enumerate(FIVE)},
        'p95_error_pct_of_range': {f.name: round(100 * np.quantile(errs[:, j], 0.95), 2)
                                   for j, f in enumerate(FIVE)},
        'within_2sigma': {f.name: round(inside[:, j].mean(), 3) for j, f in enumerate(FIVE)}}
    # single faults: isolation and confusion
    rng = np.random.default_rng(STREAM_SINGLE)
    confusion = {f.name: {} for f in FIVE}
    correct, n = 0, 0
    for rep in range(size['single_rounds']):
        for f in FIVE:
            fl = lim.fault(f.name)
            wear = dict(nominal)
            lo = fl.error
            if fl.absolute:
                wear[f.name] = float(rng.choice([-1, 1]) * rng.uniform(lo, f.hi))
            else:
                wear[f.name] = float(rng.uniform(lo, f.hi))
            est = _estimate(model, apply_wear(p0, wear), int(rng.integers(1e9)))
            sev = {g.name: _severity(g.name, est.values[g.name], lim) for g in FIVE}
            named = max(sev, key=sev.get)
            correct += named == f.name
            n += 1
            flagged = [g.name for g in FIVE if classify_fault(
                g.name, est.values[g.name], est.stds[g.name], lim)[0] > 0] or ['none']
            for g in flagged:
                confusion[f.name][g] = confusion[f.name].get(g, 0) + 1
    out['single'] = {'cases': n, 'isolation': round(correct / n, 3),
                     'confusion_injected_to_flagged': confusion}
    # nominal seeds: false alarms
    rng = np.random.default_rng(STREAM_NOMINAL)
    alarms = []
    n_nom = size['nominal']
    for k in range(n_nom):
        est = _estimate(model, p0, int(rng.integers(1e9)))
        flagged = [g.name for g in FIVE if classify_fault(
            g.name, est.values[g.name], est.stds[g.name], lim)[0] > 0]
        if flagged:
            alarms.append(flagged)
    out['nominal'] = {'runs': n_nom, 'false_alarms': len(alarms), 'flagged': alarms}
    out['validation'] = {k: model.meta.get(k) for k in (
        'validation_mean_abs_error_pct', 'validation_within_2sigma', 'calibration',
        'combination_within_2sigma')}
    return out


def bench_in_service(p0, lim, size):
    est = InServiceEstimator(p0, limits=lim)
    rows = []
    seeds = size['seeds']
    for valve, (clr, lap) in list(VALVES.items())[:size['in_service_valves']]:
        p = replace(p0, radial_clearance_m=clr, overlap_supply_m=lap, overlap_return_m=lap)
        for sc in SCENARIOS[:size['scenarios']]:
            for seed in seeds:
                r = simulate(p, sc, controller_period_s=1e-3, record_dt_s=1e-3, seed=seed)
                t = r['time_s']
                k = (t >= 0.05) & (t >= t.max() - 1.0)
                e = est.estimate(r['spool_position_m'][k], r['load_flow_m3_s'][k],
                                 r['p12_pa'][k])
                level, text = classify(e, lim)
                covered = (abs(e.radial_clearance_m - clr) <= 2 * e.radial_clearance_std_m
                           and abs(e.overlap_m - lap) <= 2 * e.overlap_std_m)
                rows.append({'valve': valve, 'scenario': sc, 'seed': seed,
                             'clearance_um': round(e.radial_clearance_m * 1e6, 3),
                             'clearance_std_um': round(e.radial_clearance_std_m * 1e6, 3),
                             'overlap_um': round(e.overlap_m * 1e6, 3),
                             'overlap_std_um': round(e.overlap_std_m * 1e6, 3),
                             'correlation': round(e.correlation, 3), 'covered': covered,
                             'separable': 'not separable' not in text,
                             'level': LEVEL_NAMES[level]})
    nominal = [r for r in rows if r['valve'] == 'nominal']
    worn = [r for r in rows if r['valve'] != 'nominal']
    return {'runs': len(rows),
            'coverage_2sigma': round(np.mean([r['covered'] for r in rows]), 3),
            'coverage_2sigma_nominal': round(np.mean([r['covered'] for r in nominal]), 3),
            'coverage_2sigma_worn': round(np.mean([r['covered'] for r in worn]), 3),
            'false_alarms_nominal': sum(r['level'] != 'OK' for r in nominal),
            'nominal_runs': len(nominal),
            'worn_detected': sum(r['level'] != 'OK' for r in worn), 'worn_runs': len(worn),
            'labelled_separable_but_not_covered': sum(r['separable'] and not r['covered']
                                                      for r in rows),
            'labelled_not_separable': sum(not r['separable'] for r in rows),
            'rows': rows}


def bench_realtime(seconds):
    from types import SimpleNamespace

    from eha_ros.harness import GraphConfig, run_graph
    from eha_ros.physics import load_params
    from eha_ros.health.monitor import MonitorCore
    from eha_ros.isolation import ros_environment
    with ros_environment() as env:
        r = run_graph(GraphConfig(scenario='sine_0p1_5pi', model='hf', mode='realtime',
                                  duration_s=float(seconds), health=True),
                      processes=True, env=env, timeout_s=120)
    # the schedule the monitor followed on the states it received: one estimate per
    # update_period_s of state time (MonitorCore without running the fits)
    core = MonitorCore(load_params(), HealthThresholds.load(), valve_test=None, faults=None)
    st = r.state
    s = SimpleNamespace(valve_test_point=0, valve_test_point_end=False)
    due = 0
    for k in range(st['stamp_ns'].size):
        s.status, s.sim_time_s = int(st['status'][k]), float(st['sim_time_s'][k])
        s.spool_position_m, s.load_flow_m3_s = st['spool_position_m'][k], st['load_flow_m3_s'][k]
        s.p12_pa = st['p12_pa'][k]
        due += len(core.on_state(int(st['stamp_ns'][k]), s))
    made = sum(1 for h in r.health if h.method == 'steady-fit')
    return {'seconds': seconds, 'states_received': int(st['stamp_ns'].size),
            'estimates_scheduled': due, 'estimates_made': made,
            'fraction_made': round(made / max(due, 1), 3), 'wall_s': round(r.wall_s, 1)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--realtime-s', type=float, default=20.0)
    ap.add_argument('--quick', action='store_true', help='fewer cases')
    ap.add_argument('--smoke', action='store_true',
                    help='the fewest cases through every section: a check, no figure')
    ap.add_argument('--no-drift', action='store_true', help='skip the drifted sets')
    ap.add_argument('--workers', type=int, default=None,
                    help='sweep workers of the drifted sets (default 2, with --smoke 1)')
    args = ap.parse_args()
    size_name = 'smoke' if args.smoke else 'quick' if args.quick else 'full'
    size = SIZES[size_name]
    if args.workers is None:
        args.workers = 1 if args.smoke else 2
    if args.smoke and args.realtime_s == ap.get_default('realtime_s'):
        args.realtime_s = 1.0
    p0 = default_params()
    lim = HealthThresholds.load()
    t0 = time.perf_counter()
    out = {'benchmark': 'health', 'smoke': args.smoke, 'size': size_name,
           'load_before': [round(x, 2) for x in os.getloadavg()]}
    if not args.no_drift:
        from health_valve import SETS as VALVE_SETS, valve_drift
        from health_preflight import (SETS as PREFLIGHT_SETS, SIZES as PREFLIGHT_SIZES,
                                      SMOKE_SIZES, preflight_drift)
        out['valve_test_drift'] = valve_drift(
            args.workers, size_name, only=VALVE_SETS[:1] if args.smoke else VALVE_SETS)
        out['preflight_drift'] = preflight_drift(
            workers=args.workers, sizes=SMOKE_SIZES if args.smoke else PREFLIGHT_SIZES,
            only=PREFLIGHT_SETS[:1] if args.smoke else PREFLIGHT_SETS)
    out['valve_test'] = bench_valve_test(p0, size)
    out['preflight'] = bench_preflight(p0, lim, size)
    out['in_service'] = bench_in_service(p0, lim, size)
    if args.realtime_s > 0:
        out['realtime'] = bench_realtime(args.realtime_s)
    out['load_after'] = [round(x, 2) for x in os.getloadavg()]
    out['wall_s'] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
