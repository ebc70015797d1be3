"""The first plant run of each model in a fresh process: what a node, a sweep worker or a
script pays before its first tick, against the same run once compiled.

Each model is timed in a process of its own (``python -c``): import, load, then 10 ms of the
closed loop on ``step_0p1`` at 1 us (``first_s``), then the same run again in that process
(``again_s``).  The shipped surrogates' loops are compiled once and cached on disk
(:class:`eha_ros.surrogates.base.Forms`), so ``first_s`` is loading, not compiling, once
the cache holds them; the first call of all (an empty cache, as on a fresh clone) compiles
and writes it.  Run it twice to see both, or with ``--cold``: each process then starts from an
empty cache of its own (a temporary ``NUMBA_CACHE_DIR``), so ``first_s`` is the compile.

``--inline-copy both`` (with ``--cold``) times each model twice, alternating in one run: with
the package's copy of an inlined callee (one scope for all its blocks,
:func:`eha_ros.jit_cache.share_inline_copies`) and with numba's own per-block copy, and prints
the ratio of their ``first_s``.  ``--blas-probe both`` does the same for numba's BLAS probe:
the package's look for the file (:func:`eha_ros.jit_cache.defer_blas_probe`) against numba's
import of ``scipy.linalg``, at the first kernel load of a process (without ``--cold``: a
loaded kernel, as a node's start has it).  Each child also reports its CPU time
(``cpu_s``).  Prints one JSON object, with the load average.

    python bench/first_run.py [--models hf,lut,dlut] [--cold]
                              [--inline-copy shared|per-block|both]
                              [--blas-probe files|numba|both] [--smoke]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

CHILD = r'''
import json, sys, time
t0 = time.perf_counter()
if sys.argv[2] == 'per-block':  # numba's own copy: mark it as the package's, which then keeps it
    from numba.core.inline_closurecall import InlineWorker
    InlineWorker.inline_ir.shared_copy = True
if sys.argv[3] == 'numba':  # numba's own BLAS probe: mark the package's as installed
    from numba.core.cpu import CPUContext
    CPUContext.load_additional_registries.deferred_blas_probe = True
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
print(json.dumps({'import_load_s': t1 - t0, 'first_s': runs[0], 'again_s': runs[1],
                  'cpu_s': time.process_time()}))
'''

ALL = ('hf', 'lut', 'ga', 'nn', 'nn2', 'dlut', 'dnn', 'dga')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--models', default=','.join(ALL))
    ap.add_argument('--cold', action='store_true',
                    help='each process from an empty numba cache of its own: the compile')
    ap.add_argument('--inline-copy', choices=('shared', 'per-block', 'both'), default='shared',
                    help="the package's copy of an inlined callee, numba's own, or both "
                         'alternating (with their ratio)')
    ap.add_argument('--blas-probe', choices=('files', 'numba', 'both'), default='files',
                    help="numba's import-time BLAS probe by the package's file check, by "
                         "numba's import of scipy.linalg, or both alternating (with their "
                         'ratio)')
    ap.add_argument('--smoke', action='store_true', help='hf and lut only: a check, no figure')
    a = ap.parse_args(argv)
    models = ['hf', 'lut'] if a.smoke else a.models.split(',')
    bad = [m for m in models if m not in ALL]
    if bad:
        print(f'first_run: error: unknown model {bad[0]!r} (one of {", ".join(ALL)})',
              file=sys.stderr)
        return 2
    if a.inline_copy == 'both' and not a.cold:
        print('first_run: error: --inline-copy both compares compiles: add --cold (from a '
              'shared cache the second run would load what the first compiled)', file=sys.stderr)
        return 2
    if a.inline_copy == 'both' and a.blas_probe == 'both':
        print('first_run: error: compare one thing at a time: --inline-copy both or '
              '--blas-probe both', file=sys.stderr)
        return 2
    if a.inline_copy == 'both':
        variants = [(c, a.blas_probe, f'{c} copy') for c in ('shared', 'per-block')]
    elif a.blas_probe == 'both':
        variants = [(a.inline_copy, b, f'{b} probe') for b in ('files', 'numba')]
    else:
        variants = [(a.inline_copy, a.blas_probe, None)]
    out = {'benchmark': 'first_run', 'smoke': a.smoke, 'scenario': 'step_0p1',
           'duration_s': 0.01, 'dt_s': 1e-6, 'cold': a.cold, 'inline_copy': a.inline_copy,
           'blas_probe': a.blas_probe,
           'load_before': os.getloadavg()[0], 'models': {}}
    for m in models:
        for copy, probe, label in variants:
            res = _child(m, copy, probe, a.cold)
            if isinstance(res, str):
                print(f'first_run: error: {m} ({label or "default"}): {res}', file=sys.stderr)
                return 1
            key = m if label is None else f'{m} ({label})'
            out['models'][key] = {k: round(v, 3) for k, v in res.items()}
        if len(variants) == 2:
            new, old = (out['models'][f'{m} ({v[2]})'] for v in variants)
            names = ' / '.join(v[2].split()[0] for v in variants)
            out['models'][m] = {f'{k} ratio, {names}': round(new[k] / old[k], 3)
                                for k in ('first_s', 'cpu_s')}
    out['load_after'] = os.getloadavg()[0]
    print(json.dumps(out))
    return 0


def _child(model: str, copy: str, probe: str, cold: bool) -> dict | str:
    """One model's first runs in a fresh process (:data:`CHILD`): its figures, or the last
    line of its error."""
    with tempfile.TemporaryDirectory(prefix='first_run_cache_') as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache) if cold else None
        t = time.perf_counter()
        r = subprocess.run([sys.executable, '-c', CHILD, model, copy, probe], capture_output=True,
                           text=True, env=env)
        if r.returncode != 0:
            return (r.stderr.strip().splitlines() or ['exit status %d' % r.returncode])[-1]
        res = json.loads(r.stdout.strip().splitlines()[-1])
        res['process_s'] = time.perf_counter() - t
        return res


if __name__ == '__main__':
    sys.exit(main())
