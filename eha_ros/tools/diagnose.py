"""``eha-diagnose FILE.mcap``: the health monitor's estimates, offline, from a recording.

Replays the recording's ``/eha/state`` through the health monitor's own logic
(:class:`eha_ros.health.monitor.MonitorCore`, the same code the ``health_monitor`` node
runs) and prints every monitored parameter under the plant's parameter names
(``radial_clearance_m``, ``overlap_supply_m``, ``demagnetisation``, ``filter_clogging``,
``spool_static_friction_n``, ``jack_static_friction_n``, ``offset_a``) with its standard
deviation, level and reason (``--json``: one JSON object).  Where the recording holds the live
monitor's ``/eha/health`` too, every recorded message is compared with the replay
(``live_agrees``: equal bit for bit; in lockstep they must be).

``--method``: ``auto`` (everything the recording supports: valve test, pre-flight check, else
the in-service estimates), ``test`` (the recording must hold a valve test or a pre-flight
check), ``network`` (a valve test), ``preflight`` (a pre-flight check) or ``steady`` (the
in-service estimate only).  ``--window-s S`` / ``--update-period-s S`` / ``--settle-s S``: the
monitor's ``window_s``, ``update_period_s`` and ``settle_s`` (defaults:
:mod:`eha_ros.health.monitor`).

Bad input (missing, truncated, corrupt or non-MCAP file, no ``/eha/state`` topic, no or an
incomplete test segment where one is required, too few samples) ends with one line on stderr
and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from types import SimpleNamespace

import numpy as np

from eha_ros.graph import (LEVEL_NAMES, STATUS_PREFLIGHT, STATUS_VALVE_TEST, TOPIC_HEALTH,
                           TOPIC_STATE)
from eha_ros.physics import ParameterError, load_params
from eha_ros.recording.arrays import flatten, load_for_tool
from eha_ros.recording.definitions import RecordingError
from eha_ros.recording.reader import McapReader
from eha_ros.health.thresholds import HealthThresholds
from eha_ros.health.monitor import ITEMS, SETTLE_S, UPDATE_PERIOD_S, WINDOW_S, MonitorCore

METHODS = ('auto', 'test', 'network', 'preflight', 'steady')
_STATE_FIELDS = ('status', 'sim_time_s', 'spool_position_m', 'load_flow_m3_s', 'p12_pa',
                 'valve_test_point', 'valve_test_point_end', 'coil_current_a',
                 'flapper_position_m', 'jack_position_m', 'jack_velocity_m_s')
#: Fields a recording may lack (made before the plant reported them): the valve test is then
#: the reference's, and the test conditions are not measured (nominal assumed, said so).
_OPTIONAL_FIELDS = {'valve_test_procedure': 0, 'supply_pressure_measured_pa': math.nan,
                    'return_pressure_measured_pa': math.nan,
                    'fluid_temperature_measured_k': math.nan}


def _same(a, b) -> bool:
    """Bit-for-bit equality of two floats (NaN equals NaN)."""
    return np.float64(a).tobytes() == np.float64(b).tobytes()


def compare_live(recorded: list, reports: list, core_items: list) -> dict:
    """Recorded ``/eha/health`` against the replay's reports, field by field."""
    if not recorded:
        return {'live_messages': 0, 'live_agrees': None}
    mism = []
    if len(recorded) != len(reports):
        mism.append(f'{len(recorded)} recorded, {len(reports)} replayed')
    for k, (m, r, items) in enumerate(zip(recorded, reports, core_items)):
        stamp = int(m['header.stamp.sec']) * 1_000_000_000 + int(m['header.stamp.nanosec'])
        ok = ((stamp, m['level'], m['method'], m['message'], m['samples_used'])
              == (r.stamp_ns, r.level, r.method, r.message, r.samples_used))
        ok &= all(_same(m[key], getattr(r, key)) for key in (
            'radial_clearance_m', 'radial_clearance_std_m', 'overlap_m', 'overlap_std_m',
            'pressure_residual_pa'))
        vals = m.get('parameter_values') or []
        stds = m.get('parameter_stds') or []
        ok &= len(vals) == len(items) and all(
            _same(v, i[0]) and _same(s, i[1]) for v, s, i in zip(vals, stds, items))
        if not ok:
            mism.append(f'message {k} (stamp {stamp} ns) differs')
    return {'live_messages': len(recorded), 'live_agrees': not mism,
            'live_mismatches': mism[:5]}


def diagnose(path, params=None, method: str = 'auto', window_s: float = WINDOW_S,
             update_period_s: float = UPDATE_PERIOD_S, settle_s: float = SETTLE_S,
             limits=None) -> dict:
    """Replay the recording at ``path``; a dict of what the monitor reports (see the module
    docstring).  Raises ParameterError on bad input."""
    if method not in METHODS:
        raise ParameterError(f'unknown method {method!r} (one of {", ".join(METHODS)})')
    try:
        a = load_for_tool(path, TOPIC_STATE, 'eha-diagnose')
    except RecordingError as exc:  # unreadable, corrupt, or without the topic
        raise ParameterError(str(exc)) from None
    missing = [f for f in ('stamp_ns',) + _STATE_FIELDS if f not in a]
    if a['log_time_ns'].size == 0 or missing:
        raise ParameterError(f'{path}: no usable {TOPIC_STATE} samples'
                             + (f' (no field {missing[0]})' if missing else ''))
    params = params or load_params()
    limits = limits or HealthThresholds.load()
    status = a['status']
    has_vt = bool(np.any(status == STATUS_VALVE_TEST))
    has_pf = bool(np.any(status == STATUS_PREFLIGHT))
    if method == 'test' and not (has_vt or has_pf):
        raise ParameterError(f'{path}: no test segment (neither a valve test nor a pre-flight '
                             'check: record scenario maintenance_test)')
    if method == 'network' and not has_vt:
        raise ParameterError(f'{path}: no valve-test segment (record scenario valve_test)')
    if method == 'preflight' and not has_pf:
        raise ParameterError(f'{path}: no pre-flight check segment (record scenario '
                             'preflight_check)')
    keep = np.ones(status.size, dtype=bool)
    if method in ('network', 'test') and not has_pf:
        keep = status == STATUS_VALVE_TEST
    elif method == 'preflight' or (method == 'test' and not has_vt):
        keep = status == STATUS_PREFLIGHT
    elif method == 'test':
        keep = (status == STATUS_VALVE_TEST) | (status == STATUS_PREFLIGHT)
    elif method == 'steady':
        keep = (status != STATUS_VALVE_TEST) & (status != STATUS_PREFLIGHT)
    states = {k: v[keep] for k, v in a.items()}
    absent = [f for f in _OPTIONAL_FIELDS if f not in states]
    for f in absent:
        states[f] = np.full(states['stamp_ns'].size, _OPTIONAL_FIELDS[f])
    if states['stamp_ns'].size == 0:
        raise ParameterError(f'{path}: no {TOPIC_STATE} samples for method {method}')
    core = MonitorCore(params, limits, window_s, update_period_s, settle_s)
    reports = []
    snapshots = []   # every parameter's (value, std) after each report, as published
    fields = _STATE_FIELDS + tuple(_OPTIONAL_FIELDS)
    cols = [states[f].tolist() for f in fields]  # plain Python values, as a message has
    stamps = states['stamp_ns']
    s = SimpleNamespace()
    for k in range(stamps.size):
        for name, col in zip(fields, cols):
            setattr(s, name, col[k])
        for job in core.on_state(int(stamps[k]), s):
            reports.append(job.run())
            snapshots.append([(core.items[n].value, core.items[n].std) if n in core.items
                              else (math.nan, math.nan) for n in ITEMS])
    test_kinds = {'valve-test', 'preflight'}
    if method in ('test', 'network', 'preflight'):
        bad = [r for r in reports if r.kind in test_kinds and r.message.startswith(
            'no estimate')]
        if bad:
            raise ParameterError(f'{path}: {bad[-1].message}')
        if not any(r.kind in test_kinds for r in reports):
            raise ParameterError(f'{path}: the test segment is incomplete (cut before its end)')
    if not reports:
        raise ParameterError(f'{path}: too short for an estimate ({stamps.size} states, the '
                             f'first after {update_period_s:g} s)')
    chosen = ([r for r in reports if r.kind in test_kinds] or reports)[-1]
    if chosen.message.startswith('no estimate'):
        raise ParameterError(f'{path}: {chosen.message}')
    models = a.get('model')
    t = states['stamp_ns'] * 1e-9
    out = {'file': str(path), 'model': str(models[0]) if models is not None and models.size
           else '', 'samples_in_file': int(a['stamp_ns'].size),
           't_from_s': float(t.min()), 't_to_s': float(t.max()),
           'method': chosen.method, 'kind': chosen.kind, 'level': LEVEL_NAMES[chosen.level],
           'message': chosen.message, 'samples_used': chosen.samples_used,
           'radial_clearance_m': chosen.radial_clearance_m,
           'radial_clearance_std_m': chosen.radial_clearance_std_m,
           'overlap_m': chosen.overlap_m, 'overlap_std_m': chosen.overlap_std_m,
           'pressure_residual_pa': chosen.pressure_residual_pa,
           'conditions': dict(chosen.conditions),
           'conditions_by_test': {r.kind: dict(r.conditions) for r in reports
                                  if r.kind in test_kinds and r.conditions},
           'conditions_in_recording': not absent,
           'estimates': {n: core.items[n].to_dict() for n in ITEMS if n in core.items},
           'not_estimated': [n for n in ITEMS if n not in core.items],
           'reports': len(reports), 'scheduled_in_service': core.scheduled}
    if method == 'auto':
        try:  # the recorded HealthStatus messages as flat dicts (sequence fields kept)
            live = [flatten(m.message) for m in McapReader(path, topics=[TOPIC_HEALTH])]
        except (OSError, RecordingError):
            live = []
        out.update(compare_live(live, reports, snapshots))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='eha-diagnose', description=__doc__.splitlines()[0])
    ap.add_argument('file')
    ap.add_argument('--method', choices=METHODS, default='auto',
                    help='auto: all the recording supports; test: valve test and/or '
                    'pre-flight check required; network: valve test; preflight: pre-flight '
                    'check; steady: in-service only')
    ap.add_argument('--window-s', type=float, default=WINDOW_S,
                    help='in-service window [s]')
    ap.add_argument('--update-period-s', type=float, default=UPDATE_PERIOD_S,
                    help='in-service period [s]')
    ap.add_argument('--settle-s', type=float, default=SETTLE_S,
                    help='state time ignored at start [s]')
    ap.add_argument('--params', default=None, help='physical parameter YAML')
    ap.add_argument('--thresholds', default=None, help='health threshold YAML')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    try:
        for name, v in (('--window-s', args.window_s),
                        ('--update-period-s', args.update_period_s)):
            if not (v > 0 and math.isfinite(v)):
                raise ParameterError(f'{name} = {v} must be a positive number of seconds')
        r = diagnose(args.file, load_params(args.params), args.method, args.window_s,
                     args.update_period_s, args.settle_s, HealthThresholds.load(args.thresholds))
    except (ParameterError, ValueError) as exc:
        print(f'eha-diagnose: error: {" ".join(str(exc).split())}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(r, allow_nan=False, default=np.generic.item))  # numpy scalars only
    else:
        print(f'{r["file"]}: [{r["level"]}] {r["kind"]} ({r["method"]}): {r["message"]}')
        c = r['conditions']
        if c:
            print(f'  conditions {"ASSUMED (not measured)" if c["assumed"] else "measured"}: '
                  f'supply {c["supply_pressure_pa"] / 1e6:.3f} MPa, return '
                  f'{c["return_pressure_pa"] / 1e6:.3f} MPa, fluid '
                  f'{c["fluid_temperature_k"] - 273.15:.1f} degC')
        for name, e in r['estimates'].items():
            print(f'  {name:24s} {e["value"]:.6g} +- {e["std"]:.3g}  [{e["level"]}] '
                  f'({e["method"]})')
        for name in r['not_estimated']:
            print(f'  {name:24s} not estimated (needs a pre-flight check)')
        if r.get('live_agrees') is not None:
            print(f'  live /eha/health: {r["live_messages"]} messages, '
                  f'{"equal to" if r["live_agrees"] else "DIFFERENT from"} the replay')
    return 0


if __name__ == '__main__':
    sys.exit(main())
