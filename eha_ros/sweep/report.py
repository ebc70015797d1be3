"""``eha-sweep report DIR``: a summary table of a sweep's dataset and the plots a user reads.

* The table: per model, cases by status and, for each metric, its median and range over the
  cases that ran (``ok``).
* ``heatmap_<metric>.png``: the metric over two swept parameters (the first two inputs that
  take more than one value, or ``--x``/``--y``), one panel per model; the mean over the
  other inputs and the seeds at each grid point, or every case as a dot where the inputs were
  drawn at random.
* ``spread_<metric>.png``: the metric against one swept parameter (``--x``), per model the
  mean over seeds and other inputs with the band from the smallest to the largest case.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .dataset import FIXED_COLUMNS, TIMING_COLUMNS, read_dataset

__all__ = ['load', 'summary_table', 'plot_heatmap', 'plot_spread', 'report']

_FIXED = tuple(n for n, _ in FIXED_COLUMNS)
#: Default metric, the first of these with values.
_DEFAULT_METRICS = ('jack_rel_error', 'rms_tracking_error_m', 'est_radial_clearance_m',
                    'est_demagnetisation')


def load(folder) -> tuple:
    """``(columns as numpy arrays, input names, metric names)`` of a dataset."""
    import yaml

    from .dataset import SPEC_FILE
    table = read_dataset(folder)
    cols = {n: np.asarray(table.column(n).to_pylist(), dtype=object)
            for n in table.column_names}
    stored = yaml.safe_load((Path(folder) / SPEC_FILE).read_text())
    from .spec import parse_spec
    spec = parse_spec(stored['spec'], check=False, base=stored['base'])
    inputs = [n for n in spec.input_names if n in cols]
    metrics = [n for n in table.column_names if n not in _FIXED and n not in inputs
               and n not in TIMING_COLUMNS and not n.startswith('signal_')]
    return cols, inputs, metrics


def _numeric(v) -> np.ndarray:
    return np.array([np.nan if x is None else float(x) for x in v], dtype=float)


def summary_table(cols, metrics) -> str:
    """Markdown table: per model, cases by status, each metric's median [min, max]."""
    head = ['model', 'cases', 'ok', 'diverged', 'error'] + list(metrics)
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for m in dict.fromkeys(cols['model'].tolist()):
        sel = cols['model'] == m
        st = cols['status'][sel]
        ok = sel & (cols['status'] == 'ok')
        counts = [str(int((st == s).sum())) for s in ('ok', 'diverged', 'error')]
        cells = [m, str(int(sel.sum()))] + counts
        for name in metrics:
            v = _numeric(cols[name][ok])
            v = v[np.isfinite(v)]
            cells.append(f'{np.median(v):.4g} [{v.min():.3g}, {v.max():.3g}]' if v.size else '-')
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def plot_heatmap(cols, metric, x, y, path: Path) -> Path:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    v = _numeric(cols[metric])
    models = [m for m in dict.fromkeys(cols['model'].tolist())
              if np.isfinite(v[cols['model'] == m]).any()]
    xs, ys = _numeric(cols[x]), _numeric(cols[y])
    ux, uy = np.unique(xs), np.unique(ys)
    gridded = ux.size * uy.size <= max(4 * len(xs) // max(len(models), 1), 1) \
        and ux.size * uy.size <= 2500
    fig, axes = plt.subplots(1, len(models), figsize=(4.2 * len(models) + 0.8, 3.8),
                             squeeze=False)
    finite = v[np.isfinite(v)]
    vmin, vmax = (finite.min(), finite.max()) if finite.size else (0.0, 1.0)
    im = None
    for ax, m in zip(axes[0], models):
        sel = (cols['model'] == m) & (cols['status'] == 'ok') & np.isfinite(v)
        if gridded:
            z = np.full((uy.size, ux.size), np.nan)
            for j, yv in enumerate(uy):
                for i, xv in enumerate(ux):
                    k = sel & (xs == xv) & (ys == yv)
                    if k.any():
                        z[j, i] = v[k].mean()
            im = ax.imshow(z, origin='lower', aspect='auto', vmin=vmin, vmax=vmax,
                           cmap='viridis')
            ax.set_xticks(range(ux.size), [f'{t:.3g}' for t in ux], rotation=45, fontsize=7)
            ax.set_yticks(range(uy.size), [f'{t:.3g}' for t in uy], fontsize=7)
        else:
            im = ax.scatter(xs[sel], ys[sel], c=v[sel], s=12, vmin=vmin, vmax=vmax,
                            cmap='viridis')
        ax.set_title(f'{m}: {int(sel.sum())} cases', fontsize=9)
        ax.set_xlabel(x)
        ax.set_ylabel(y)
    if im is not None:
        fig.colorbar(im, ax=axes[0].tolist(), label=metric)
    fig.savefig(path, dpi=110, bbox_inches='tight')
    plt.close(fig)
    return path


def plot_spread(cols, metric, x, path: Path) -> Path:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    v = _numeric(cols[metric])
    xs = _numeric(cols[x])
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for m in dict.fromkeys(cols['model'].tolist()):
        sel = (cols['model'] == m) & (cols['status'] == 'ok') & np.isfinite(v)
        ux = np.unique(xs[sel])
        if not ux.size:
            continue
        groups = [v[sel & (xs == u)] for u in ux]
        mean, lo, hi = (np.array([f(g) for g in groups]) for f in (np.mean, np.min, np.max))
        line, = ax.plot(ux, mean, 'o-', ms=3, label=f'{m} (mean)')
        ax.fill_between(ux, lo, hi, color=line.get_color(), alpha=0.2)
    ax.set_xlabel(x)
    ax.set_ylabel(metric)
    ax.set_title(f'{metric}: mean, band = smallest to largest case (seeds, other inputs)',
                 fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches='tight')
    plt.close(fig)
    return path


def report(folder, metric: str | None = None, x: str | None = None, y: str | None = None,
           plots=None) -> dict:
    """Table and plots of a dataset; returns ``{'table': text, 'plots': [paths]}``."""
    cols, inputs, metrics = load(folder)
    if metric is None:
        metric = next((m for m in _DEFAULT_METRICS if m in cols and np.isfinite(
            _numeric(cols[m])).any()), metrics[0] if metrics else None)
    elif metric not in metrics:
        raise ValueError(f'unknown metric {metric!r} (one of {", ".join(metrics)})')
    for name in (x, y):
        if name is not None and name not in inputs:
            raise ValueError(f'{name!r} is not a swept parameter of this sweep (one of '
                             f'{", ".join(inputs) or "none"})')
    swept = [n for n in inputs if len(set(cols[n].tolist())) > 1]
    x = x or (swept[0] if swept else None)
    y = y or next((n for n in swept if n != x), None)
    out = Path(plots) if plots is not None else Path(folder) / '_report'
    out.mkdir(parents=True, exist_ok=True)
    written = []
    if metric is not None and x is not None:
        if y is not None:
            written.append(plot_heatmap(cols, metric, x, y, out / f'heatmap_{metric}.png'))
        written.append(plot_spread(cols, metric, x, out / f'spread_{metric}.png'))
    return {'table': summary_table(cols, metrics), 'metric': metric, 'x': x, 'y': y,
            'plots': [str(p) for p in written]}
