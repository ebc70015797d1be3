"""The first plant run of each model in a fresh process: what a node, a sweep worker or a
script pays before its first tick, against the same run once compiled.

Each model is timed in a process of its own (``python -c``): import, load, then 10 ms of the
closed loop on ``step_0p1`` at 1 us (``first_s``), then the same run again in that process
(``again_s``).  The shipped surrogates' loops are compiled once and cached on disk
(:class:`eha_ros.surrogates.base.Forms`), so ``first_s`` is loading, not compiling, once
the cache holds them; the first call of all (an empty cache, as on a fresh clone) compiles
and writes it.  Run it twice to see both.  Prints one JSON object, with the load average.

    python bench/first_run.py [--models hf,lut,dlut] [--smoke]
"""

import argparse
import json
import os
import subprocess
import sys
import time

CHILD = r'''
import json, sys, time
t0 = time.perf_counter()
from eha_ros.physics import default_params, simulate
from eha_ros.surrogates.registry import load_surrogate
p = default_params()
name = sys.argv[1]
fluid = None if name == 'hf' else load_surrogate(name, p)
t1 = time.perf_counter()
runs = []
for _ in range(2):
    t = time.perf_counter()
    simulate(p, 'step_0p1', duration_s=0.01, dt_s=1e-6, controller_period_s=1e-3,
             record_dt_s=None, fluid=fluid)
    runs.append(time.perf_counter() - t)
print(json.dumps({'import_load_s': t1 - t0, 'first_s': runs[0], 'again_s': runs[1]}))
'''

ALL = ('hf', 'lut', 'ga', 'nn', 'nn2', 'dlut', 'dnn', 'dga')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--models', default=','.join(ALL))
    ap.add_argument('--smoke', action='store_true', help='hf and lut only: a check, no figure')
    a = ap.parse_args(argv)
    models = ['hf', 'lut'] if a.smoke else a.models.split(',')
    bad = [m for m in models if m not in ALL]
    if bad:
        print(f'first_run: error: unknown model {bad[0]!r} (one of {", ".join(ALL)})',
              file=sys.stderr)
        return 2
    out = {'benchmark': 'first_run', 'smoke': a.smoke, 'scenario': 'step_0p1',
           'duration_s': 0.01, 'dt_s': 1e-6, 'load_before': os.getloadavg()[0], 'models': {}}
    for m in models:
        t = time.perf_counter()
        r = subprocess.run([sys.executable, '-c', CHILD, m], capture_output=True, text=True)
        if r.returncode != 0:
            print(f'first_run: error: {m}: {r.stderr.strip().splitlines()[-1]}',
                  file=sys.stderr)
            return 1
        res = json.loads(r.stdout.strip().splitlines()[-1])
        res['process_s'] = time.perf_counter() - t
        out['models'][m] = {k: round(v, 3) for k, v in res.items()}
    out['load_after'] = os.getloadavg()[0]
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
