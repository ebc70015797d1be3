"""Characteristic curves of the valve and a closed-loop step response, to PNG.

* ``p12_xs.png``   P12 against XS at five imposed flows (the reference's Figure 3.2, from the
  1e-2 s map transient; the steady solution dashed): saturation at +-(PS - PR) and the peaks
  above supply near null when flow is forced through a nearly closed valve.
* ``qj_xs.png``    flow into outlet 1 against XS at five outlet pressures P1 = 0.6 ... 20.6 MPa
  (Figure 3.3): the horizontal segments where P1 equals the return or supply pressure.
* ``overlap.png``  P12 against XS at zero flow for several overlaps and clearances: the dead
  zone of overlap and the gain lost to clearance.
* ``step.png``     closed-loop 0.1 mm and 1 mm steps: position, spool, P12, current.

Prints one JSON object with the files written.

    python bench/plots.py [--out docs/figures] [--smoke]

``--smoke`` draws every figure into a temporary folder (removed afterwards, unless ``--out`` is
given) and reports their sizes: a check that the figures can be drawn, nothing overwritten.
"""

import argparse
import json
from pathlib import Path
import shutil
import tempfile

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from eha_ros.physics import default_params, simulate  # noqa: E402
from eha_ros.physics.maps import spool_grid, steady_map, transient_map  # noqa: E402
from eha_ros.physics.params import replace  # noqa: E402
from eha_ros.physics.valve import valve_flows  # noqa: E402


def p12_xs(p, out):
    xs = spool_grid(401)
    flows = np.array([-5e-5, -2.5e-5, 0.0, 2.5e-5, 5e-5])
    tr = transient_map(xs[:, None], flows[None, :], params=p)['p12_pa']
    st = steady_map(xs[:, None], flows[None, :], params=p)['p12_pa']
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    for a, lim in zip(ax, (None, 30e-6)):
        for j, q in enumerate(flows):
            line, = a.plot(xs * 1e6, tr[:, j] / 1e6, label=f'Q = {q * 6e4:+.1f} L/min')
            a.plot(xs * 1e6, np.clip(st[:, j], -1e9, 1e9) / 1e6, '--', lw=0.8,
                   color=line.get_color())
        dps = (p.supply_pressure_pa - p.return_pressure_pa) / 1e6
        a.axhline(dps, color='k', lw=0.5)
        a.axhline(-dps, color='k', lw=0.5)
        a.set_xlabel('spool position XS [um]')
        a.set_ylabel('P12 [MPa]')
        if lim:
            a.set_xlim(-lim * 1e6, lim * 1e6)
            a.set_title('near null (dashed: steady state)')
        else:
            a.set_title('P12-XS at imposed flow (1e-2 s transient)')
            a.legend(fontsize=8)
        a.set_ylim(-80, 80)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def qj_xs(p, out):
    xs = spool_grid(401)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for p1 in (0.6e6, 5.6e6, 10.6e6, 15.6e6, 20.6e6):
        q = np.array([valve_flows(x, p1, p.supply_pressure_pa + p.return_pressure_pa - p1,
                                  p)[0] for x in xs])
        ax.plot(xs * 1e6, q * 6e4, label=f'P1 = {p1 / 1e6:.1f} MPa')
    ax.set_xlabel('spool position XS [um]')
    ax.set_ylabel('flow into outlet 1 [L/min]')
    ax.set_title('QJ-XS at fixed outlet pressure')
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def overlap_plot(p, out):
    xs = np.linspace(-15e-6, 15e-6, 301)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    for lap in (-2e-6, 0.0, 1e-6, 3e-6, 6e-6):
        r = transient_map(xs, 0.0, lap, p.radial_clearance_m, params=p)['p12_pa']
        ax[0].plot(xs * 1e6, r / 1e6, label=f'overlap {lap * 1e6:+.0f} um')
        q = np.array([valve_flows(x, 1.06e7, 1.06e7, replace(
            p, overlap_supply_m=lap, overlap_return_m=lap))[0] for x in xs])
        ax[1].plot(xs * 1e6, q * 6e4, label=f'overlap {lap * 1e6:+.0f} um')
    ax[0].set_title(f'P12 at Q = 0 (clearance {p.radial_clearance_m * 1e6:.1f} um)')
    ax[1].set_title('flow at P1 = P2 = 10.6 MPa (no load)')
    for a, yl in zip(ax, ('P12 [MPa]', 'flow into outlet 1 [L/min]')):
        a.set_xlabel('spool position XS [um]')
        a.set_ylabel(yl)
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def step_plot(p, out):
    fig, ax = plt.subplots(4, 2, figsize=(11, 9), sharex='col')
    for col, name in enumerate(('step_0p1', 'step_1mm')):
        r = simulate(p, name)
        t = r['time_s']
        ax[0, col].plot(t, r['command_m'] * 1e3, 'k--', label='command')
        ax[0, col].plot(t, r['jack_position_m'] * 1e3, label='jack')
        ax[0, col].step(t, r['jack_position_measured_m'] * 1e3, lw=0.6, label='sensor')
        ax[0, col].set_ylabel('position [mm]')
        ax[0, col].legend(fontsize=8)
        ax[0, col].set_title(name)
        ax[1, col].plot(t, r['spool_position_m'] * 1e6)
        ax[1, col].set_ylabel('spool [um]')
        ax[2, col].plot(t, r['p12_pa'] / 1e6)
        ax[2, col].set_ylabel('P12 [MPa]')
        ax[3, col].plot(t, r['coil_current_a'] * 1e3)
        ax[3, col].set_ylabel('current [mA]')
        ax[3, col].set_xlabel('time [s]')
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--out', type=Path, default=None, help='folder (default docs/figures)')
    ap.add_argument('--smoke', action='store_true',
                    help='draw into a temporary folder and report the sizes: a check')
    args = ap.parse_args()
    scratch = None
    if args.out is None:
        args.out = Path(scratch := tempfile.mkdtemp(prefix='eha-plots-')) if args.smoke \
            else Path('docs/figures')
    args.out.mkdir(parents=True, exist_ok=True)
    p = default_params()
    files, sizes = {}, {}
    try:
        for name, fn in (('p12_xs', p12_xs), ('qj_xs', qj_xs), ('overlap', overlap_plot),
                         ('step', step_plot)):
            path = args.out / f'{name}.png'
            fn(p, path)
            files[name] = None if scratch else str(path)
            sizes[name] = path.stat().st_size
    finally:
        if scratch:
            shutil.rmtree(scratch)
    print(json.dumps({'benchmark': 'plots', 'smoke': args.smoke, 'files': files,
                      'bytes': sizes}))


if __name__ == '__main__':
    main()
