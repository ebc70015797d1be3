"""Every surrogate side by side: held-out error in the reference's metric, per-call and batch
inference time, training time, and what a user would pick instead (scipy
``RegularGridInterpolator`` for the LUT, scipy ``differential_evolution`` for the GA,
scikit-learn ``MLPRegressor`` for the networks).  Prints one JSON object merging
``bench/surrogates_lut_ga.py`` and ``bench/surrogates_nn.py``.

    python bench/surrogates.py          # needs requirements-bench.txt (scipy, scikit-learn)
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import surrogates_lut_ga  # noqa: E402
import surrogates_nn  # noqa: E402


def main():
    print(json.dumps({'benchmark': 'surrogates', 'lut_ga': surrogates_lut_ga.run(),
                      'nn': surrogates_nn.run()}))


if __name__ == '__main__':
    main()
