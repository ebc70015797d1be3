"""``eha-diagnose FILE.mcap``: offline wear estimate from a recording.

Reads the ``/eha/state`` samples of a recording (spool position, load flow, load pressure),
fits the valve model to them as the health monitor does
(:class:`eha_ros.surrogates.health.InServiceEstimator`), grades the estimate with
``config/health.yaml`` and prints it (``--json``: one JSON object).  ``--window S`` uses only
the last S seconds; ``--skip S`` drops the first S seconds (start-up).

Bad input (missing, truncated, corrupt or non-MCAP file, no ``/eha/state`` topic, too few
samples) ends with one line on stderr and exit status 2.

A recording of a diagnostic valve test (states with ``STATUS_VALVE_TEST``) is read as the health
monitor reads it: the P12 curves at the point ends go to the diagnostic network
(:class:`eha_ros.surrogates.health.ValveTestEstimator`, method ``diagnostic-network``);
``--method steady`` fits the in-service samples instead.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from eha_ros.graph import LEVEL_NAMES as LEVELS, STATUS_DIVERGED, STATUS_VALVE_TEST, TOPIC_STATE
from eha_ros.physics import ParameterError, load_params
from eha_ros.physics.valve_test import MAP_POINTS
from eha_ros.recording.arrays import load_for_tool
from eha_ros.recording.definitions import RecordingError
from eha_ros.surrogates.base import SurrogateError
from eha_ros.surrogates.health import (HealthThresholds, InServiceEstimator, ValveTestEstimator,
                                       classify)


def _valve_test_curves(a):
    """``(q, xs, p12)`` of every complete curve of the valve test in the arrays ``a``."""
    ends = (a['status'] == STATUS_VALVE_TEST) & a.get(
        'valve_test_point_end', np.zeros(a['status'].size, dtype=bool))
    curves = []
    q_all = a['load_flow_m3_s'][ends]
    for q in dict.fromkeys(q_all.tolist()):  # in order of appearance
        sel = q_all == q
        point = a['valve_test_point'][ends][sel]
        _, first = np.unique(point, return_index=True)
        if first.size == MAP_POINTS:
            curves.append((q, a['spool_position_m'][ends][sel][first],
                           a['p12_pa'][ends][sel][first]))
    return curves


def diagnose(path, params=None, window_s=None, skip_s=0.05, max_samples=400, method='auto'):
    """Wear estimate (dict) of the recording at ``path``; ``method``: ``auto`` (the valve
    test's curves if the recording has one, else the in-service fit), ``network`` or
    ``steady``."""
    try:
        a = load_for_tool(path, TOPIC_STATE, 'eha-diagnose')
    except RecordingError as exc:  # unreadable, corrupt, or without the topic
        raise ParameterError(str(exc)) from None
    needed = ('stamp_ns', 'spool_position_m', 'load_flow_m3_s', 'p12_pa')
    if a['log_time_ns'].size == 0 or any(k not in a for k in needed):
        raise ParameterError(f'{path}: no usable {TOPIC_STATE} samples')
    t = a['stamp_ns'] * 1e-9
    params = params or load_params()
    status = a.get('status')
    curves = _valve_test_curves(a) if status is not None else []
    if method == 'network' or (method == 'auto' and curves):
        if not curves:
            raise ParameterError(f'{path}: no complete valve-test curve (133 points at one '
                                 'flow) to give the diagnostic network')
        try:
            estimator = ValveTestEstimator(params)
        except (SurrogateError, OSError) as exc:
            raise ParameterError(' '.join(str(exc).split())) from None
        keep = (status == STATUS_VALVE_TEST)
        est = estimator.estimate(curves)
    else:
        keep = t >= t.min() + skip_s
        if window_s:
            keep &= t >= t.max() - window_s
        if status is not None:
            keep &= (status != STATUS_DIVERGED) & (status != STATUS_VALVE_TEST)
        est = InServiceEstimator(params, max_samples=max_samples).estimate(
            a['spool_position_m'][keep], a['load_flow_m3_s'][keep], a['p12_pa'][keep])
    level, text = classify(est, HealthThresholds.load())
    models = a.get('model')
    return {'file': str(path), 'model': str(models[0]) if models is not None and models.size
            else '', 'samples_in_file': int(t.size), 'samples_used': est.samples_used,
            't_from_s': float(t[keep].min()), 't_to_s': float(t[keep].max()),
            'radial_clearance_m': est.radial_clearance_m,
            'radial_clearance_std_m': est.radial_clearance_std_m, 'overlap_m': est.overlap_m,
            'overlap_std_m': est.overlap_std_m,
            'pressure_residual_pa': est.pressure_residual_pa,
            'nominal_residual_pa': (est.nominal_residual_pa
                                    if np.isfinite(est.nominal_residual_pa) else None),
            'method': est.method,
            'level': LEVELS[level], 'message': text}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='eha-diagnose', description=__doc__.splitlines()[0])
    ap.add_argument('file')
    ap.add_argument('--window', type=float, default=None, help='last S seconds only')
    ap.add_argument('--skip', type=float, default=0.05, help='drop the first S seconds')
    ap.add_argument('--params', default=None, help='physical parameter YAML')
    ap.add_argument('--method', choices=('auto', 'network', 'steady'), default='auto',
                    help='network: the valve test\'s curves; steady: in-service fit; auto: '
                    'network if the recording holds a valve test')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    try:
        r = diagnose(args.file, load_params(args.params), args.window, args.skip,
                     method=args.method)
    except ParameterError as exc:
        print(f'eha-diagnose: error: {exc}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(r))
    else:
        print(f'{r["file"]}: [{r["level"]}] {r["message"]}')
        print(f'  radial clearance {r["radial_clearance_m"] * 1e6:.3f} +- '
              f'{r["radial_clearance_std_m"] * 1e6:.3f} um, overlap {r["overlap_m"] * 1e6:.3f} '
              f'+- {r["overlap_std_m"] * 1e6:.3f} um, residual '
              f'{r["pressure_residual_pa"] / 1e6:.3f} MPa, {r["samples_used"]} samples '
              f'({r["t_from_s"]:.3f}..{r["t_to_s"]:.3f} s, {r["method"]})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
