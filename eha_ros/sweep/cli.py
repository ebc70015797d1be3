"""``eha-sweep``: run a sweep spec into a Parquet dataset, or report on one.

    eha-sweep SPEC.yaml --out DIR [--workers N | --scheduler tcp://HOST:8786 | --in-process]
              [--resume] [--max-cases N] [--batch-size N] [--warm] [--quiet]
    eha-sweep report DIR [--metric NAME] [--x NAME] [--y NAME] [--plots FOLDER]

A bad spec or folder is refused before anything runs: one line, exit 2.  Ctrl-C keeps every
finished batch and prints how to resume (exit 130).  The summary is printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys

from .dataset import SweepError
from .spec import MAX_CASES, SpecError, load_spec


def _run(argv) -> int:
    ap = argparse.ArgumentParser(
        prog='eha-sweep', description='run every case of a sweep spec into a Parquet dataset',
        epilog='eha-sweep report DIR [--metric NAME] [--x NAME] [--y NAME]: the summary '
               'table and plots of a dataset (eha-sweep report --help)')
    ap.add_argument('spec', help='the sweep spec (YAML; README, "Sweeps")')
    ap.add_argument('--out', required=True, help='dataset folder (new, or --resume)')
    where = ap.add_mutually_exclusive_group()
    where.add_argument('--workers', type=int, default=None,
                       help='LocalCluster of N single-threaded workers (default: the cores)')
    where.add_argument('--scheduler', default=None,
                       help='an existing Dask cluster, tcp://HOST:PORT')
    where.add_argument('--in-process', action='store_true', help='no Dask: a loop here')
    ap.add_argument('--resume', action='store_true', help='skip the cases already in --out')
    ap.add_argument('--max-cases', type=int, default=MAX_CASES,
                    help=f'refuse a sweep of more cases (default {MAX_CASES})')
    ap.add_argument('--batch-size', type=int, default=None, help='points per batch')
    ap.add_argument('--warm', action='store_true',
                    help='compile every model on every worker first (timing without JIT)')
    ap.add_argument('--quiet', action='store_true', help='no progress bar')
    args = ap.parse_args(argv)
    from .engine import SweepInterrupted, run_sweep
    try:
        if args.workers is not None and args.workers < 1:
            raise SweepError(f'--workers {args.workers} must be at least 1')
        if args.batch_size is not None and args.batch_size < 1:
            raise SweepError(f'--batch-size {args.batch_size} must be at least 1')
        spec = load_spec(args.spec, args.max_cases)
        summary = run_sweep(spec, args.out, workers=args.workers, scheduler=args.scheduler,
                            in_process=args.in_process, resume=args.resume,
                            batch_size=args.batch_size, progress=not args.quiet,
                            warm=args.warm)
    except (SpecError, SweepError) as exc:
        print(f'eha-sweep: error: {exc}', file=sys.stderr)
        return 2
    except SweepInterrupted as exc:
        s = exc.summary
        again = ' '.join(shlex.quote(a) for a in [args.spec, '--out', args.out, '--resume'])
        print(f'eha-sweep: interrupted: {s["already_done"] + s["ran"]} of {s["cases"]} cases '
              f'are in {args.out}; resume with: eha-sweep {again}', file=sys.stderr)
        print(json.dumps(s))
        return 130
    print(json.dumps(summary))
    return 0


def _report(argv) -> int:
    ap = argparse.ArgumentParser(prog='eha-sweep report',
                                 description='summary table and plots of a sweep')
    ap.add_argument('dir', help='a sweep folder')
    ap.add_argument('--metric', default=None, help='metric of the plots')
    ap.add_argument('--x', default=None, help='swept parameter on the x axis')
    ap.add_argument('--y', default=None, help='swept parameter on the heat map y axis')
    ap.add_argument('--plots', default=None, help='folder for the plots (DIR/_report)')
    args = ap.parse_args(argv)
    from .report import report
    try:
        r = report(args.dir, args.metric, args.x, args.y, args.plots)
    except (SweepError, ValueError, OSError) as exc:
        print(f'eha-sweep report: error: {exc}', file=sys.stderr)
        return 2
    print(r['table'])
    for p in r['plots']:
        print(f'plot: {p}')
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    return _report(argv[1:]) if argv and argv[0] == 'report' else _run(argv)


if __name__ == '__main__':
    sys.exit(main())
