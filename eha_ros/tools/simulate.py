"""``eha-simulate``: run the high-fidelity closed loop on a named scenario and report.

Examples::

    eha-simulate                               # step_0p1 with config/eha_params.yaml
    eha-simulate --scenario sine_0p1_5pi --controller-period 1e-3 --plot out.png
    eha-simulate --set radial_clearance_m=4e-6 --set overlap_supply_m=0 --json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from eha_ros.physics import (ParameterError, SimulationDiverged, get_scenario, load_params,
                             load_scenarios, simulate)
from eha_ros.physics.params import SPEC_BY_NAME


def response_metrics(result) -> dict:
    """Tracking figures of a run: final error, overshoot, 90 % rise time, peaks."""
    t = result['time_s']
    r = result['command_m']
    x = result['jack_position_m']
    out = {
        'final_command_m': float(r[-1]),
        'final_position_m': float(x[-1]),
        'final_error_m': float(r[-1] - x[-1]),
        'max_abs_error_m': float(np.max(np.abs(r - x))),
        'rms_error_m': float(np.sqrt(np.mean((r - x) ** 2))),
        'p12_max_pa': float(np.max(result['p12_pa'])),
        'p12_min_pa': float(np.min(result['p12_pa'])),
        'spool_max_abs_m': float(np.max(np.abs(result['spool_position_m']))),
        'current_max_abs_a': float(np.max(np.abs(result['coil_current_a']))),
    }
    sc = result.scenario
    if sc.waveform == 'step' and sc.amplitude_m != 0:
        a = sc.amplitude_m
        after = t >= sc.start_s
        rel = x[after] / a
        out['overshoot_pct'] = float(max(0.0, (rel.max() - 1.0) * 100.0))
        hit = np.flatnonzero(rel >= 0.9)
        out['rise_time_90_s'] = float(t[after][hit[0]] - sc.start_s) if hit.size else None
    return out


def _parse_set(items):
    values = {}
    for item in items or ():
        if '=' not in item:
            raise ParameterError(f'--set {item!r}: expected name=value')
        name, value = item.split('=', 1)
        if name not in SPEC_BY_NAME:
            raise ParameterError(f'--set: unknown parameter {name}')
        try:
            values[name] = value if SPEC_BY_NAME[name].choices else float(value)
        except ValueError:
            raise ParameterError(f'--set {name}={value!r}: not a number') from None
    return values


def plot_result(result, path: Path) -> None:
    """Command/position, spool, P12 and current against time, to PNG."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    t = result['time_s']
    fig, ax = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    ax[0].plot(t, result['command_m'] * 1e3, 'k--', label='command')
    ax[0].plot(t, result['jack_position_m'] * 1e3, label='jack')
    ax[0].plot(t, result['jack_position_measured_m'] * 1e3, lw=0.7, label='sensor')
    ax[0].set_ylabel('position [mm]')
    ax[0].legend(loc='best')
    ax[1].plot(t, result['spool_position_m'] * 1e6)
    ax[1].set_ylabel('spool XS [um]')
    ax[2].plot(t, result['p12_pa'] / 1e6)
    ax[2].set_ylabel('P12 [MPa]')
    ax[3].plot(t, result['coil_current_a'] * 1e3)
    ax[3].set_ylabel('coil current [mA]')
    ax[3].set_xlabel('time [s]')
    fig.suptitle(f'{result.scenario.name}: {result.scenario.description}')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='eha-simulate', description=__doc__.splitlines()[0])
    ap.add_argument('--scenario', default='step_0p1', help='scenario name (see --list)')
    ap.add_argument('--list', action='store_true', help='list the scenarios and exit')
    ap.add_argument('--params', type=Path, default=None, help='parameter YAML file')
    ap.add_argument('--set', action='append', metavar='NAME=VALUE',
                    help='override a parameter (repeatable)')
    ap.add_argument('--duration', type=float, default=None, help='simulated time [s]')
    ap.add_argument('--dt', type=float, default=1e-6, help='plant step [s] (default 1e-6)')
    ap.add_argument('--controller-period', type=float, default=None,
                    help='controller sample period [s] (default: every plant step)')
    ap.add_argument('--seed', type=int, default=0, help='noise seed')
    ap.add_argument('--plot', type=Path, default=None, help='write a PNG of the run')
    ap.add_argument('--csv', type=Path, default=None, help='write the time histories as CSV')
    ap.add_argument('--json', action='store_true', help='print one JSON object only')
    args = ap.parse_args(argv)
    try:
        if args.list:
            for name, sc in sorted(load_scenarios().items()):
                print(f'{name:16s} {sc.waveform:6s} {sc.duration_s:5.2f} s  {sc.description}')
            return 0
        params = load_params(args.params, **_parse_set(args.set))
        scenario = get_scenario(args.scenario)
        for path in (args.plot, args.csv):
            if path is not None and path.exists():
                raise ParameterError(f'{path} exists: refusing to overwrite it')
        result = simulate(params, scenario, duration_s=args.duration, dt_s=args.dt,
                          seed=args.seed, controller_period_s=args.controller_period)
    except (ParameterError, SimulationDiverged) as exc:
        print(f'eha-simulate: error: {exc}', file=sys.stderr)
        return 2
    sim_s = float(result['time_s'][-1])
    summary = {'scenario': scenario.name, 'simulated_s': sim_s, 'dt_s': result.dt_s,
               'controller_period_s': result.controller_period_s,
               'wall_s': result.wall_time_s,
               'real_time_factor': sim_s / result.wall_time_s if result.wall_time_s else None,
               **response_metrics(result)}
    if args.plot is not None:
        plot_result(result, args.plot)
        summary['plot'] = str(args.plot)
    if args.csv is not None:
        names = list(result.data)
        np.savetxt(args.csv, np.column_stack([result.data[k] for k in names]), delimiter=',',
                   header=','.join(names), comments='')
        summary['csv'] = str(args.csv)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f'eha-simulate: {scenario.name} ({scenario.description})')
        for k, v in summary.items():
            print(f'  {k:22s} {v:.6g}' if isinstance(v, float) else f'  {k:22s} {v}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
