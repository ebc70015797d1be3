"""Real-time factor of the high-fidelity closed loop on one core.

Prints one JSON object: simulated seconds per wall second at dt = 1 us, with the controller
evaluated every plant step (the reference's continuous PID) and at 1 kHz (the ROS graph's
rate), for a step and a sine command; best of ``--repeat`` runs after a warm-up (JIT
compilation excluded and reported separately).

    python bench/plant_rtf.py [--duration 1.0] [--repeat 3]
"""

import argparse
import json
import os
import platform
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

from eha_ros.physics import default_params, simulate  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--duration', type=float, default=1.0)
    ap.add_argument('--repeat', type=int, default=3)
    args = ap.parse_args()
    p = default_params()
    t0 = time.perf_counter()
    simulate(p, 'step_0p1', duration_s=1e-3)
    simulate(p, 'step_0p1', duration_s=1e-3, controller_period_s=1e-3)
    warmup = time.perf_counter() - t0
    out = {'benchmark': 'plant_rtf', 'dt_s': 1e-6, 'simulated_s': args.duration,
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
    print(json.dumps(out))


if __name__ == '__main__':
    main()
