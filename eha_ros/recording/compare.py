"""``eha-compare``: compare recorded runs against a reference run.

Examples::

    eha-compare hf.mcap lut.mcap ga.mcap nn.mcap --out plots/
    eha-compare hf.mcap lut.mcap --reference lut --json
    eha-compare a.mcap b.mcap --json errors.json --no-plots

For each run and each signal ``x`` of ``/eha/state`` (jack position, load pressure P12, spool
position) the relative Euclidean-norm error against the reference ``A``::

    e = ||x_B - x_A||_2 / ||x_A||_2

is taken over the reference's samples, with ``x_B`` linearly interpolated onto the reference's
``header.stamp`` times (runs recorded in lockstep at the same rate share their stamps, so
nothing is interpolated); reference samples outside a run's time span are left out.
``--align start`` measures every run's time from its own first sample instead.

Runs are labelled by the ``model`` field of their messages (``hf``, ``lut``, ``ga``, ``nn``),
or by file name where that is empty or not unique. The errors are printed as a table, or as
JSON with ``--json`` (to stdout, or to a file). One PNG per signal shows it over time with every
run overlaid: ``jack_position.png``, ``p12.png``, ``spool_position.png`` in ``--out``
(existing plots are not overwritten without ``--force``).

Bad input (a missing, truncated, damaged or non-MCAP file, no ``/eha/state`` messages, an
unknown ``--reference``, runs that do not overlap in time, an existing output) ends the command
with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
from collections import Counter
import json
import os
from pathlib import Path
import sys
from typing import Dict, List, NamedTuple, Optional, Sequence

import numpy as np

from eha_ros.graph import TOPIC_STATE
from eha_ros.recording.arrays import load_for_tool
from eha_ros.recording.definitions import RecordingError

__all__ = ['SIGNALS', 'Run', 'load_run', 'resampled_relative_error', 'compare_runs', 'plot_runs',
           'main']

PROG = 'eha-compare'

#: Compared fields of ActuatorState: (field, plot file stem, axis label, display scale).
SIGNALS = (
    ('jack_position_m', 'jack_position', 'jack position [mm]', 1e3),
    ('p12_pa', 'p12', 'load pressure P12 [bar]', 1e-5),
    ('spool_position_m', 'spool_position', 'spool position [µm]', 1e6),
)


class CompareError(ValueError):
    """Bad input: the message is the one line printed."""


class Run(NamedTuple):
    """One recorded run: state samples on its stamp times."""

    label: str
    path: str
    model: str
    time_s: np.ndarray                 # header.stamp, s
    signals: Dict[str, np.ndarray]     # field -> values (SI)


def load_run(path: str, topic: str = TOPIC_STATE) -> Run:
    """Load the compared signals of ``topic`` from a recording, sorted by stamp (duplicates of
    a stamp keep the last sample).

    Raises
    ------
    CompareError
        If the file cannot be read or has no messages on ``topic``.
    """
    try:
        arrays = load_for_tool(path, topic, PROG)
    except RecordingError as exc:  # unreadable, corrupt, or without the topic
        raise CompareError(str(exc)) from None
    if arrays['log_time_ns'].size == 0:
        raise CompareError(f'{path} has no {topic} messages')
    missing = [f for f, *_ in SIGNALS if f not in arrays]
    if missing or 'stamp_ns' not in arrays:
        raise CompareError(f'{path}: {topic} messages lack {", ".join(missing or ["header"])}')
    stamp = arrays['stamp_ns']
    order = np.argsort(stamp, kind='stable')
    stamp = stamp[order]
    keep = np.ones(stamp.size, dtype=bool)
    keep[:-1] = stamp[1:] != stamp[:-1]          # last sample of each stamp
    idx = order[keep]
    models = arrays.get('model', ())
    model = Counter(map(str, models)).most_common(1)[0][0] if len(models) else ''
    return Run(label=model or Path(path).stem, path=str(path), model=model,
               time_s=stamp[keep] * 1e-9,
               signals={f: np.asarray(arrays[f][idx], dtype=float) for f, *_ in SIGNALS})


def resampled_relative_error(t_ref: np.ndarray, x_ref: np.ndarray, t: np.ndarray,
                             x: np.ndarray) -> Dict[str, float]:
    """``||x(t_ref) - x_ref||_2 / ||x_ref||_2`` over the reference times inside ``t``'s span.

    ``x`` is linearly interpolated onto ``t_ref`` (exact where the times coincide). Returns
    ``{'relative_error': e, 'samples': n}``; ``e`` is ``nan`` when no reference time is inside
    the span, ``inf`` when the reference is zero there and the run is not (both are reported
    as ``null`` / ``n/a`` by the command).
    """
    inside = (t_ref >= t[0]) & (t_ref <= t[-1])
    n = int(inside.sum())
    if n == 0:
        return {'relative_error': float('nan'), 'samples': 0}
    ref = x_ref[inside]
    other = np.interp(t_ref[inside], t, x)
    num = float(np.linalg.norm(other - ref))
    den = float(np.linalg.norm(ref))
    if den == 0.0:
        return {'relative_error': 0.0 if num == 0.0 else float('inf'), 'samples': n}
    return {'relative_error': num / den, 'samples': n}


def compare_runs(runs: Sequence[Run], reference: int = 0, align: str = 'stamp') -> dict:
    """Relative errors of every run against ``runs[reference]``; a JSON-ready dict."""
    if align == 'start':
        runs = [r._replace(time_s=r.time_s - r.time_s[0]) for r in runs]
    ref = runs[reference]
    result = {
        'topic': TOPIC_STATE,
        'metric': '||x - x_ref||_2 / ||x_ref||_2 on the reference stamps',
        'align': align,
        'reference': {'label': ref.label, 'file': ref.path, 'samples': int(ref.time_s.size)},
        'signals': [f for f, *_ in SIGNALS],
        'runs': [],
    }
    for i, run in enumerate(runs):
        if i == reference:
            continue
        errors, samples = {}, 0
        for field, *_ in SIGNALS:
            e = resampled_relative_error(ref.time_s, ref.signals[field], run.time_s,
                                         run.signals[field])
            errors[field] = e['relative_error'] if np.isfinite(e['relative_error']) else None
            samples = e['samples']
        if samples == 0:
            raise CompareError(
                f'{run.path} does not overlap the reference {ref.path} in time '
                f'({run.time_s[0]:.6g}..{run.time_s[-1]:.6g} s vs '
                f'{ref.time_s[0]:.6g}..{ref.time_s[-1]:.6g} s); try --align start')
        result['runs'].append({'label': run.label, 'file': run.path, 'samples': samples,
                               'relative_error': errors})
    return result


def format_table(result: dict) -> str:
    """The errors of :func:`compare_runs` as a text table."""
    ref = result['reference']
    lines = [f"reference: {ref['label']} ({ref['file']}), {ref['samples']} samples; "
             f"relative error ||x - x_ref||_2 / ||x_ref||_2"]
    header = ['run', 'samples'] + result['signals']
    rows = [[r['label'], str(r['samples'])] + [
        'n/a' if r['relative_error'][s] is None else f"{r['relative_error'][s]:.4e}"
        for s in result['signals']] for r in result['runs']]
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    lines += ['  '.join(str(c).ljust(w) for c, w in zip(row, widths)).rstrip()
              for row in [header] + rows]
    return '\n'.join(lines)


def plot_paths(out_dir: Path) -> List[Path]:
    """The PNG files :func:`plot_runs` writes."""
    return [out_dir / f'{stem}.png' for _, stem, _, _ in SIGNALS]


def plot_runs(runs: Sequence[Run], out_dir: Path, align: str = 'stamp') -> List[Path]:
    """One PNG per signal, every run overlaid, time from the reference's first sample."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = runs[0].time_s[0]
    paths = plot_paths(out_dir)
    for (field, stem, ylabel, scale), path in zip(SIGNALS, paths):
        fig, ax = plt.subplots(figsize=(8, 4.5), layout='constrained')
        for run in runs:
            t = run.time_s - (run.time_s[0] if align == 'start' else t0)
            ax.plot(t, run.signals[field] * scale, label=run.label, linewidth=1.0)
        ax.set_xlabel('time [s]')
        ax.set_ylabel(ylabel)
        ax.set_title(f'{ylabel.split(" [")[0]} over time')
        ax.grid(True, alpha=0.3)
        ax.legend()
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return paths


def _reference_index(runs: List[Run], reference: Optional[str]) -> int:
    if reference is None:
        return 0
    for i, run in enumerate(runs):
        if os.path.abspath(reference) == os.path.abspath(run.path):
            return i
    matches = [i for i, run in enumerate(runs) if reference in (run.label, run.model)]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise CompareError(f'--reference {reference!r} matches several runs; give its file')
    raise CompareError(f'--reference {reference!r} is none of the runs '
                       f'({", ".join(r.label for r in runs)})')


def main(argv: Optional[List[str]] = None) -> int:
    """Console script ``eha-compare``; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Relative errors and plots of recorded runs against a reference.')
    parser.add_argument('files', nargs='+', metavar='FILE.mcap')
    parser.add_argument('--reference', metavar='A',
                        help='reference run: a file given, or a run label (default: the first)')
    parser.add_argument('--out', default='.', metavar='DIR',
                        help='folder for the PNG plots (default: the working directory)')
    parser.add_argument('--json', nargs='?', const='-', metavar='FILE',
                        help='JSON instead of the table (to FILE, or stdout)')
    parser.add_argument('--align', choices=('stamp', 'start'), default='stamp',
                        help='align on header stamps (default) or on each run\'s start')
    parser.add_argument('--no-plots', action='store_true', help='write no PNG')
    parser.add_argument('--force', action='store_true', help='overwrite existing outputs')
    args = parser.parse_args(argv)
    try:
        if len(args.files) < 2:
            raise CompareError('give at least two recordings (a reference and a run)')
        out_dir = Path(args.out)
        outputs = [] if args.no_plots else plot_paths(out_dir)
        if args.json not in (None, '-'):
            outputs.append(Path(args.json))
        existing = [str(p) for p in outputs if p.exists()]
        if existing and not args.force:
            raise CompareError(f'{", ".join(existing)} exist; refusing to overwrite '
                               '(use --force)')
        if out_dir.exists() and not out_dir.is_dir():
            raise CompareError(f'--out {out_dir} is not a folder')
        runs = [load_run(f) for f in args.files]
        counts = Counter(r.label for r in runs)  # a label two runs share: their files' names
        runs = [r._replace(label=r.label if counts[r.label] == 1
                           else f'{r.label} ({Path(r.path).name})') for r in runs]
        ref = _reference_index(runs, args.reference)
        result = compare_runs(runs, ref, args.align)
        if not args.no_plots:
            ordered = [runs[ref]] + [r for i, r in enumerate(runs) if i != ref]
            result['plots'] = [str(p) for p in plot_runs(ordered, out_dir, args.align)]
    except CompareError as exc:
        print(f'{PROG}: error: {" ".join(str(exc).split())}', file=sys.stderr)
        return 2
    text = json.dumps(result, indent=2)
    if args.json == '-':
        print(text)
    else:
        if args.json is not None:
            Path(args.json).write_text(text + '\n', encoding='utf-8')
        print(format_table(result))
        for path in result.get('plots', []):
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
