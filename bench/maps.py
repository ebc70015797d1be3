"""Throughput of the characteristic-map generator (the reference's transient: spool fixed,
flow imposed, pressures from zero, 1e-2 s at 1e-6 s).

Prints one JSON object: point-steps per second on all cores, and the wall time of a
DB4-size set (133 spool positions x 15 flows x 30 overlaps x 30 clearances = 1,795,500
points), measured on the full set (``--full``) or extrapolated from ``--maps`` of its maps.

    python bench/maps.py [--maps 60] [--full]
"""

import argparse
import json
import os
import time

import numpy as np

from eha_ros.physics import default_params
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, transient_map


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--maps', type=int, default=60, help='maps timed when not --full')
    ap.add_argument('--full', action='store_true', help='time the whole DB4-size set')
    ap.add_argument('--smoke', action='store_true',
                    help='the same code on two maps: a check, no figure')
    args = ap.parse_args()
    if args.smoke:
        args.maps, args.full = 2, False
    p = default_params()
    xs = spool_grid(133)
    q = np.linspace(-5e-5, 5e-5, 15)
    laps = np.linspace(*WEAR_RANGES['overlap_m'], 30)
    clrs = np.linspace(*WEAR_RANGES['radial_clearance_m'], 30)
    lap_g, clr_g = [a.ravel() for a in np.meshgrid(laps, clrs, indexing='ij')]
    n_maps = lap_g.size if args.full else min(args.maps, lap_g.size)
    sel = np.linspace(0, lap_g.size - 1, n_maps).astype(int)
    transient_map(xs[:3], 0.0, t_end_s=1e-5)  # JIT warm-up
    shape = (133, 15, n_maps)
    t0 = time.perf_counter()
    r = transient_map(xs[:, None, None], q[None, :, None], lap_g[sel][None, None, :],
                      clr_g[sel][None, None, :], params=p)
    wall = time.perf_counter() - t0
    points = int(np.prod(shape))
    steps = 10_000
    rate = points * steps / wall
    db4_points = 133 * 15 * 30 * 30
    print(json.dumps({
        'benchmark': 'maps', 'smoke': args.smoke, 't_end_s': 1e-2, 'dt_s': 1e-6, 'points': points,
        'maps_timed': n_maps, 'wall_s': round(wall, 3),
        'point_steps_per_s': float(f'{rate:.4g}'),
        'db4_points': db4_points,
        'db4_wall_s': round(wall if args.full else db4_points * steps / rate, 2),
        'db4_measured': bool(args.full),
        'threads': int(os.environ.get('NUMBA_NUM_THREADS', os.cpu_count())),
        'finite': bool(np.all(np.isfinite(r['p12_pa'])))}))


if __name__ == '__main__':
    main()
