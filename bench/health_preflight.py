"""The pre-flight fault network under drift: accuracy, coverage, false alarms and refusals.

Every case runs the high-fidelity plant's pre-flight check as one sweep
(:class:`eha_ros.health.procedures.PreflightProcedure`: the network's estimates with the
conditions the bench measures, its OOD score and mismatch flag), on streams used neither for
training nor calibration nor the OOD limit (:mod:`eha_ros.training.preflight`: 21-24):

``clean`` (stream 41)
    Faults drawn as for training (half every fault uniform, half sparse), every other
    parameter nominal, nominal conditions: per fault the mean absolute error in % of range.
``drifted`` (stream 42)
    The same faults with every nuisance of ``config/test_bench.yaml`` and the clearance and
    overlap uniform over their ranges, and the true conditions uniform over the service
    envelope less each sensor's calibration error and three noise deviations (measured, they
    lie in the envelope; :func:`eha_ros.training.preflight.inner_service`): per fault the
    mean absolute error in % of range, the fraction within 2 sigma, and the fraction flagged
    as mismatch.
``nominal`` (stream 43)
    Nominal valves (all five faults nominal) with drift as ``drifted``, own noise seeds: false
    alarms (a fault graded above OK by :func:`eha_ros.health.thresholds.classify_fault`, or a
    mismatch flag).
``beyond`` (stream 44)
    Drifted cases with one entry of the bench's ``beyond`` section applied (a factor on the
    nominal value, or a value; temperatures through the fluid law): the fraction flagged as
    mismatch, per entry too, and ``silent_misses``: fault items not flagged whose 2-sigma
    interval excludes the truth.
``fleet`` (stream 45)
    Drifted cases as ``drifted`` on units of a fleet: every nuisance of
    ``config/tolerances.yaml`` uniform over its range besides
    (:func:`eha_ros.physics.tolerances.draw_unit`): per fault the mean and max absolute error
    in % of range and the fraction within 2 sigma, over every check and over those not
    refused, the share refused (mismatch), the OK grades whose 2-sigma interval excludes the
    truth, and the share of each fault's mean square error each drawn parameter explains
    (:func:`eha_ros.physics.tolerances.error_shares`, a linear fit on the fleet itself).

    PYTHONPATH=. python bench/health_preflight.py [--workers 2] [--smoke] [--sets fleet,...]

``--smoke``: one or two cases per set (:data:`SMOKE_SIZES`), in process: a check, no figure.
"""

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from eha_ros.health.preflight import FAULTS, FAULT_NAMES, load_faults
from eha_ros.health.thresholds import OK, HealthThresholds, classify_fault
from eha_ros.physics import default_params, params_to_dict
from eha_ros.physics.bench import load_bench
from eha_ros.physics.tolerances import error_shares
from eha_ros.training.preflight import cases, draw_drift, wear_changes

STREAM_CLEAN, STREAM_DRIFTED, STREAM_NOMINAL, STREAM_BEYOND = 41, 42, 43, 44
STREAM_FLEET = 45
SIZES = {'clean': 100, 'drifted': 240, 'nominal': 24, 'beyond_per_entry': 8, 'fleet': 400}
SMOKE_SIZES = {'clean': 2, 'drifted': 2, 'nominal': 1, 'beyond_per_entry': 1, 'fleet': 2}
SETS = ('clean', 'drifted', 'nominal', 'beyond', 'fleet')


def beyond_entries(bench=None) -> list:
    """``(label, plant changes)`` of every value of the bench's ``beyond`` section."""
    b = bench or load_bench()
    p = default_params()
    out = []
    for name, e in b.beyond.items():
        values = ([f * getattr(p, name) for f in e['factors']] if 'factors' in e
                  else [float(v) for v in e['values']])
        for v in values:
            changes = {name: v}
            out.append((f'{name}={v:.4g}', changes))
    return out


def bench_cases(sizes: dict = SIZES) -> dict:
    """``{set: [(label, plant changes, seed)]}`` of the sets, of ``sizes``."""
    b, p = load_bench(), default_params()
    clean = cases(sizes['clean'], STREAM_CLEAN, drift=False)
    drifted = cases(sizes['drifted'], STREAM_DRIFTED, inner=True)
    fleet = cases(sizes['fleet'], STREAM_FLEET, inner=True, fleet=True)
    out = {'clean': [('clean', w, s) for w, s in clean],
           'drifted': [('drifted', w, s) for w, s in drifted],
           'fleet': [('fleet', w, s) for w, s in fleet],
           'nominal': [], 'beyond': []}
    for i in range(sizes['nominal']):
        rng = np.random.default_rng([STREAM_NOMINAL, i])
        wear = {f.name: f.nominal for f in FAULTS}
        wear.update(draw_drift(rng, b, p, inner=True))
        out['nominal'].append(('nominal', wear, int(rng.integers(0, 2 ** 31 - 1))))
    entries = beyond_entries(b)
    drifted = cases(sizes['beyond_per_entry'] * len(entries), STREAM_BEYOND, inner=True)
    for k, (wear, seed) in enumerate(drifted):
        label, changes = entries[k % len(entries)]
        out['beyond'].append((label, {**wear, **changes}, seed))
    return out


def _run(all_cases: list, workers: int) -> list:
    """The network's metrics of every ``(label, changes, seed)``, in order."""
    from eha_ros.sweep import SweepError, parse_spec, read_dataset, run_sweep
    metrics = ([f'est_{n}' for n in FAULT_NAMES] + [f'std_{n}' for n in FAULT_NAMES]
               + ['ood_score', 'mismatch'])
    raw = {'procedure': 'preflight_check', 'models': ['hf'], 'noise': True,
           'metrics': metrics,
           'cases': [{**wear_changes(w), 'seed': int(s)} for _, w, s in all_cases]}
    spec = parse_spec(raw, source='pre-flight drift bench',
                      base=params_to_dict(default_params()))
    ids = [pt.cases[0].case_id for pt in spec.points()]
    with tempfile.TemporaryDirectory(prefix='eha-preflight-bench-') as tmp:
        run_sweep(spec, Path(tmp) / 'sweep', workers=workers, in_process=workers <= 1,
                  progress=False)
        rows = {r['case_id']: r for r in read_dataset(Path(tmp) / 'sweep').to_pylist()}
    bad = [rows[i] for i in ids if rows[i]['status'] != 'ok']
    if bad:
        raise SweepError(f'pre-flight drift bench: {len(bad)} cases did not run, first: '
                         f'{bad[0]["error"]}')
    return [rows[i] for i in ids]


def _errors(rows, wears):
    span = np.array([f.span for f in FAULTS])
    est = np.array([[r[f'est_{n}'] for n in FAULT_NAMES] for r in rows])
    std = np.array([[r[f'std_{n}'] for n in FAULT_NAMES] for r in rows])
    truth = np.array([[w[n] for n in FAULT_NAMES] for w in wears])
    return np.abs(est - truth), std, span


def _per_fault(a, digits=3) -> dict:
    return dict(zip(FAULT_NAMES, np.round(a, digits).tolist()))


def fleet_figures(pairs, limits) -> dict:
    """The ``fleet`` set's figures (module docstring) of ``[((label, changes, seed), row)]``."""
    rows, wears = [r for _, r in pairs], [w for (_, w, _), _ in pairs]
    err, std, span = _errors(rows, wears)
    est = np.array([[r[f'est_{n}'] for n in FAULT_NAMES] for r in rows])
    truth = np.array([[w[n] for n in FAULT_NAMES] for w in wears])
    refused = np.array([bool(r['mismatch']) for r in rows])
    out = {'cases': len(pairs), 'refused': round(float(refused.mean()), 3)}
    for tag, m in (('all', np.ones(len(rows), bool)), ('assessed', ~refused)):
        if m.any():
            out[tag] = {'n': int(m.sum()),
                        'mean_abs_error_pct': _per_fault(100 * err[m].mean(axis=0) / span),
                        'max_abs_error_pct': _per_fault(100 * err[m].max(axis=0) / span),
                        'within_2sigma': _per_fault(np.mean(err[m] <= 2 * std[m], axis=0))}
    ok_out = 0
    for i, r in enumerate(rows):
        if refused[i]:
            continue
        for j, n in enumerate(FAULT_NAMES):
            graded_ok = classify_fault(n, r[f'est_{n}'], r[f'std_{n}'], limits)[0] == OK
            ok_out += int(graded_ok and err[i, j] > 2 * std[i, j])
    out['ok_excluding_truth'] = ok_out
    try:
        shares = error_shares((est - truth) / span, wears)
        out['error_shares'] = dict(zip(FAULT_NAMES, shares))
    except ValueError as exc:
        out['error_shares'] = None
        out['error_shares_not_computed'] = str(exc)
    return out


def preflight_drift(workers: int = 2, sizes: dict = SIZES, only=SETS) -> dict:
    """The figures of the module's sets ``only`` (one sweep on ``workers`` processes)."""
    t0 = time.perf_counter()
    sets = bench_cases(sizes)
    order = [name for name in SETS if name in only]
    flat = [c for name in order for c in sets[name]]
    rows = _run(flat, workers)
    by_set, k = {}, 0
    for name in order:
        by_set[name] = list(zip(sets[name], rows[k:k + len(sets[name])]))
        k += len(sets[name])
    limits = HealthThresholds.load()
    out = {'sets': order,
           'network': {kk: load_faults().meta.get(kk) for kk in ('sizes', 'streams')}}
    for name in ('clean', 'drifted'):
        if name not in by_set:
            continue
        pairs = by_set[name]
        err, std, span = _errors([r for _, r in pairs], [w for (_, w, _), _ in pairs])
        out[name] = {'cases': len(pairs),
                     'mean_abs_error_pct': _per_fault(100 * err.mean(axis=0) / span),
                     'within_2sigma': _per_fault(np.mean(err <= 2 * std, axis=0)),
                     'mismatch_rate': round(float(np.mean([r['mismatch'] for _, r in pairs])),
                                            3)}
    if 'fleet' in by_set:
        out['fleet'] = fleet_figures(by_set['fleet'], limits)
    alarms = []
    for (_, w, seed), r in by_set.get('nominal', []):
        raised = [n for n in FAULT_NAMES
                  if classify_fault(n, r[f'est_{n}'], r[f'std_{n}'], limits)[0] != OK]
        if raised or r['mismatch']:
            alarms.append({'seed': seed, 'faults': raised, 'mismatch': bool(r['mismatch']),
                           'ood_score': round(r['ood_score'], 3)})
    if 'nominal' in by_set:
        scores = [r['ood_score'] for _, r in by_set['nominal']]
        out['nominal'] = {'valves': len(by_set['nominal']), 'false_alarms': len(alarms),
                          'alarms': alarms, 'ood_score_max': round(float(np.max(scores)), 3)}
    per_entry, silent = {}, 0
    for (label, w, _), r in by_set.get('beyond', []):
        per_entry.setdefault(label, []).append(bool(r['mismatch']))
        if not r['mismatch']:
            err, std, _ = _errors([r], [w])
            silent += int(np.sum(err > 2 * std))
    hits = [h for v in per_entry.values() for h in v]
    if 'beyond' in by_set:
        out['beyond'] = {'cases': len(hits), 'mismatch_hit_rate': round(float(np.mean(hits)), 3),
                         'per_entry': {k: round(float(np.mean(v)), 3)
                                       for k, v in per_entry.items()},
                         'silent_misses': silent}
    out['ood_limit'] = load_faults().ood.limit
    out['wall_s'] = round(time.perf_counter() - t0, 1)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description='pre-flight fault network under drift')
    ap.add_argument('--workers', type=int, default=None,
                    help='sweep workers (1: in process; default 2, with --smoke 1)')
    ap.add_argument('--smoke', action='store_true',
                    help='one or two cases per set: a check, no figure')
    ap.add_argument('--sets', default=','.join(SETS),
                    help=f'comma-separated sets to run (default all: {",".join(SETS)})')
    args = ap.parse_args(argv)
    only = tuple(x for x in args.sets.split(',') if x)
    bad = [x for x in only if x not in SETS]
    if bad or not only:
        ap.error(f'--sets: unknown set {bad[0]!r} (known: {", ".join(SETS)})' if bad
                 else '--sets: name at least one set')
    if args.workers is None:
        args.workers = 1 if args.smoke else 2
    if args.workers < 1:
        ap.error(f'--workers {args.workers} must be at least 1')
    out = {'benchmark': 'health_preflight', 'smoke': args.smoke,
           'load_before': [round(v, 2) for v in os.getloadavg()],
           **preflight_drift(args.workers, SMOKE_SIZES if args.smoke else SIZES, only)}
    out['load_after'] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(out, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
