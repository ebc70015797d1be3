"""Sensitivity screening of the diagnosis: Morris elementary effects (SALib) of every drawn
plant parameter of ``config/tolerances.yaml`` on every estimate of the settled valve test and
of the pre-flight check, in units of the estimate's stated deviation.

Factors, per test: every ``nuisance`` and ``negligible`` parameter over its range (a factor on
nominal, an absolute range, or a ratio to its breakaway friction), the measured conditions over
the service envelope less the sensors' errors (the fluid through its temperature), the other
test's estimated items over their estimators' ranges, and a yardstick: ``noise_seed`` (the
torque-motor noise and sensor seed, two values), whose effect is what another noise seed does.
The test's own items stay at the nominal valve, so an estimate's change is its error's change.
A parameter the test's model does not contain (the coil noise in the valve test, which imposes
the spool position) is listed with effect 0 and the reason (``not_in_model``).
Every case runs through the sweep engine (``eha_ros.sweep``), one Morris design per test
(``--trajectories`` trajectories of ``k + 1`` points on a 4-level grid, seeded).

Then Sobol indices (:func:`sobol`) of the few parameters that matter: the
``--sobol-factors`` largest by Morris, over their ranges, the rest nominal.

Beside it, one at a time: each factor alone at either end of its range, every other parameter
nominal (the nominal valve's own deviation as the unit), and whether an end is flagged as a
mismatch.

Per test and estimate: ``mu_star`` (mean absolute elementary effect: about what the whole
range does), its 95 % bootstrap half-width and ``sigma`` (spread of the effects: interaction
or non-linearity), each divided by the median stated deviation of the estimate over the
design's cases; per parameter the largest over the test's estimates.  The classification
rule of ``config/tolerances.yaml``: ``negligible`` is a largest effect under 0.2.  Cases the
test cannot assess (an error, too few settled points) drop their trajectory; the count is
reported.

The unit of an effect is the median deviation the estimator states on the design's cases it
does not flag as a mismatch (a mismatch widens the deviation to the item's range); the median
over every case is listed beside it.

Writes ``screening.json`` (the figures), ``screening.md`` (the table), ``screening.png``
(largest effect per parameter) and ``design_<test>.npz`` (the design and its rows) into
``--out`` (default ``docs/screening``), and prints the JSON.

    python bench/sensitivity.py [--tests valve_test,preflight] [--trajectories 8]
        [--workers 2] [--seed 2027] [--sobol-factors 6] [--sobol-n 64]
        [--out docs/screening] [--smoke]

``--smoke``: two trajectories of the pre-flight check over six factors (one of each kind), in
process, written to a temporary folder: a check that the bench runs, no figure.
"""

import argparse
import json
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from eha_ros.health.preflight import FAULTS  # noqa: E402
from eha_ros.physics import default_params, params_to_dict  # noqa: E402
from eha_ros.physics.bench import load_bench  # noqa: E402
from eha_ros.physics.maps import WEAR_RANGES  # noqa: E402
from eha_ros.physics.tolerances import DRAWN, NEGLIGIBLE_SIGMA, load_tolerances  # noqa: E402
from eha_ros.training.preflight import inner_service  # noqa: E402

#: The valve fit's items: (estimate column, deviation column, plant parameter, range).
VALVE_ITEMS = (
    ('est_radial_clearance_m', 'est_radial_clearance_std_m', 'radial_clearance_m',
     WEAR_RANGES['radial_clearance_m']),
    ('est_overlap_m', 'est_overlap_std_m', 'overlap_supply_m', WEAR_RANGES['overlap_m']),
    ('est_valve_degradation', 'est_valve_degradation_std', 'valve_degradation', (0.0, 0.2)),
    ('est_leakage_coeff_m3_s_pa', 'est_leakage_coeff_m3_s_pa_std', 'leakage_coeff_m3_s_pa',
     (1e-13, 1e-12)))
#: The pre-flight network's items, the same way.
PREFLIGHT_ITEMS = tuple((f'est_{f.name}', f'std_{f.name}', f.name, (f.lo, f.hi))
                        for f in FAULTS)
TESTS = {'valve_test': VALVE_ITEMS, 'preflight': PREFLIGHT_ITEMS}
CONDITIONS = ('supply_pressure_pa', 'return_pressure_pa', 'fluid_temperature_k')
#: Parameters a test's model does not contain (effect 0 by construction), with the reason.
NOT_IN_MODEL = {'valve_test': {
    'noise_std_a': 'the valve test imposes the spool position: no coil current, no noise',
    'noise_sample_time_s': 'the valve test imposes the spool position: no coil current'}}
#: The factors of a ``--smoke`` run: one of each kind (an absolute, a relative and a ratio
#: range, a condition through the fluid law, the yardstick), plus the other test's first item.
SMOKE_FACTORS = ('external_force_n', 'discharge_coefficient', 'spool_dynamic_friction_n',
                 'fluid_temperature_k', 'noise_seed')
NOISE_SEEDS = (0, 1)


def factors(test: str, smoke: bool = False) -> list:
    """``[(name, kind, payload)]`` of the test's Morris factors (module docstring); ``smoke``:
    those of :data:`SMOKE_FACTORS` and the other test's first item."""
    tol = load_tolerances()
    out = [(n, 'tolerance', t) for n, t in tol.items()
           if t.klass in DRAWN and n not in NOT_IN_MODEL.get(test, {})]
    service = inner_service(load_bench())
    out += [(n, 'condition', service[n]) for n in CONDITIONS]
    other = PREFLIGHT_ITEMS if test == 'valve_test' else VALVE_ITEMS
    out += [(param, 'item', rng) for _, _, param, rng in other]
    out.append(('noise_seed', 'seed', NOISE_SEEDS))
    if smoke:
        first = other[0][2]
        out = [f for f in out if f[0] in SMOKE_FACTORS or f[0] == first]
    return out


def case_of(fs: list, u: np.ndarray, bench) -> dict:
    """The plant changes and seed of one design point ``u`` in [0, 1]^k."""
    p0 = default_params()
    c, ratios, seed = {}, [], 0
    for (name, kind, payload), x in zip(fs, u):
        if kind == 'tolerance':
            if payload.ratio_of:
                ratios.append((name, payload, x))
                continue
            lo, hi = payload.bounds(p0)
            c[name] = float(lo + x * (hi - lo))
        elif kind == 'condition':
            v = float(payload[0] + x * (payload[1] - payload[0]))
            c[name] = v
        elif kind == 'item':
            c[name] = float(payload[0] + x * (payload[1] - payload[0]))
        else:
            seed = int(payload[int(x >= 0.5)])
    for name, t, x in ratios:   # dynamic frictions on their (possibly drawn) breakaway values
        ref = c.get(t.ratio_of, getattr(p0, t.ratio_of))
        c[name] = float((t.lo + x * (t.hi - t.lo)) * ref)
    if 'overlap_supply_m' in c:
        c['overlap_return_m'] = c['overlap_supply_m']
    c['seed'] = seed
    return c


def run_design(test: str, cases: list, workers: int):
    """The sweep's rows of ``cases`` in order."""
    from eha_ros.sweep import parse_spec, read_dataset, run_sweep
    items = TESTS[test]
    metrics = [m for e, s, _, _ in items for m in (e, s)] + ['mismatch']
    if test == 'valve_test':   # every metric of the procedure (it writes them all)
        raw = {'procedure': 'valve_test', 'valve_test_procedure': 'settled'}
    else:
        raw = {'procedure': 'preflight_check', 'noise': True, 'metrics': metrics + ['ood_score']}
    raw.update(models=['hf'], cases=cases)
    spec = parse_spec(raw, source=f'screening ({test})', base=params_to_dict(default_params()))
    ids = [pt.cases[0].case_id for pt in spec.points()]
    with tempfile.TemporaryDirectory(prefix='eha-screening-') as tmp:
        run_sweep(spec, Path(tmp) / 'sweep', workers=workers, in_process=workers <= 1,
                  progress=False)
        rows = {r['case_id']: r for r in read_dataset(Path(tmp) / 'sweep').to_pylist()}
    return [rows[i] for i in ids]


def screen(test: str, trajectories: int, seed: int, workers: int,
           keep_dir: Path | None = None, smoke: bool = False) -> dict:
    """The Morris figures of one test (module docstring)."""
    from SALib.analyze import morris as morris_analyze
    from SALib.sample import morris as morris_sample
    t0 = time.perf_counter()
    fs = factors(test, smoke)
    k = len(fs)
    problem = {'num_vars': k, 'names': [f[0] for f in fs], 'bounds': [[0.0, 1.0]] * k}
    x = morris_sample.sample(problem, trajectories, num_levels=4, seed=seed)
    bench = load_bench()
    rows = run_design(test, [case_of(fs, u, bench) for u in x], workers)
    ok = np.array([r['status'] == 'ok' for r in rows])
    per_traj = ok.reshape(trajectories, k + 1).all(axis=1)
    if per_traj.sum() < 2:
        raise SystemExit(f'sensitivity: {test}: fewer than two complete trajectories '
                         f'({int(ok.sum())} of {ok.size} cases ran)')
    keep = np.repeat(per_traj, k + 1)
    xs = x[keep]
    out = {'factors': k, 'trajectories': trajectories,
           'trajectories_complete': int(per_traj.sum()), 'cases': int(ok.size),
           'cases_failed': int((~ok).sum()),
           'first_failure': next((r['error'] for r in rows if r['status'] != 'ok'), None),
           'mismatch_share': round(float(np.mean([bool(r['mismatch']) for r, o in
                                                  zip(rows, ok) if o])), 3),
           'estimates': {}}
    largest = {n: 0.0 for n in problem['names']}
    out['not_in_model'] = NOT_IN_MODEL.get(test, {})
    kept = [r for r, kk in zip(rows, keep) if kk]
    # the unit: the deviation the estimator states where it does assess (a mismatch widens
    # its deviation to the item's range, which would shrink every effect)
    assessed = [r for r in kept if not r['mismatch']]
    out['stated_std_from'] = ('cases not flagged as mismatch' if len(assessed) >= 5 else
                              'every case (fewer than 5 not flagged as mismatch)')
    ref_rows = assessed if len(assessed) >= 5 else kept
    for est, std, param, _ in TESTS[test]:
        y = np.array([r[est] for r in kept], dtype=float)
        s_ref = float(np.median([r[std] for r in ref_rows]))
        res = morris_analyze.analyze(problem, xs, y, num_levels=4, seed=seed)
        table = {}
        for j, name in enumerate(problem['names']):
            table[name] = {'mu_star_sigma': round(float(res['mu_star'][j]) / s_ref, 4),
                           'mu_star_conf_sigma': round(float(res['mu_star_conf'][j]) / s_ref,
                                                       4),
                           'sigma_sigma': round(float(res['sigma'][j]) / s_ref, 4)}
            largest[name] = max(largest[name], table[name]['mu_star_sigma'])
        out['estimates'][param] = {
            'stated_std_median': s_ref,
            'stated_std_median_every_case': float(np.median([r[std] for r in kept])),
            'effects': table}
    if keep_dir is not None:   # the design and its rows, to analyse again without running
        np.savez_compressed(keep_dir / f'design_{test}.npz', x=x, names=problem['names'],
                            rows=json.dumps([{k: r.get(k) for k in ('status', 'mismatch') + tuple(
                                c for e, sd, _, _ in TESTS[test] for c in (e, sd))}
                                for r in rows]))
    largest.update({n: 0.0 for n in out['not_in_model']})
    out['largest_effect_sigma'] = {n: round(v, 4) for n, v in
                                   sorted(largest.items(), key=lambda kv: -kv[1])}
    out['wall_s'] = round(time.perf_counter() - t0, 1)
    return out


def one_at_a_time(test: str, workers: int, smoke: bool = False) -> dict:
    """Each factor alone at the two ends of its range, every other parameter nominal: per
    estimate and factor the larger change from the nominal valve's estimate in units of the
    nominal valve's stated deviation, and whether either end is flagged as a mismatch."""
    fs = [f for f in factors(test, smoke) if f[1] != 'seed']
    bench = load_bench()
    cases = [{'seed': 0}] + [case_of([f], [end], bench) for f in fs for end in (0.0, 1.0)]
    # an end at the nominal value is the nominal case: every distinct case runs once
    nominal = params_to_dict(default_params())
    keys = [json.dumps({k: v for k, v in c.items() if k == 'seed' or v != nominal[k]},
                       sort_keys=True) for c in cases]
    unique = list(dict.fromkeys(keys))
    ran = dict(zip(unique, run_design(test, [json.loads(k) for k in unique], workers)))
    rows = [ran[k] for k in keys]
    if rows[0]['status'] != 'ok':
        raise SystemExit(f'sensitivity: {test}: the nominal valve did not run: '
                         f'{rows[0]["error"]}')
    out = {'nominal_mismatch': bool(rows[0]['mismatch']), 'estimates': {}, 'largest': {}}
    for est, std, param, _ in TESTS[test]:
        y0, s0 = rows[0][est], rows[0][std]
        table = {}
        for j, (name, _, _) in enumerate(fs):
            lo, hi = rows[1 + 2 * j], rows[2 + 2 * j]
            if lo['status'] != 'ok' or hi['status'] != 'ok':
                table[name] = {'error': (lo if lo['status'] != 'ok' else hi)['error']}
                continue
            table[name] = {'change_sigma': round(max(abs(lo[est] - y0), abs(hi[est] - y0)) / s0,
                                                 4),
                           'mismatch_at_an_end': bool(lo['mismatch'] or hi['mismatch'])}
            out['largest'][name] = max(out['largest'].get(name, 0.0),
                                       table[name]['change_sigma'])
        out['estimates'][param] = {'nominal_estimate': y0, 'nominal_std': s0, 'effects': table}
    out['largest'] = dict(sorted(out['largest'].items(), key=lambda kv: -kv[1]))
    out['flagged_at_an_end'] = sorted({n for e in out['estimates'].values()
                                       for n, v in e['effects'].items()
                                       if v.get('mismatch_at_an_end')})
    return out


def sobol(test: str, morris: dict, n: int, seed: int, workers: int, top: int,
          smoke: bool = False) -> dict:
    """First-order and total Sobol indices (SALib; Saltelli's scheme, no second order) of the
    ``top`` factors with the largest Morris effects on the test's estimates, over their
    ranges, every other parameter nominal and the noise seed 0 (the yardstick is no factor
    here): the few that matter, apportioned.  Per estimate: ``S1`` and ``ST`` with their 95 %
    half-widths, and the estimate's standard deviation over the design in units of its median
    stated deviation (``std_sigma``, on the cases not flagged as a mismatch): how much the
    few parameters move it together.  ``n`` (a power of two) base samples give
    ``n (top + 2)`` cases."""
    from SALib.analyze import sobol as sobol_analyze
    from SALib.sample import sobol as sobol_sample
    t0 = time.perf_counter()
    by_name = {f[0]: f for f in factors(test, smoke)}
    ranked = [name for name in morris['largest_effect_sigma'] if name in by_name
              and by_name[name][1] != 'seed' and name not in morris['not_in_model']]
    fs = [by_name[name] for name in ranked[:top]]
    problem = {'num_vars': len(fs), 'names': [f[0] for f in fs],
               'bounds': [[0.0, 1.0]] * len(fs)}
    x = sobol_sample.sample(problem, n, calc_second_order=False, seed=seed)
    bench = load_bench()
    rows = run_design(test, [case_of(fs, u, bench) for u in x], workers)
    ok = [r['status'] == 'ok' for r in rows]
    out = {'factors': problem['names'], 'base_samples': n, 'cases': len(rows),
           'cases_failed': int(len(rows) - sum(ok)),
           'mismatch_share': round(float(np.mean([bool(r['mismatch']) for r, o in
                                                  zip(rows, ok) if o])), 3)
           if any(ok) else None, 'estimates': {}}
    if not all(ok):   # the indices need every case: said, not filled in
        out['not_analysed'] = (f'{out["cases_failed"]} of {len(rows)} cases did not run, '
                               f'first: {next(r["error"] for r in rows if r["status"] != "ok")}')
        return out
    assessed = [r for r in rows if not r['mismatch']]
    for est, std, param, _ in TESTS[test]:
        y = np.array([r[est] for r in rows], dtype=float)
        s_ref = float(np.median([r[std] for r in (assessed if len(assessed) >= 5 else rows)]))
        res = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=seed)
        out['estimates'][param] = {
            'std_sigma': round(float(np.std(y)) / s_ref, 4),
            **{key: {name: round(float(v), 4) for name, v in zip(problem['names'], res[key])}
               for key in ('S1', 'S1_conf', 'ST', 'ST_conf')}}
    out['wall_s'] = round(time.perf_counter() - t0, 1)
    return out


def classify(result: dict) -> dict:
    """``{parameter: (largest effect over the tests, Morris and one at a time, class by the
    rule)}`` of the drawn parameters, with the class ``config/tolerances.yaml`` gives them."""
    tol = load_tolerances()
    out = {}
    for name, t in tol.items():
        if t.klass not in DRAWN:
            continue
        eff = max(max(r['largest_effect_sigma'].get(name, 0.0),
                      r.get('one_at_a_time', {}).get('largest', {}).get(name, 0.0))
                  for r in result['tests'].values())
        out[name] = {'largest_effect_sigma': eff, 'class': t.klass,
                     'by_the_rule': 'negligible' if eff < NEGLIGIBLE_SIGMA else 'nuisance'}
    return out


def write_report(result: dict, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / 'screening.json').write_text(json.dumps(result, indent=1) + '\n')
    cls = result['classification']
    tests = list(result['tests'])
    lines = ['# Sensitivity screening (Morris, SALib)', '',
             f'`python bench/sensitivity.py` ({result["trajectories"]} trajectories, seed '
             f'{result["seed"]}; load {result["load_before"]} before, '
             f'{result["load_after"]} after). Largest effect of each parameter\'s range on any '
             'estimate of the test, in units of that estimate\'s stated deviation '
             f'(negligible: below {NEGLIGIBLE_SIGMA}).', '',
             'Morris: over the design (every parameter drawn at once); alone: the parameter '
             'alone at either end of its range, the rest nominal.', '',
             '| parameter | class | ' + ' | '.join(f'{t} Morris | {t} alone' for t in tests)
             + ' |',
             '| --- | --- | ' + ' | '.join('---: | ---:' for _ in tests) + ' |']
    names = sorted(set().union(*(r['largest_effect_sigma'] for r in result['tests'].values())),
                   key=lambda n: -max(r['largest_effect_sigma'].get(n, 0.0)
                                      for r in result['tests'].values()))
    tol = load_tolerances()
    for n in names:
        klass = cls[n]['class'] if n in cls else (
            tol[n].klass if n in tol else 'yardstick' if n == 'noise_seed' else 'condition')
        cells = []
        for t in tests:
            r = result['tests'][t]
            v = r['largest_effect_sigma'].get(n)
            cells.append('held (its own item)' if v is None else
                         '0 (not in its model)' if n in r['not_in_model'] else f'{v:.3g}')
            alone = r.get('one_at_a_time', {}).get('largest', {}).get(n)
            cells.append('-' if alone is None else f'{alone:.3g}')
        lines.append(f'| `{n}` | {klass} | ' + ' | '.join(cells) + ' |')
    for t in tests:
        sb = result['tests'][t].get('sobol')
        if not sb:
            continue
        lines += ['', f'## Sobol indices, {t}', '',
                  f'{sb["cases"]} cases ({sb["base_samples"]} base samples), the '
                  f'{len(sb["factors"])} parameters with the largest Morris effects over '
                  'their ranges, the rest nominal. Per estimate: its spread over the design '
                  'in stated sigma, then first-order / total index of each parameter.', '']
        if 'not_analysed' in sb:
            lines.append(f'Not analysed: {sb["not_analysed"]}.')
            continue
        lines += ['| estimate | spread [sigma] | ' + ' | '.join(f'`{n}`' for n in sb['factors'])
                  + ' |', '| --- | ---: | ' + ' | '.join('---:' for _ in sb['factors']) + ' |']
        for param, e in sb['estimates'].items():
            lines.append(f'| `{param}` | {e["std_sigma"]:.3g} | ' + ' | '.join(
                f'{e["S1"][n]:.2f} / {e["ST"][n]:.2f}' for n in sb['factors']) + ' |')
    (folder / 'screening.md').write_text('\n'.join(lines) + '\n')
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 0.22 * len(names) + 1.5))
    yy = np.arange(len(names))
    for j, t in enumerate(tests):
        v = [max(result['tests'][t]['largest_effect_sigma'].get(n, 0.0), 1e-4) for n in names]
        ax.barh(yy + 0.4 * j - 0.2, v, height=0.4, label=t)
    ax.axvline(NEGLIGIBLE_SIGMA, color='k', lw=0.8, ls='--', label='negligible below')
    ax.set_xscale('log')
    ax.set_yticks(yy, names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel('largest Morris effect over the estimates [stated sigma]')
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / 'screening.png', dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--tests', default='valve_test,preflight')
    ap.add_argument('--trajectories', type=int, default=8)
    ap.add_argument('--workers', type=int, default=2, help='sweep workers (1: in process)')
    ap.add_argument('--seed', type=int, default=2027)
    ap.add_argument('--out', type=Path, default=None, help='report folder (docs/screening)')
    ap.add_argument('--sobol-factors', type=int, default=6,
                    help='Sobol indices of this many factors, the largest by Morris (0: none)')
    ap.add_argument('--sobol-n', type=int, default=64,
                    help='Sobol base samples, a power of two: n (factors + 2) cases a test')
    ap.add_argument('--smoke', action='store_true', help='a tiny design: a check, no figure')
    args = ap.parse_args(argv)
    tests = [t for t in args.tests.split(',') if t]
    unknown = [t for t in tests if t not in TESTS]
    if unknown or not tests:
        ap.error(f'--tests: unknown {", ".join(unknown) or "(none)"}; known: {", ".join(TESTS)}')
    if args.trajectories < 2 or args.workers < 1:
        ap.error('--trajectories must be at least 2 and --workers at least 1')
    if args.sobol_factors < 0 or args.sobol_n < 2 or args.sobol_n & (args.sobol_n - 1):
        ap.error(f'--sobol-factors {args.sobol_factors} must be at least 0 and --sobol-n '
                 f'{args.sobol_n} a power of two')
    scratch = None
    if args.smoke:
        tests, args.trajectories, args.workers = ['preflight'], 2, 1
        args.sobol_factors, args.sobol_n = min(args.sobol_factors, 2), 4
        if args.out is None:
            args.out = Path(scratch := tempfile.mkdtemp(prefix='eha-screening-'))
    out = args.out or Path('docs/screening')
    result = {'benchmark': 'sensitivity', 'smoke': args.smoke, 'method': 'morris',
              'trajectories': args.trajectories, 'seed': args.seed, 'levels': 4,
              'load_before': [round(v, 2) for v in os.getloadavg()], 'tests': {}}
    try:
        for t in tests:
            out.mkdir(parents=True, exist_ok=True)
            result['tests'][t] = screen(t, args.trajectories, args.seed, args.workers, out,
                                        args.smoke)
            result['tests'][t]['one_at_a_time'] = one_at_a_time(t, args.workers, args.smoke)
            if args.sobol_factors:
                result['tests'][t]['sobol'] = sobol(t, result['tests'][t], args.sobol_n,
                                                    args.seed, args.workers,
                                                    args.sobol_factors, args.smoke)
        result['classification'] = classify(result)
        result['load_after'] = [round(v, 2) for v in os.getloadavg()]
        write_report(result, out)
    finally:
        if scratch:
            shutil.rmtree(scratch)
    print(json.dumps(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
