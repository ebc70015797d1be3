"""Accuracy of the dynamic surrogates (``dlut``, ``dnn``, ``dga``) against the hf model's edge
equations: one edge's relative flow error on fresh random inputs, and the chamber flows against
``valve_flows`` at nominal wear and two off-grid wear points (relative to the largest flow at
each spool position); the kernel's cost per call (``kernel_ns_per_call``: one call = the four
edges of a plant step, on a 0.2 s trajectory of spool position and chamber pressures sampled
every 1 us, best of 7, JIT excluded; hf's ``valve_flows`` beside them); with ``--refit`` also
the GA-form function refitted by the genetic algorithm and by the gradient fit (same
objective), with their times.  Prints one JSON object.

    python bench/surrogates_dynamic.py [--refit] [--n 20000]
"""

import argparse
import json
import time

import numpy as np
from numba import njit

from eha_ros.graph import DYNAMIC_MODELS
from eha_ros.physics import default_params
from eha_ros.physics.valve import valve_flows
from eha_ros.artefacts import models_dir
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.training.dynamic import build_dga, chamber_errors, edge_errors


@njit(cache=True)
def _hf_loop(xs, p1, p2, p, out1, out2):
    """hf's flows over the points, as a surrogate's compiled loop over points runs its
    kernel (:data:`eha_ros.surrogates.base.Forms`; for the timing)."""
    for i in range(xs.size):
        out1[i], out2[i] = valve_flows(xs[i], p1[i], p2[i], p)


def _trajectory(n=200000):
    """Spool near null (a few um, as in the small-signal cases) and chamber pressures moving
    about half supply, every 1 us."""
    t = np.arange(n) * 1e-6
    xs = 3e-6 * np.sin(2 * np.pi * 50 * t) + 1e-6 * np.sin(2 * np.pi * 7 * t)
    p1 = 1.03e7 + 2e6 * np.sin(2 * np.pi * 31 * t)
    return xs, p1, 2.12e7 - p1


def _best_ns(fn, n, repeat=7):
    fn()
    best = float('inf')
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return round(best / n * 1e9, 1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--n', type=int, default=20000)
    ap.add_argument('--refit', action='store_true')
    ap.add_argument('--smoke', action='store_true',
                    help='the same code on tiny sets (no refit): a check, no figure')
    args = ap.parse_args()
    if args.smoke:
        args.n, args.refit = 400, False
    out = {'benchmark': 'surrogates_dynamic', 'smoke': args.smoke, 'models': {}}
    p = default_params()
    xs, p1, p2 = _trajectory(2000 if args.smoke else 200000)
    o1, o2 = np.empty(xs.size), np.empty(xs.size)
    lap_s, lap_r = np.full(xs.size, p.overlap_supply_m), np.full(xs.size, p.overlap_return_m)
    out['hf_valve_flows_ns_per_call'] = _best_ns(lambda: _hf_loop(xs, p1, p2, p, o1, o2),
                                                 xs.size)
    for name in DYNAMIC_MODELS:
        s = load_surrogate(name)
        data = s.prepare(p)
        ns = _best_ns(lambda: s.forms.points(data, xs, p1, p2, lap_s, lap_r, o1, o2),
                      xs.size)
        t0 = time.perf_counter()
        grid = {'n_xs': 7, 'n_p': 7} if args.smoke else {}
        out['models'][name] = {'edge_flow_relative': edge_errors(s, n=args.n, seed=5),
                               'chamber_flow_relative_to_max': chamber_errors(s, **grid),
                               'artefact_bytes': (models_dir('surrogates')
                                                  / f'{name}.npz').stat().st_size,
                               'kernel_ns_per_call': ns}
        out['models'][name]['eval_s'] = round(time.perf_counter() - t0, 2)
    if args.refit:
        _, meta = build_dga()
        out['dga_refit'] = {'ga': meta['ga'], 'gradient_fit': meta['gradient_fit'],
                            'hf_values': meta['hf_values']['coefficients']}
    print(json.dumps(out))


if __name__ == '__main__':
    main()
