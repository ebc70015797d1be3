"""Every surrogate side by side: held-out error in the reference's metric, per-call and batch
inference time, training time, and what a user would pick instead (scipy
``RegularGridInterpolator`` for the LUT, scipy ``differential_evolution`` for the GA,
scikit-learn ``MLPRegressor`` for the networks).  Prints one JSON object merging
``bench/surrogates_lut_ga.py`` and ``bench/surrogates_nn.py``.

    python bench/surrogates.py [--smoke]   # needs requirements-bench.txt (scikit-learn)

``--smoke``: both benches on their tiny sets (a check that they run, no figure).
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import surrogates_lut_ga  # noqa: E402
import surrogates_nn  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--smoke', action='store_true',
                    help='both benches on tiny sets: a check, no figure')
    a = ap.parse_args()
    print(json.dumps({'benchmark': 'surrogates', 'smoke': a.smoke,
                      'lut_ga': surrogates_lut_ga.run(smoke=a.smoke),
                      'nn': surrogates_nn.run(smoke=a.smoke)}))


if __name__ == '__main__':
    main()
