"""``eha-campaign`` (``make demo``): the reference's EHA test campaign through the ROS graph.

Every scenario of the reference's section 6.3 (steps, ramps and sines of 0.1 and 0.01 mm) is
run through the node graph in lockstep with the high-fidelity fluid block and with the
recommended surrogate plant (``dlut``, dynamic lookup table) - ``--models`` chooses - each run
recorded to MCAP by the ``recorder`` node.  The recorded surrogate runs are compared with the hf
run of the same scenario (relative Euclidean-norm error of jack position, P12 and spool
position, as ``eha-compare``), the hf recordings are diagnosed offline (``eha-diagnose``), and a
report is written: ``report.md`` and one folder of PNG plots per scenario (the reference's
Figures 6.4-6.16).

The surrogate comparison (``--compare-models``, default every shipped surrogate: the dynamic
family and the reference's algebraic ``lut``, ``ga``, ``nn``, ``nn2``) is made physics-only
(:mod:`eha_ros.evaluation`), where noise and perturbations can be controlled: noise off
against the yardstick (hf at half the step and with the discharge coefficient within +-0.1 %), and
with noise over ``--seeds`` seeds against hf's own seed-to-seed spread; plots in
``comparison/`` show the yardstick's band beside the models.  The comparison runs as two
sweeps (:mod:`eha_ros.sweep.comparison`), in its own process while the graph runs; their
datasets stay in ``comparison/sweeps/`` (``eha-sweep report`` reads them).

The health monitor runs live in every run: its ``/eha/health`` and ``/diagnostics`` are
recorded with the rest, and the report's verdicts are the recorded ones; each recording is
also replayed through the monitor's logic offline (``eha-diagnose``), which must give the same
messages bit for bit (``live = offline`` in the report).

Then the maintenance part: the maintenance test (scenario ``maintenance_test_quick``: the
reference's map sweep at one flow run by the plant, then the pre-flight check) on the nominal
valve and on a worn one with a weakened magnet, sticking jack seals and a current offset,
recorded; every estimate (clearance, overlap, demagnetisation, filter
clogging, spool and jack friction, current offset) is read from the recordings against the
truth.

    eha-campaign [--out runs/campaign-<time>] [--scenarios a,b] [--models hf,dlut]
                 [--compare-models dlut,dnn,dga,lut,ga,nn,nn2] [--seeds 10]
                 [--seed-models dlut,dnn,dga,lut,ga]
                 [--valve-tests nominal,worn] [--processes]

Nothing existing is overwritten: the output folder must not exist.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

from eha_ros.graph import ALGEBRAIC_MODELS, DYNAMIC_MODELS, MODELS, REFERENCE_SCENARIOS
from eha_ros.harness import GraphConfig, GraphError, run_graph
from eha_ros.physics import ParameterError, get_scenario, load_params


#: Valves of the maintenance part: wear parameters set on the plant.
VALVES = {
    'nominal': {},
    'worn': {'radial_clearance_m': 4.5e-6, 'overlap_supply_m': -0.5e-6,
             'overlap_return_m': -0.5e-6, 'demagnetisation': 0.3,
             'jack_static_friction_n': 1200.0, 'jack_dynamic_friction_n': 600.0,
             'offset_a': 6e-4},
}


#: The health monitor's in-service period in the campaign: the shortest scenarios last 0.2 s.
HEALTH_PERIOD_S = 0.1


def available_models(models):
    from eha_ros.artefacts import models_dir
    return [m for m in models if m == 'hf' or (models_dir('surrogates') / f'{m}.npz').is_file()]


#: Models run through the graph by default: hf and the recommended surrogate plant.
GRAPH_MODELS = ('hf', 'dlut')
#: Models of the physics-only comparison: the dynamic family, then the reference's.
COMPARE_MODELS = DYNAMIC_MODELS + ALGEBRAIC_MODELS
#: Models also run with noise over the seeds here: the dynamic family and the reference's
#: cheaper two (its networks ``nn``, ``nn2`` cost over 10 x hf per simulated second and miss
#: the noise-free bounds by far; ``bench/inloop.py --noise-models`` runs any).
SEED_MODELS = ('dlut', 'dnn', 'dga', 'lut', 'ga')


def run_campaign(out: Path, scenarios=REFERENCE_SCENARIOS, models=GRAPH_MODELS,
                 processes=False, progress=print, valve_tests=tuple(VALVES),
                 valve_test_scenario='maintenance_test_quick', compare_models=COMPARE_MODELS,
                 seeds: int = 10, seed_models=SEED_MODELS) -> dict:
    """Run, record, compare and report; returns the summary written to ``summary.json``."""
    from eha_ros.recording.compare import compare_runs, load_run, plot_runs
    from eha_ros.isolation import ros_environment
    from eha_ros.tools.diagnose import diagnose

    unknown = [v for v in valve_tests if v not in VALVES]
    if unknown:
        raise ParameterError(f'unknown valve {unknown[0]!r} (one of {", ".join(VALVES)})')
    for sc in scenarios:
        get_scenario(sc)
    out.mkdir(parents=True)
    models = available_models(models)
    # the physics-only comparison runs in its own process while the graph runs (it needs one
    # core, the lockstep graph in one process about one)
    compare = [m for m in available_models(compare_models) if m != 'hf']
    comparer = _start_comparison(out / 'comparison', scenarios, compare, seeds,
                                 [m for m in compare if m in seed_models]) if compare else None
    # (scenario, label, fluid model, plant parameters): the campaign, then the valve tests
    jobs = ([(sc, model, model, {}) for sc in scenarios for model in models]
            + [(valve_test_scenario, valve, 'hf', VALVES[valve]) for valve in valve_tests])
    runs, t_start = {}, time.monotonic()
    try:
        for k, (sc, label, model, plant) in enumerate(jobs, start=1):
            path = out / f'{sc}_{label}.mcap'
            with ros_environment() as env:
                r = run_graph(GraphConfig(scenario=sc, model=model, mode='lockstep',
                                          record=str(path), plant=dict(plant), health=True,
                                          health_params={'update_period_s': HEALTH_PERIOD_S}),
                              processes=processes, env=env, timeout_s=120)
            runs[(sc, label)] = {'file': path.name, 'sim_s': r.sim_s, 'wall_s': round(r.wall_s, 2),
                                 'ticks': int(r.state['tick'].size)}
            progress(f'[{k:2d}/{len(jobs)}] {sc:15s} {label:7s} {r.sim_s:5.2f} s simulated in '
                     f'{r.wall_s:5.1f} s  -> {path.name}')
    except BaseException:
        if comparer is not None:
            comparer.terminate()
        raise
    nominal = load_params()
    from eha_ros.health.monitor import ITEMS
    valve_results = {}
    for valve in valve_tests:
        try:
            d = diagnose(str(out / f'{valve_test_scenario}_{valve}.mcap'))
        except ParameterError as exc:  # reported, not fatal: the other runs stand
            d = {'level': 'n/a', 'message': f'no estimate: {exc}', 'estimates': {},
                 'radial_clearance_m': float('nan'), 'overlap_m': float('nan')}
        d['true'] = {n: VALVES[valve].get(n, getattr(nominal, n)) for n in ITEMS}
        d['true_radial_clearance_m'] = d['true']['radial_clearance_m']
        d['true_overlap_m'] = d['true']['overlap_supply_m']
        valve_results[valve] = d
    health = {f'{s}/{m}': _health_verdict(out / runs[(s, m)]['file'], diagnose)
              for (s, m) in runs}
    table, diagnoses = {}, {}
    for sc in scenarios:
        loaded = [load_run(str(out / f'{sc}_{m}.mcap')) for m in models]
        result = compare_runs(loaded, reference=0)
        plot_runs(loaded, out / sc)
        table[sc] = {r['label']: r['relative_error'] for r in result['runs']}
        diagnoses[sc] = diagnose(str(out / f'{sc}_hf.mcap'), update_period_s=HEALTH_PERIOD_S)
    comparison = _finish_comparison(comparer, out / 'comparison') if comparer else {}
    summary = {'models': models, 'scenarios': list(scenarios),
               'wall_s': round(time.monotonic() - t_start, 1),
               'runs': {f'{s}/{m}': v for (s, m), v in runs.items()},
               'relative_error_vs_hf': table, 'diagnosis_hf': diagnoses,
               'valve_test': valve_results, 'health_live': health,
               'comparison': comparison}
    (out / 'summary.json').write_text(json.dumps(summary, indent=1))
    (out / 'report.md').write_text(_report(summary))
    return summary


def _health_verdict(path: Path, diagnose) -> dict:
    """The live monitor's last verdict from a recording, and whether the offline replay of its
    states gives the same messages."""
    try:
        d = diagnose(str(path), update_period_s=HEALTH_PERIOD_S)
    except ParameterError as exc:
        return {'level': 'n/a', 'message': f'no estimate: {exc}', 'kind': '',
                'live_messages': 0, 'live_agrees': None}
    return {'level': d['level'], 'message': d['message'], 'kind': d['kind'],
            'live_messages': d.get('live_messages', 0), 'live_agrees': d.get('live_agrees')}


def _start_comparison(folder: Path, scenarios, models, seeds, seed_models):
    """Start :func:`_compare` in a fresh process (spawned: it shares nothing with ROS)."""
    import multiprocessing
    folder.mkdir()
    proc = multiprocessing.get_context('spawn').Process(
        target=_compare_to_file, args=(str(folder), list(scenarios), list(models), int(seeds),
                                       list(seed_models)),
        name='eha-campaign-comparison', daemon=True)
    proc.start()
    return proc


def _compare_to_file(folder, scenarios, models, seeds, seed_models):
    res = _compare(Path(folder), scenarios, models, seeds,
                   lambda line: print(line, flush=True), seed_models)
    tmp = Path(folder) / 'comparison.json.partial'
    tmp.write_text(json.dumps(res))
    tmp.replace(Path(folder) / 'comparison.json')


def _finish_comparison(proc, folder: Path) -> dict:
    try:
        proc.join()
    except BaseException:  # interrupted while waiting: the comparison goes too
        proc.terminate()
        raise
    path = folder / 'comparison.json'
    if proc.exitcode != 0 or not path.is_file():
        raise RuntimeError(f'the physics-only comparison failed (exit code {proc.exitcode}); '
                           f'the graph recordings in {folder.parent} are complete')
    return json.loads(path.read_text())


#: Signals the comparison keeps per run for its plots (every controller tick).
COMPARISON_SIGNALS = ('time_s', 'command_m', 'jack_position_m', 'p12_pa')


def _compare(folder: Path, scenarios, models, seeds, progress, seed_models) -> dict:
    """Physics-only comparison of ``models`` with hf (:mod:`eha_ros.evaluation`), noise
    off against the yardstick and, for ``seed_models`` (among ``models``), with noise over
    ``seeds`` seeds, run as two sweeps in this process (:mod:`eha_ros.sweep.comparison`:
    their datasets in ``folder/sweeps``); one plot per scenario."""
    from eha_ros.evaluation import summarise
    from eha_ros.sweep.comparison import run_comparison
    t0 = time.monotonic()
    done = run_comparison(folder / 'sweeps', scenarios, {'nominal': None}, models,
                          seed_models if seeds > 0 else (), seeds, signals=COMPARISON_SIGNALS,
                          in_process=True, warm=False, progress=False)
    res = {'models': list(models), 'seeds': int(seeds), 'noise_free': {}, 'noise': {}}
    for sc in scenarios:
        r = done['noise_free'][f'{sc}/nominal']
        _plot_comparison(r.pop('signals'), folder / f'{sc}.png', sc, r)
        res['noise_free'][sc] = r
        if sc in done['noise']:
            res['noise'][sc] = done['noise'][sc]
    n = sum(s['cases'] for s in done['sweeps'].values())
    progress(f'comparison: {len(scenarios)} scenarios, {len(models)} models, noise off and '
             f'{seeds} seeds: {n} cases in {time.monotonic() - t0:5.1f} s')
    res['summary'] = summarise(res)
    return res


def _plot_comparison(signals, path: Path, scenario, result) -> None:
    """hf, the band of its yardstick runs (half the step, Cd within +-0.1 %) and every model:
    ``signals[model][name]`` as the sweep keeps them."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    hf = signals['hf']
    t = hf['time_s']
    for ax, key, scale, unit in ((axes[0], 'jack_position_m', 1e3, 'mm'),
                                 (axes[1], 'p12_pa', 1e-6, 'MPa')):
        ax.fill_between(t, hf[f'{key}_yardstick_lo'] * scale, hf[f'{key}_yardstick_hi'] * scale,
                        color='0.6', alpha=0.6, lw=2.5,
                        label='hf yardstick (dt/2, Cd within +-0.1 %)')
        ax.plot(t, hf[key] * scale, color='k', lw=1.2, label='hf')
        for name, sig in signals.items():
            if name == 'hf':
                continue
            ax.plot(sig['time_s'], sig[key] * scale, lw=0.9,
                    ls='-' if name in DYNAMIC_MODELS else '--', label=name)
        ax.set_ylabel(f'{key.replace("_m", "").replace("_pa", "")} [{unit}]')
        ax.grid(alpha=0.3)
    axes[0].plot(t, hf['command_m'] * 1e3, color='k', ls=':', lw=0.8, label='command')
    axes[0].legend(fontsize=7, ncol=3)
    axes[1].set_xlabel('time [s]')
    y = result['yardstick']
    fig.suptitle(f'{scenario}, noise off: yardstick jack {100 * y["jack"]:.2f} %, '
                 f'P12 {100 * y["p12"]:.2f} %', fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _comparison_report(c) -> list:
    if not c:
        return []
    models = c['models']
    lines = ['## Surrogates in the loop (physics only)', '',
             'Noise off, controller at 1 kHz, plant step 1 us. Relative Euclidean-norm error of '
             'jack position / P12 against hf. Yardstick: the largest change of hf itself at '
             'half the step or with the discharge coefficient within +-0.1 % - a difference '
             'inside it is not a model error. A model meets a case when jack <= max(1 %, 2 x '
             'yardstick) and P12 <= max(5 %, 2 x yardstick) (marked `ok`). Dynamic surrogates '
             '(metering edges learned, chambers and jack physical): '
             + ', '.join(m for m in models if m in DYNAMIC_MODELS)
             + '; the reference\'s algebraic P12(XS, Q) surrogates, kept as its reproduction: '
             + ', '.join(m for m in models if m not in DYNAMIC_MODELS) + '.', '',
             '| scenario | yardstick jack / P12 | ' + ' | '.join(models) + ' |',
             '| --- | ---: |' + ' ---: |' * len(models)]
    for sc, r in c['noise_free'].items():
        y = r['yardstick']
        cells = ['failed' if 'error' in e or not e else
                 f'{_pct(e["jack"])} / {_pct(e["p12"])}' + (' ok' if e['meets'] else '')
                 for e in (r['models'].get(m, {}) for m in models)]
        lines.append(f'| {sc} | {_pct(y["jack"])} / {_pct(y["p12"])} | ' + ' | '.join(cells)
                     + ' |')
    if c['noise']:
        lines += ['', f'With torque-motor noise: each model with seed k against hf with seed k, '
                  f'mean over {c["seeds"]} seeds, beside hf\'s own seed-to-seed spread (hf seed '
                  f'k against seed k+1); `ok`: within 1.5 x the spread (jack and P12). For '
                  f'reference, hf with the discharge coefficient +0.1 % against hf, same seeds. '
                  f'Each cell is the mean ± its standard error: on small-signal holds a late '
                  f'stick-slip step happens in one run and not in another, so the errors are '
                  f'heavy-tailed and a verdict on few seeds is uncertain (`bench/inloop.py` runs '
                  f'20). `n/a`: not run with seeds here (its cost).', '',
                  '| scenario | hf seed-to-seed jack / P12 | hf, Cd +0.1 %, same seed | '
                  + ' | '.join(models) + ' |',
                  '| --- | ---: | ---: |' + ' ---: |' * len(models)]
        for sc, r in c['noise'].items():
            h = r['hf_seed_to_seed']
            hc = r['hf_cd_plus_0.1%_same_seed']
            cells = [f'{_pct_sem(hc, "jack")} / {_pct_sem(hc, "p12")}']
            for m in models:
                e = r['models'].get(m)
                cells.append('n/a' if e is None else 'failed' if 'error' in e else
                             f'{_pct_sem(e, "jack")} / {_pct_sem(e, "p12")}'
                             + (' ok' if e['meets'] else ''))
            lines.append(f'| {sc} | {_pct_sem(h, "jack")} / {_pct_sem(h, "p12")} | '
                         + ' | '.join(cells) + ' |')
    lines += ['', 'Per model: noise-free cases meeting the bounds; cases whose features (RMS '
              'tracking error, final position, number and mean size of stick-slip steps, P12 '
              'RMS and peak) all lie within the yardstick\'s spread (the largest deviation of '
              'its three runs, so a model as close as they are lands outside it about half the '
              'time) and within twice it; noise scenarios within 1.5 x the seed spread; median '
              'cost per simulated second against hf.', '',
              '| model | bounds met | features within spread / 2x spread | noise met | '
              'cost vs hf |',
              '| --- | ---: | ---: | ---: | ---: |']
    for m, r in c['summary'].items():
        noise = (f'{r["noise_scenarios_meeting"]}/{r["noise_scenarios"]}'
                 if 'noise_scenarios' in r else 'n/a')
        cost = 'n/a' if r['median_cost_vs_hf'] is None else f'{r["median_cost_vs_hf"]:.2f}'
        lines.append(f'| {m} | {r["cases_meeting_bounds"]}/{r["cases"]} | '
                     f'{r["cases_all_features_within_spread"]} / '
                     f'{r["cases_all_features_within_2x_spread"]} of {r["cases"]} | {noise} | '
                     f'{cost} |')
    lines += ['', 'Plots: `comparison/<scenario>.png` (hf, the band of its yardstick runs in '
              'grey, every model). Every case: `comparison/sweeps/` (Parquet, one row per '
              'case; `eha-sweep report comparison/sweeps/noise_free`).', '']
    return lines


def _report(s) -> str:
    surrogates = [m for m in s['models'] if m != 'hf']
    lines = ['# EHA test campaign', '']
    lines += _comparison_report(s.get('comparison'))
    lines += ['## Through the ROS 2 graph', '',
              f'Scenarios of the reference (section 6.3) through the ROS 2 graph in lockstep, '
              f'1 kHz, plant step 1 us, torque-motor noise on (seed 0); {len(s["runs"])} runs '
              f'in {s["wall_s"]} s.', '',
              'Relative Euclidean-norm error against the high-fidelity run, '
              '`||x - x_hf|| / ||x_hf||` (with noise on; compare with hf\'s seed-to-seed '
              'spread above):', '',
              '| scenario | ' + ' | '.join(f'{m}: jack | {m}: P12 | {m}: spool'
                                           for m in surrogates) + ' |',
              '| --- |' + ' ---: |' * (3 * len(surrogates))]
    for sc, errs in s['relative_error_vs_hf'].items():
        cells = [_pct(errs.get(m, {}).get(k)) for m in surrogates
                 for k in ('jack_position_m', 'p12_pa', 'spool_position_m')]
        lines.append(f'| {sc} | ' + ' | '.join(cells) + ' |')
    lines += ['', 'Health monitor, live in every run (the last `/eha/health` of each recording; '
              '`live = offline`: the replay of its `/eha/state` through `eha-diagnose` gives the '
              'same messages bit for bit):', '',
              '| run | messages | level | live = offline | verdict |', '| --- | ---: | --- | --- '
              '| --- |']
    lines += [f'| {key} | {h["live_messages"]} | {h["level"]} | '
              f'{ {True: "yes", False: "NO", None: "n/a"}[h["live_agrees"]]} | {h["message"]} |'
              for key, h in s.get('health_live', {}).items()]
    lines += ['', 'Offline diagnosis of the hf recordings (`eha-diagnose`, nominal valve: '
              'clearance 2.5 um, overlap 1 um):', '',
              '| scenario | clearance [um] | overlap [um] | residual [MPa] | level |',
              '| --- | ---: | ---: | ---: | --- |']
    lines += [f'| {sc} | {d["radial_clearance_m"] * 1e6:.2f} ± '
              f'{d["radial_clearance_std_m"] * 1e6:.2f} | {d["overlap_m"] * 1e6:.2f} ± '
              f'{d["overlap_std_m"] * 1e6:.2f} | {d["pressure_residual_pa"] / 1e6:.3f} | '
              f'{d["level"]} |' for sc, d in s['diagnosis_hf'].items()]
    if s.get('valve_test'):
        lines += ['', 'Maintenance test (the plant runs the reference\'s map sweep, jack '
                  'clamped, then the pre-flight check, jack free; `eha-diagnose` reads every '
                  'estimate from the recording: clearance and overlap by the diagnostic '
                  'network, the rest by the pre-flight network). True / estimated +- 1 sigma '
                  '[level]:', '']
        valves = list(s['valve_test'])
        lines += ['| parameter | ' + ' | '.join(valves) + ' |',
                  '| --- |' + ' --- |' * len(valves)]
        for n in next(iter(s['valve_test'].values()))['true']:
            cells = [f'{d["true"][n]:.4g} / '
                     + (f'{e["value"]:.4g} +- {e["std"]:.2g} [{e["level"]}]'
                        if (e := d['estimates'].get(n)) else 'n/a')
                     for d in s['valve_test'].values()]
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        lines.append('| verdict | ' + ' | '.join(
            f'[{s["valve_test"][v]["level"]}] {s["valve_test"][v]["message"]}'
            for v in valves) + ' |')
    lines += ['', 'Plots: one folder per scenario (`jack_position.png`, `p12.png`, '
              '`spool_position.png`), every model overlaid.', '',
              'Runs (simulated / wall seconds):', '']
    lines += [f'- `{r["file"]}`: {r["sim_s"]:.2f} s / {r["wall_s"]:.1f} s, {r["ticks"]} ticks'
              for r in s['runs'].values()]
    return '\n'.join(lines) + '\n'


def _pct(x):
    return 'n/a' if x is None else f'{100 * x:.2f} %'


def _pct_sem(e, q):
    """``mean +- standard error`` of quantity ``q`` over the seeds."""
    sem = e.get(f'{q}_sem')
    return _pct(e[q]) if sem is None else f'{100 * e[q]:.2f} ± {100 * sem:.2f} %'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='eha-campaign', description=__doc__.splitlines()[0])
    stamp = datetime.datetime.now().strftime('%Y%m%d-%H%M%S')
    ap.add_argument('--out', type=Path, default=Path('runs') / f'campaign-{stamp}')
    ap.add_argument('--scenarios', default=','.join(REFERENCE_SCENARIOS))
    ap.add_argument('--models', default=','.join(GRAPH_MODELS),
                    help='models run through the graph')
    ap.add_argument('--compare-models', default=','.join(COMPARE_MODELS),
                    help='surrogates of the physics-only comparison (empty: none)')
    ap.add_argument('--seed-models', default=','.join(SEED_MODELS),
                    help='compared surrogates also run with noise over the seeds')
    ap.add_argument('--seeds', type=int, default=10,
                    help='noise seeds of the physics-only comparison (0: noise off only)')
    ap.add_argument('--valve-tests', default=','.join(VALVES),
                    help='valves given the diagnostic valve test (empty: none)')
    ap.add_argument('--processes', action='store_true',
                    help='each node its own process (default: one process, one executor)')
    args = ap.parse_args(argv)

    def fail(message: str) -> int:
        print(f'eha-campaign: error: {message}', file=sys.stderr)
        return 2
    if args.out.exists():
        return fail(f'{args.out} exists: refusing to overwrite it')
    compare = [m for m in args.compare_models.split(',') if m]
    unknown = [m for m in args.models.split(',') + compare if m not in MODELS]
    if unknown:
        return fail(f'unknown model {unknown[0]!r} (one of {", ".join(MODELS)})')
    if args.seeds < 0:
        return fail(f'--seeds {args.seeds} must not be negative')
    try:
        s = run_campaign(args.out, args.scenarios.split(','), args.models.split(','),
                         args.processes, progress=lambda line: print(line, flush=True),
                         valve_tests=[v for v in args.valve_tests.split(',') if v],
                         compare_models=compare, seeds=args.seeds,
                         seed_models=[m for m in args.seed_models.split(',') if m])
    except (ParameterError, GraphError) as exc:
        return fail(str(exc))
    print(f'\n{args.out / "report.md"}:\n')
    print((args.out / 'report.md').read_text())
    print(f'campaign done in {s["wall_s"]} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
