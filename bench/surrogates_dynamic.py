"""Accuracy of the dynamic surrogates (``dlut``, ``dnn``, ``dga``) against the hf model's edge
equations: one edge's relative flow error on fresh random inputs, and the chamber flows against
``valve_flows`` at nominal wear and two off-grid wear points (relative to the largest flow at
each spool position); with ``--refit`` also the GA-form function refitted by the genetic
algorithm and by the gradient fit (same objective), with their times.  Prints one JSON object.

    python bench/surrogates_dynamic.py [--refit] [--n 20000]
"""

import argparse
import json
import time

from eha_ros.graph import DYNAMIC_MODELS
from eha_ros.surrogates.base import load_surrogate, models_dir
from eha_ros.surrogates.dynamic_train import build_dga, chamber_errors, edge_errors


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--n', type=int, default=20000)
    ap.add_argument('--refit', action='store_true')
    args = ap.parse_args()
    out = {'benchmark': 'surrogates_dynamic', 'models': {}}
    for name in DYNAMIC_MODELS:
        s = load_surrogate(name)
        t0 = time.perf_counter()
        out['models'][name] = {'edge_flow_relative': edge_errors(s, n=args.n, seed=5),
                               'chamber_flow_relative_to_max': chamber_errors(s),
                               'artefact_bytes': (models_dir() / f'{name}.npz').stat().st_size}
        out['models'][name]['eval_s'] = round(time.perf_counter() - t0, 2)
    if args.refit:
        _, meta = build_dga()
        out['dga_refit'] = {'ga': meta['ga'], 'gradient_fit': meta['gradient_fit'],
                            'hf_values': meta['hf_values']['coefficients']}
    print(json.dumps(out))


if __name__ == '__main__':
    main()
