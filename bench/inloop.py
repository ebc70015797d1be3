"""Surrogates in the closed loop against hf, judged against hf's own sensitivity: prints one
JSON object (:mod:`eha_ros.evaluation` defines every figure).

Cases: the reference's nine scenarios, ``step_1mm`` and ``step_0p3mm`` (large signals) and
``chirp_0p1``, at every wear point of ``WEAR_POINTS`` (nominal, two off the wear grids of
every table, six drawn at random over the dynamic surrogates' range and two worn holds,
:mod:`eha_ros.evaluation`).  Noise-free: errors, yardstick, bounds and features per case,
every model, and hf and the dynamic surrogates again at each of ``--large-dts`` (2, 5 and
10 us) against hf at 1 us, and by the split integrator at each of ``--split-dts`` (10, 20 and
25 us; models ``hf@split``, ``dlut@split``, ...), which gives ``largest_steps``: per model and
integrator the largest step meeting the bounds in every case.  Every case is also judged
against hf converged in its step (``--converged-dt``, 10 ns, checked against 20 ns), under the
same bounds: ``converged`` (per model, hf at 1 us as ``hf``) and ``largest_steps_vs_converged``
(:func:`eha_ros.evaluation.converged_summary`).  With noise
(nominal wear): ``--seeds`` seeds (20: the errors are heavy-tailed on small-signal holds, see
:mod:`eha_ros.evaluation`) for ``--noise-models`` (default all but the reference's
networks ``nn``, ``nn2``, which miss the noise-free bounds by far and cost 15-20x hf).
Cost: wall seconds per simulated second of each run against hf's (JIT compilation excluded:
each worker runs every model once before); ``bench/plant_rtf.py`` measures cost on its own.

The cases run as two sweeps (:mod:`eha_ros.sweep.comparison`): noise-free (scenario x wear
point, every model) and with noise (scenario x seed); ``--jobs 2`` on a LocalCluster of two
workers (258 s for the default run on the 2-core reference machine), ``--jobs 1`` in this
process; ``--data DIR`` keeps both datasets (and resumes them).

    nice python bench/inloop.py [--models dlut,dnn,dga,lut,ga,nn,nn2] [--seeds 20]
        [--noise-models dlut,dnn,dga,lut,ga] [--large-dts 2e-6,5e-6,1e-5]
        [--split-dts 1e-5,2e-5,2.5e-5] [--converged-dt 1e-8]
        [--scenarios a,b] [--no-noise] [--wear nominal|all] [--wear-points rand_6,...]
        [--jobs 2] [--data DIR] [--quiet] [--out FILE] [--smoke]

``--smoke``: one short scenario at nominal wear for dlut and lut, two seeds, one larger step
of each integrator, the converged reference at 0.25 us, in process: a check that the bench
runs, no figure.
"""

import argparse
import json
import os
import sys
import tempfile
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

from eha_ros.graph import MODELS, REFERENCE_SCENARIOS  # noqa: E402
from eha_ros.evaluation import (CONTROLLER_PERIOD_S, DT_S, EXTRA_SCENARIOS,  # noqa: E402
                                WEAR_POINTS, converged_summary, largest_steps, summarise)
from eha_ros.sweep import SpecError, SweepError  # noqa: E402
from eha_ros.sweep.comparison import run_comparison  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument('--models', default='dlut,dnn,dga,lut,ga,nn,nn2')
    ap.add_argument('--scenarios', default=','.join(REFERENCE_SCENARIOS + EXTRA_SCENARIOS))
    ap.add_argument('--wear', choices=('nominal', 'all'), default='all')
    ap.add_argument('--wear-points', default=None,
                    help='only these wear points of --wear all (comma-separated names)')
    ap.add_argument('--seeds', type=int, default=20)
    ap.add_argument('--noise-models', default='dlut,dnn,dga,lut,ga',
                    help='models run with noise over the seeds (those also in --models)')
    ap.add_argument('--no-noise', action='store_true')
    ap.add_argument('--large-dts', default='2e-6,5e-6,1e-5',
                    help='also run hf and the dynamic surrogates at these steps [s] ("": none)')
    ap.add_argument('--split-dts', default='1e-5,2e-5,2.5e-5',
                    help='also run hf and the dynamic surrogates by the split integrator at '
                         'these steps [s] ("": none)')
    ap.add_argument('--converged-dt', default='1e-8',
                    help='also judge every case against hf explicit at this step [s], '
                         'checked against twice it ("": none)')
    ap.add_argument('--jobs', type=int, default=1,
                    help='sweep workers (a LocalCluster; 1: in this process)')
    ap.add_argument('--data', default=None,
                    help='keep the sweeps\' datasets here (resumed if present)')
    ap.add_argument('--quiet', action='store_true', help='no progress bar')
    ap.add_argument('--out', default=None, help='also write the JSON here')
    ap.add_argument('--smoke', action='store_true', help='a tiny case: a check, no figure')
    args = ap.parse_args(argv)
    if args.smoke:
        args.models, args.scenarios, args.wear, args.seeds = 'dlut,lut', 'step_0p01', \
            'nominal', 2
        args.large_dts, args.split_dts, args.jobs, args.quiet = '5e-6', '1e-5', 1, True
        args.converged_dt = '2.5e-7'
    t0 = time.perf_counter()
    models = [m for m in args.models.split(',') if m]
    unknown = [m for m in models if m not in MODELS or m == 'hf']
    if unknown:
        print(f'inloop: error: unknown model(s) {", ".join(unknown)}', file=sys.stderr)
        return 2
    scenarios = [s for s in args.scenarios.split(',') if s]
    if args.jobs < 1:
        print(f'inloop: error: --jobs {args.jobs} must be at least 1', file=sys.stderr)
        return 2
    steps = {}
    for opt in ('large_dts', 'split_dts'):
        text = getattr(args, opt)
        try:
            steps[opt] = [float(v) for v in text.split(',') if v]
        except ValueError:
            steps[opt] = None
        if steps[opt] is None or not all(v > 0 for v in steps[opt]):
            print(f'inloop: error: --{opt.replace("_", "-")} {text!r} is not a list of '
                  'positive steps [s]', file=sys.stderr)
            return 2
    large_dts = steps['large_dts']
    try:
        converged_dt = float(args.converged_dt) if args.converged_dt.strip() else None
    except ValueError:
        print(f'inloop: error: --converged-dt {args.converged_dt!r} is not a step [s]',
              file=sys.stderr)
        return 2
    wear = WEAR_POINTS if args.wear == 'all' else {'nominal': None}
    if args.wear_points is not None:
        names = [w for w in args.wear_points.split(',') if w]
        unknown = [w for w in names if w not in WEAR_POINTS]
        if unknown:
            print(f'inloop: error: unknown wear point(s) {", ".join(unknown)}', file=sys.stderr)
            return 2
        wear = {w: WEAR_POINTS[w] for w in names}
    noise_models = ([m for m in models if m in args.noise_models.split(',')]
                    if not args.no_noise and args.seeds > 0 else [])
    result = {'benchmark': 'inloop', 'smoke': args.smoke,
              'dt_s': DT_S, 'controller_period_s': CONTROLLER_PERIOD_S,
              'models': models, 'scenarios': scenarios, 'noise_models': noise_models,
              'seeds': args.seeds, 'jobs': args.jobs, 'converged_dt_s': converged_dt,
              'wear': {k: v for k, v in wear.items()}, 'noise_free': {}, 'noise': {},
              'load_before': os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix='eha-inloop-') as tmp:
        data = args.data or tmp
        try:
            done = run_comparison(data, scenarios, wear, models, noise_models, args.seeds,
                                  large_dts, workers=args.jobs, in_process=args.jobs == 1,
                                  progress=not args.quiet, split_dts=steps['split_dts'],
                                  converged_dt=converged_dt)
        except (SpecError, SweepError) as exc:
            print(f'inloop: error: {exc}', file=sys.stderr)
            return 2
    for wname in wear:  # in order, whatever order they finished in
        for sc in scenarios:
            result['noise_free'][f'{sc}/{wname}'] = done['noise_free'][f'{sc}/{wname}']
    for sc in scenarios:
        if sc in done['noise']:
            result['noise'][sc] = done['noise'][sc]
    result['sweeps'] = done['sweeps']
    result['summary'] = summarise(result)
    result['largest_steps'] = largest_steps(result['summary'])
    result['converged'] = converged_summary(result)
    if result['converged'] is not None:
        result['largest_steps_vs_converged'] = largest_steps(result['converged'])
    result['wall_s'] = round(time.perf_counter() - t0, 1)
    result['load_after'] = os.getloadavg()
    text = json.dumps(result)
    if args.out:
        with open(args.out, 'w') as f:
            f.write(text)
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
