"""Surrogates in the closed loop against hf, judged against hf's own sensitivity: prints one
JSON object (:mod:`eha_ros.surrogates.inloop` defines every figure).

Cases: the reference's nine scenarios, ``step_1mm`` (large signal) and ``chirp_0p1``, at
nominal wear and two off-grid wear points (off the wear grids of every table).  Noise-free:
errors, yardstick, bounds and features per case, every model, and the dynamic surrogates again
at ``--large-dt`` (2 us) against hf at 1 us.  With noise (nominal wear): ``--seeds`` seeds.
Cost: wall seconds per simulated second of each run against hf's (JIT compilation excluded:
every model runs once before).

    nice python bench/inloop.py [--models dlut,dnn,dga,lut,ga,nn,nn2] [--seeds 5]
        [--scenarios a,b] [--no-noise] [--wear nominal|all] [--out FILE]
"""

import argparse
import json
import os
import sys
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

from eha_ros.graph import MODELS, REFERENCE_SCENARIOS  # noqa: E402
from eha_ros.physics import default_params  # noqa: E402
from eha_ros.physics.params import replace  # noqa: E402
from eha_ros.surrogates.base import load_surrogate  # noqa: E402
from eha_ros.surrogates.inloop import (CONTROLLER_PERIOD_S, DT_S, EXTRA_SCENARIOS,  # noqa
                                       WEAR, largest_steps, noise_free, run,
                                       summarise, with_noise)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument('--models', default='dlut,dnn,dga,lut,ga,nn,nn2')
    ap.add_argument('--scenarios', default=','.join(REFERENCE_SCENARIOS + EXTRA_SCENARIOS))
    ap.add_argument('--wear', choices=('nominal', 'all'), default='all')
    ap.add_argument('--seeds', type=int, default=20)
    ap.add_argument('--noise-models', default='dlut,dnn,dga,lut,ga',
                    help='models run with noise over the seeds (those also in --models)')
    ap.add_argument('--no-noise', action='store_true')
    ap.add_argument('--large-dts', default='2e-6,5e-6,1e-5',
                    help='also run hf and the dynamic surrogates at these steps [s] ("": none)')
    ap.add_argument('--out', default=None, help='also write the JSON here')
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    base = default_params()
    p0 = replace(base, noise_std_a=0.0)
    models = [m for m in args.models.split(',') if m]
    unknown = [m for m in models if m not in MODELS or m == 'hf']
    if unknown:
        print(f'inloop: error: unknown model(s) {", ".join(unknown)}', file=sys.stderr)
        return 2
    scenarios = [s for s in args.scenarios.split(',') if s]
    try:
        large_dts = [float(v) for v in args.large_dts.split(',') if v]
    except ValueError:
        print(f'inloop: error: --large-dts {args.large_dts!r} is not a list of steps [s]',
              file=sys.stderr)
        return 2
    for m in models:  # compile every model's loop first: costs exclude JIT compilation
        run(p0, 'step_0p1', load_surrogate(m, base), dt=1e-6)
    run(p0, 'step_0p1')
    wear = WEAR if args.wear == 'all' else {'nominal': None}
    result = {'benchmark': 'inloop', 'dt_s': DT_S, 'controller_period_s': CONTROLLER_PERIOD_S,
              'models': models, 'scenarios': scenarios,
              'wear': {k: v for k, v in wear.items()}, 'noise_free': {}, 'noise': {}}
    for wname, w in wear.items():
        p = p0 if w is None else replace(p0, overlap_supply_m=w[0], overlap_return_m=w[0],
                                         radial_clearance_m=w[1])
        sur = {m: load_surrogate(m, base) for m in models}
        for sc in scenarios:
            result['noise_free'][f'{sc}/{wname}'] = noise_free(p, sc, sur, large_dts)
            print(f'inloop: {sc}/{wname} done at {time.perf_counter() - t0:.0f} s',
                  file=sys.stderr, flush=True)
    if not args.no_noise and args.seeds > 0:
        sur = {m: load_surrogate(m, base) for m in models
               if m in args.noise_models.split(',')}
        for sc in scenarios:
            result['noise'][sc] = with_noise(base, sc, sur, args.seeds)
            print(f'inloop: noise {sc} done at {time.perf_counter() - t0:.0f} s',
                  file=sys.stderr, flush=True)
    result['summary'] = summarise(result)
    result['largest_steps'] = largest_steps(result['summary'])
    result['wall_s'] = round(time.perf_counter() - t0, 1)
    text = json.dumps(result)
    if args.out:
        with open(args.out, 'w') as f:
            f.write(text)
    print(text)
    return 0



if __name__ == '__main__':
    sys.exit(main())
