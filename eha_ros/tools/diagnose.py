"""``eha-diagnose FILE.mcap``: offline wear estimate from a recording.

Reads the ``/eha/state`` samples of a recording (spool position, load flow, load pressure),
fits the valve model to them as the health monitor does
(:class:`eha_ros.surrogates.health.InServiceEstimator`), grades the estimate with
``config/health.yaml`` and prints it (``--json``: one JSON object).  ``--window S`` uses only
the last S seconds; ``--skip S`` drops the first S seconds (start-up).

Bad input (missing, truncated, corrupt or non-MCAP file, no ``/eha/state`` topic, too few
samples) ends with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys


from eha_ros.physics import ParameterError, load_params
from eha_ros.recording.mcap_io import RecordingError, load_topic_arrays
from eha_ros.recording.topics import TOPIC_STATE
from eha_ros.surrogates.health import HealthThresholds, InServiceEstimator, classify

LEVELS = ('OK', 'WARN', 'ERROR')


def diagnose(path, params=None, window_s=None, skip_s=0.05, max_samples=400):
    """Wear estimate (dict) of the recording at ``path``."""
    try:
        a = load_topic_arrays(path, TOPIC_STATE, strict=True)
    except KeyError:
        raise ParameterError(f'{path} has no {TOPIC_STATE} topic') from None
    except RecordingError as exc:
        raise ParameterError(str(exc)) from None
    except OSError as exc:
        raise ParameterError(f'cannot read {path}: {exc.strerror or exc}') from None
    needed = ('stamp_ns', 'spool_position_m', 'load_flow_m3_s', 'p12_pa')
    if a['log_time_ns'].size == 0 or any(k not in a for k in needed):
        raise ParameterError(f'{path}: no usable {TOPIC_STATE} samples')
    t = a['stamp_ns'] * 1e-9
    keep = t >= t.min() + skip_s
    if window_s:
        keep &= t >= t.max() - window_s
    status = a.get('status')
    if status is not None:
        keep &= status != 3
    est = InServiceEstimator(params or load_params(), max_samples=max_samples).estimate(
        a['spool_position_m'][keep], a['load_flow_m3_s'][keep], a['p12_pa'][keep])
    level, text = classify(est, HealthThresholds.load())
    models = a.get('model')
    return {'file': str(path), 'model': str(models[0]) if models is not None and models.size
            else '', 'samples_in_file': int(t.size), 'samples_used': est.samples_used,
            't_from_s': float(t[keep].min()), 't_to_s': float(t[keep].max()),
            'radial_clearance_m': est.radial_clearance_m,
            'radial_clearance_std_m': est.radial_clearance_std_m, 'overlap_m': est.overlap_m,
            'overlap_std_m': est.overlap_std_m,
            'pressure_residual_pa': est.pressure_residual_pa, 'method': est.method,
            'level': LEVELS[level], 'message': text}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='eha-diagnose', description=__doc__.splitlines()[0])
    ap.add_argument('file')
    ap.add_argument('--window', type=float, default=None, help='last S seconds only')
    ap.add_argument('--skip', type=float, default=0.05, help='drop the first S seconds')
    ap.add_argument('--params', default=None, help='physical parameter YAML')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    try:
        r = diagnose(args.file, load_params(args.params), args.window, args.skip)
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
