"""Wear estimation accuracy: in-service fit over the reference's scenarios and the diagnostic
valve test, for a nominal and three worn valves.

Prints one JSON object.  ``in_service``: for each valve and scenario (physics-only closed loop,
1 kHz controller, samples at 1 kHz after 50 ms) the steady-fit estimate, its error [um], the
nominal valve's residual over the best fit's (``ratio``) and the level it gets.  ``valve_test``:
the diagnostic network on the three curves of the ``valve_test`` scenario.  ``summary``: false
alarms (a nominal valve graded WARN/ERROR), missed detections (a worn valve graded OK), the
error where a level was raised, and the ratio ranges.

    python bench/health.py [--scenarios a,b]
"""

import argparse
import json
import time

import numpy as np

from eha_ros.graph import LEVEL_NAMES as LEVELS, REFERENCE_SCENARIOS as SCENARIOS
from eha_ros.physics import default_params, get_scenario, simulate
from eha_ros.physics.maps import spool_grid, transient_map
from eha_ros.physics.params import replace
from eha_ros.surrogates.health import (HealthThresholds, InServiceEstimator, ValveTestEstimator,
                                       classify)

VALVES = {'nominal': (2.5e-6, 1e-6), 'clearance_4p5': (4.5e-6, 1e-6),
          'underlap_1': (2.5e-6, -1e-6), 'worn': (4.5e-6, -0.5e-6)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--scenarios', default=','.join(SCENARIOS))
    args = ap.parse_args()
    p0 = default_params()
    lim = HealthThresholds.load()
    est = InServiceEstimator(p0, max_samples=400)
    net = ValveTestEstimator(p0)
    flows = get_scenario('valve_test').valve_test_flows_m3_s
    xs = spool_grid(133, p0.spool_stroke_m)
    out = {'benchmark': 'health', 'anomaly_ratio': lim.anomaly_ratio,
           'model_bias_pa': lim.model_bias_pa, 'in_service': {},
           'valve_test': {}}
    t0 = time.perf_counter()
    for valve, (clr, lap) in VALVES.items():
        p = replace(p0, radial_clearance_m=clr, overlap_supply_m=lap, overlap_return_m=lap)
        rows = {}
        for sc in args.scenarios.split(','):
            r = simulate(p, sc, controller_period_s=1e-3, record_dt_s=1e-3)
            k = r['time_s'] >= 0.05
            e = est.estimate(r['spool_position_m'][k], r['load_flow_m3_s'][k], r['p12_pa'][k])
            level, _ = classify(e, lim)
            rows[sc] = {'clearance_um': round(e.radial_clearance_m * 1e6, 3),
                        'overlap_um': round(e.overlap_m * 1e6, 3),
                        'clearance_error_um': round((e.radial_clearance_m - clr) * 1e6, 3),
                        'overlap_error_um': round((e.overlap_m - lap) * 1e6, 3),
                        'residual_kpa': round(e.pressure_residual_pa / 1e3, 1),
                        'nominal_residual_kpa': round(e.nominal_residual_pa / 1e3, 1),
                        'ratio': round(e.nominal_residual_pa / max(e.pressure_residual_pa,
                                                                   lim.model_bias_pa), 2),
                        'level': LEVELS[level]}
        out['in_service'][valve] = rows
        curves = [(q, xs, transient_map(xs, q, params=p)['p12_pa']) for q in flows]
        e = net.estimate(curves)
        out['valve_test'][valve] = {
            'clearance_error_um': round((e.radial_clearance_m - clr) * 1e6, 4),
            'overlap_error_um': round((e.overlap_m - lap) * 1e6, 4),
            'residual_kpa': round(e.pressure_residual_pa / 1e3, 2),
            'level': LEVELS[classify(e, lim)[0]]}
    rows = [(v, sc, r) for v, d in out['in_service'].items() for sc, r in d.items()]
    raised = [r for v, sc, r in rows if r['level'] != 'OK']
    out['summary'] = {
        'runs': len(rows),
        'false_alarms': sum(1 for v, sc, r in rows if v == 'nominal' and r['level'] != 'OK'),
        'missed_detections': sum(1 for v, sc, r in rows if v != 'nominal' and r['level'] == 'OK'),
        'worn_runs': sum(1 for v, sc, r in rows if v != 'nominal'),
        'nominal_ratio_range': [min(r['ratio'] for v, sc, r in rows if v == 'nominal'),
                                max(r['ratio'] for v, sc, r in rows if v == 'nominal')],
        'worn_ratio_range': [min(r['ratio'] for v, sc, r in rows if v != 'nominal'),
                             max(r['ratio'] for v, sc, r in rows if v != 'nominal')],
        'max_abs_error_um_where_raised': max(
            (max(abs(r['clearance_error_um']), abs(r['overlap_error_um'])) for r in raised),
            default=None),
        'valve_test_max_abs_error_um': max(max(abs(r['clearance_error_um']),
                                               abs(r['overlap_error_um']))
                                           for r in out['valve_test'].values()),
        'wall_s': round(time.perf_counter() - t0, 1)}
    print(json.dumps(out))


if __name__ == '__main__':
    main()
