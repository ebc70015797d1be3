"""Real-time factor of the high-fidelity closed loop on one core.

Prints one JSON object: simulated seconds per wall second at dt = 1 us, with the controller
evaluated every plant step (the reference's continuous PID) and at 1 kHz (the ROS graph's
rate), for a step and a sine command; best of ``--repeat`` runs after a warm-up (JIT
compilation excluded and reported separately).

With ``--models`` (default: every shipped surrogate) it adds one row per fluid model: the
plant with that surrogate in place of the hf fluid block, controller at 1 kHz, same commands,
at dt = 1 us and, for hf and the dynamic surrogates, at each of ``--large-dts`` (the larger
steps at which ``bench/inloop.py`` measures them against hf at 1 us): wall seconds per simulated
second and the ratio to hf's at 1 us.

    python bench/plant_rtf.py [--duration 1.0] [--repeat 3] [--models dlut,dnn,dga,lut,...]
        [--large-dts 2e-6,5e-6]
"""

import argparse
import json
import os
import platform
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

from eha_ros.graph import DYNAMIC_MODELS, MODELS  # noqa: E402
from eha_ros.physics import default_params, simulate  # noqa: E402
from eha_ros.surrogates.registry import load_surrogate  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--duration', type=float, default=1.0)
    ap.add_argument('--repeat', type=int, default=3)
    ap.add_argument('--models', default=','.join(m for m in MODELS if m != 'hf'))
    ap.add_argument('--large-dts', default='2e-6,5e-6')
    ap.add_argument('--smoke', action='store_true',
                    help='the same code on a tiny case (10 ms, one repeat, dlut and lut): a check')
    args = ap.parse_args()
    if args.smoke:
        args.duration, args.repeat, args.large_dts = 0.01, 1, '5e-6'
        if args.models == ap.get_default('models'):
            args.models = 'dlut,lut'  # one dynamic, one static: each model compiles anew
    p = default_params()
    t0 = time.perf_counter()
    simulate(p, 'step_0p1', duration_s=1e-3)
    simulate(p, 'step_0p1', duration_s=1e-3, controller_period_s=1e-3)
    warmup = time.perf_counter() - t0
    out = {'benchmark': 'plant_rtf', 'smoke': args.smoke,
           'dt_s': 1e-6, 'simulated_s': args.duration,
           'jit_warmup_s': round(warmup, 3), 'cpu': platform.processor() or platform.machine(),
           'cases': {}}
    for scenario in ('step_0p1', 'sine_0p1_10pi'):
        for label, period in (('controller_every_step', None), ('controller_1khz', 1e-3)):
            walls = []
            for _ in range(args.repeat):
                r = simulate(p, scenario, duration_s=args.duration, dt_s=1e-6,
                             controller_period_s=period)
                walls.append(r.wall_time_s)
            best = min(walls)
            out['cases'][f'{scenario}/{label}'] = {
                'wall_s': round(best, 5), 'real_time_factor': round(args.duration / best, 2),
                'ns_per_step': round(best / (args.duration / 1e-6) * 1e9, 1)}
    out['real_time_factor'] = out['cases']['step_0p1/controller_every_step']['real_time_factor']
    out['real_time_factor_1khz_controller'] = out['cases']['step_0p1/controller_1khz'][
        'real_time_factor']
    models = [m for m in args.models.split(',') if m]
    out['models'] = {}
    large = [float(v) for v in args.large_dts.split(',') if v]
    for model in ['hf'] + models:
        fluid = None if model == 'hf' else load_surrogate(model, p)
        dts = [1e-6] + (large if model == 'hf' or model in DYNAMIC_MODELS else [])
        for dt in dts:
            simulate(p, 'step_0p1', duration_s=2e-3, dt_s=dt, controller_period_s=1e-3,
                     fluid=fluid)  # compile
            row = {}
            for scenario in ('step_0p1', 'sine_0p1_10pi'):
                best = min(simulate(p, scenario, duration_s=args.duration, dt_s=dt,
                                    controller_period_s=1e-3, fluid=fluid).wall_time_s
                           for _ in range(args.repeat))
                row[scenario] = {'wall_s_per_simulated_s': round(best / args.duration, 5),
                                 'ns_per_step': round(best / (args.duration / dt) * 1e9, 1)}
            out['models'][f'{model}@dt={dt:g}'] = row
    hf_cost = {sc: out['models']['hf@dt=1e-06'][sc]['wall_s_per_simulated_s']
               for sc in ('step_0p1', 'sine_0p1_10pi')}
    for row in out['models'].values():
        for sc, v in row.items():
            v['cost_vs_hf'] = round(v['wall_s_per_simulated_s'] / hf_cost[sc], 3)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
