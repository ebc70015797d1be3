"""``eha-campaign`` (``make demo``): the reference's EHA test campaign through the ROS graph.

Every scenario of the reference's section 6.3 (steps, ramps and sines of 0.1 and 0.01 mm) is
run with the high-fidelity fluid block and with each shipped surrogate (ga, nn, lut), through
the node graph in lockstep, each run recorded to MCAP by the ``recorder`` node.  Then the
surrogate runs are compared with the hf run of the same scenario (relative Euclidean-norm error
of jack position, P12 and spool position, as ``eha-compare``), the hf recordings are diagnosed
offline (``eha-diagnose``), and a report is written: ``report.md`` with the comparison table and
one folder of PNG plots per scenario (the reference's Figures 6.4-6.16).

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

    eha-campaign [--out runs/campaign-<time>] [--scenarios a,b] [--models hf,ga,nn,lut]
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

from eha_ros.graph import REFERENCE_MODELS, REFERENCE_SCENARIOS
from eha_ros.harness import GraphConfig, GraphError, run_graph
from eha_ros.physics import ParameterError, get_scenario


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
    from eha_ros.surrogates.base import models_dir
    return [m for m in models if m == 'hf' or (models_dir() / f'{m}.npz').is_file()]


def run_campaign(out: Path, scenarios=REFERENCE_SCENARIOS, models=REFERENCE_MODELS,
                 processes=False, progress=print, valve_tests=tuple(VALVES),
                 valve_test_scenario='maintenance_test_quick') -> dict:
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
    # (scenario, label, fluid model, plant parameters): the campaign, then the valve tests
    jobs = ([(sc, model, model, {}) for sc in scenarios for model in models]
            + [(valve_test_scenario, valve, 'hf', VALVES[valve]) for valve in valve_tests])
    runs, t_start = {}, time.monotonic()
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
    from eha_ros.physics import load_params
    nominal = load_params()
    from eha_ros.surrogates.monitor import ITEMS
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
        files = [out / f'{sc}_{m}.mcap' for m in models]
        loaded = [load_run(str(f)) for f in files]
        result = compare_runs(loaded, reference=0)
        plot_runs(loaded, out / sc)
        table[sc] = {r['label']: r['relative_error'] for r in result['runs']}
        diagnoses[sc] = diagnose(str(out / f'{sc}_hf.mcap'), update_s=HEALTH_PERIOD_S)
    summary = {'models': models, 'scenarios': list(scenarios),
               'wall_s': round(time.monotonic() - t_start, 1),
               'runs': {f'{s}/{m}': v for (s, m), v in runs.items()},
               'relative_error_vs_hf': table, 'diagnosis_hf': diagnoses,
               'valve_test': valve_results, 'health_live': health}
    (out / 'summary.json').write_text(json.dumps(summary, indent=1))
    (out / 'report.md').write_text(_report(summary))
    return summary


def _health_verdict(path: Path, diagnose) -> dict:
    """The live monitor's last verdict from a recording, and whether the offline replay of its
    states gives the same messages."""
    try:
        d = diagnose(str(path), update_s=HEALTH_PERIOD_S)
    except ParameterError as exc:
        return {'level': 'n/a', 'message': f'no estimate: {exc}', 'kind': '',
                'live_messages': 0, 'live_agrees': None}
    return {'level': d['level'], 'message': d['message'], 'kind': d['kind'],
            'live_messages': d.get('live_messages', 0), 'live_agrees': d.get('live_agrees')}


def _report(s) -> str:
    surrogates = [m for m in s['models'] if m != 'hf']
    lines = ['# EHA test campaign', '',
             f'Scenarios of the reference (section 6.3) through the ROS 2 graph in lockstep, '
             f'1 kHz, plant step 1 us; {len(s["runs"])} runs in {s["wall_s"]} s.', '',
             'Relative Euclidean-norm error against the high-fidelity run, '
             '`||x - x_hf|| / ||x_hf||`:', '',
             '| scenario | ' + ' | '.join(f'{m}: jack | {m}: P12 | {m}: spool'
                                          for m in surrogates) + ' |',
             '| --- |' + ' ---: |' * (3 * len(surrogates))]
    for sc, errs in s['relative_error_vs_hf'].items():
        cells = []
        for m in surrogates:
            e = errs.get(m, {})
            cells += [_pct(e.get('jack_position_m')), _pct(e.get('p12_pa')),
                      _pct(e.get('spool_position_m'))]
        lines.append(f'| {sc} | ' + ' | '.join(cells) + ' |')
    lines += ['', 'Health monitor, live in every run (the last `/eha/health` of each recording; '
              '`live = offline`: the replay of its `/eha/state` through `eha-diagnose` gives the '
              'same messages bit for bit):', '',
              '| run | messages | level | live = offline | verdict |', '| --- | ---: | --- | --- '
              '| --- |']
    for key, h in s.get('health_live', {}).items():
        lines.append(f'| {key} | {h["live_messages"]} | {h["level"]} | '
                     f'{ {True: "yes", False: "NO", None: "n/a"}[h["live_agrees"]]} | '
                     f'{h["message"]} |')
    lines += ['', 'Offline diagnosis of the hf recordings (`eha-diagnose`, nominal valve: '
              'clearance 2.5 um, overlap 1 um):', '',
              '| scenario | clearance [um] | overlap [um] | residual [MPa] | level |',
              '| --- | ---: | ---: | ---: | --- |']
    for sc, d in s['diagnosis_hf'].items():
        lines.append(f'| {sc} | {d["radial_clearance_m"] * 1e6:.2f} ± '
                     f'{d["radial_clearance_std_m"] * 1e6:.2f} | {d["overlap_m"] * 1e6:.2f} ± '
                     f'{d["overlap_std_m"] * 1e6:.2f} | {d["pressure_residual_pa"] / 1e6:.3f} | '
                     f'{d["level"]} |')
    if s.get('valve_test'):
        lines += ['', 'Maintenance test (the plant runs the reference\'s map sweep, jack '
                  'clamped, then the pre-flight check, jack free; `eha-diagnose` reads every '
                  'estimate from the recording: clearance and overlap by the diagnostic '
                  'network, the rest by the pre-flight network). True / estimated +- 1 sigma '
                  '[level]:', '']
        valves = list(s['valve_test'])
        lines += ['| parameter | ' + ' | '.join(valves) + ' |',
                  '| --- |' + ' --- |' * len(valves)]
        names = list(next(iter(s['valve_test'].values()))['true'])
        for n in names:
            cells = []
            for v in valves:
                d = s['valve_test'][v]
                e = d['estimates'].get(n)
                cells.append(f'{d["true"][n]:.4g} / ' + (
                    f'{e["value"]:.4g} +- {e["std"]:.2g} [{e["level"]}]' if e else 'n/a'))
            lines.append(f'| {n} | ' + ' | '.join(cells) + ' |')
        lines.append('| verdict | ' + ' | '.join(
            f'[{s["valve_test"][v]["level"]}] {s["valve_test"][v]["message"]}'
            for v in valves) + ' |')
    lines += ['', 'Plots: one folder per scenario (`jack_position.png`, `p12.png`, '
              '`spool_position.png`), every model overlaid.', '',
              'Runs (simulated / wall seconds):', '']
    for key, r in s['runs'].items():
        lines.append(f'- `{r["file"]}`: {r["sim_s"]:.2f} s / {r["wall_s"]:.1f} s, '
                     f'{r["ticks"]} ticks')
    return '\n'.join(lines) + '\n'


def _pct(x):
    return 'n/a' if x is None else f'{100 * x:.2f} %'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='eha-campaign', description=__doc__.splitlines()[0])
    stamp = datetime.datetime.now().strftime('%Y%m%d-%H%M%S')
    ap.add_argument('--out', type=Path, default=Path('runs') / f'campaign-{stamp}')
    ap.add_argument('--scenarios', default=','.join(REFERENCE_SCENARIOS))
    ap.add_argument('--models', default=','.join(REFERENCE_MODELS))
    ap.add_argument('--valve-tests', default=','.join(VALVES),
                    help='valves given the diagnostic valve test (empty: none)')
    ap.add_argument('--processes', action='store_true',
                    help='each node its own process (default: one process, one executor)')
    args = ap.parse_args(argv)
    if args.out.exists():
        print(f'eha-campaign: error: {args.out} exists: refusing to overwrite it',
              file=sys.stderr)
        return 2
    unknown = [m for m in args.models.split(',') if m not in REFERENCE_MODELS]
    if unknown:
        print(f'eha-campaign: error: unknown model {unknown[0]!r} '
              f'(one of {", ".join(REFERENCE_MODELS)})', file=sys.stderr)
        return 2
    try:
        s = run_campaign(args.out, args.scenarios.split(','), args.models.split(','),
                         args.processes, progress=lambda line: print(line, flush=True),
                         valve_tests=[v for v in args.valve_tests.split(',') if v])
    except (ParameterError, GraphError) as exc:
        print(f'eha-campaign: error: {exc}', file=sys.stderr)
        return 2
    print(f'\n{args.out / "report.md"}:\n')
    print((args.out / 'report.md').read_text())
    print(f'campaign done in {s["wall_s"]} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
