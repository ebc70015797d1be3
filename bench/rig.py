"""The rig's promises, measured over many runs: nothing lost at start-up, faults on the
simulation clock repeatable bit for bit, and an idle realtime run with every tick on the clock.

Prints one JSON object:

* ``lossless``: ``--runs`` consecutive lockstep runs through ``run_graph``, each node its own
  process (``sine_0p01_10pi``, 0.3 s): per run the messages per topic, the losses from the
  publishers' sequence numbers, the messages missed at the start and the ticks without a state,
  a position command or a current command; the totals, and how many runs were complete;
* ``events``: ``--event-runs`` process-mode lockstep runs with a wear fault on the plant and a
  gain change on the controller (between ticks and on a tick): whether every run's states and
  current commands are bit-identical to the first's and to ``simulate(..., events=...)``, and
  the ticks at which the events took effect;
* ``idle_realtime``: one ``eha-graph --mode realtime`` run of ``--realtime-s`` (processes), its
  states against its ticks and each ticking node's slipped ticks, from the synchronised start.

Each section records the load averages before and after (``os.getloadavg``).

    python bench/rig.py [--runs 50] [--event-runs 10] [--realtime-s 10] [--smoke]

``--smoke``: one lockstep run, one event run and 0.5 s of realtime: a check, no figure.
"""

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile

import numpy as np

from eha_ros.harness import GraphConfig, GraphDataLoss, run_graph
from eha_ros.isolation import ros_environment
from eha_ros.physics import default_params, simulate

EVENTS = [(0.1004, 'servovalve_plant', {'overlap_supply_m': 2.7e-6, 'radial_clearance_m': 3.5e-6}),
          (0.15, 'controller', {'kp_a_m': 12.0})]


def _load():
    return [round(x, 2) for x in os.getloadavg()]


def lossless(runs: int) -> dict:
    before, rows = _load(), []
    for k in range(runs):
        with ros_environment() as env:
            try:
                r = run_graph(GraphConfig(scenario='sine_0p01_10pi', duration_s=0.3),
                              processes=True, env=env, timeout_s=60)
            except GraphDataLoss as exc:
                r = exc.result
        rows.append({'run': k, 'complete': r.complete, 'messages': r.messages,
                     'lost': sum(r.lost.values()),
                     'missed_at_start': sum(r.missed_at_start.values()),
                     'ticks_missing': {w: len(t) for w, t in r.missing.items()},
                     'discovery_s': round(r.discovery_s, 2)})
    return {'runs': runs, 'complete_runs': sum(row['complete'] for row in rows),
            'lost_total': sum(row['lost'] for row in rows),
            'missed_at_start_total': sum(row['missed_at_start'] for row in rows),
            'ticks_missing_total': sum(sum(row['ticks_missing'].values()) for row in rows),
            'states_per_run': sorted({row['messages']['/eha/state'] for row in rows}),
            'per_run': rows, 'load_average_before': before, 'load_average_after': _load()}


def events(runs: int) -> dict:
    before = _load()
    ref = simulate(default_params(), 'sine_0p01_10pi', duration_s=0.25,
                   controller_period_s=1e-3, record_dt_s=None,
                   events=[(t, c) for t, _, c in EVENTS])
    first, same_as_first, equal_to_physics, ticks = None, 0, 0, []
    for _ in range(runs):
        with ros_environment() as env:
            r = run_graph(GraphConfig(scenario='sine_0p01_10pi', duration_s=0.25,
                                      events=EVENTS), processes=True, env=env, timeout_s=60)
        data = {f: r.state[f] for f in ('jack_position_m', 'p12_pa', 'spool_position_m',
                                        'coil_current_a')}
        data['current_command_a'] = r.servovalve['current_command_a'][:250]
        first = first or data
        same_as_first += all(np.array_equal(first[f], data[f]) for f in data)
        n = r.state['tick'].size
        equal_to_physics += all(np.array_equal(data[f][:n], ref[f][:n]) for f in data
                                if f != 'current_command_a') and np.array_equal(
            data['current_command_a'], ref['current_command_a'][:250])
        ticks.append([(e['node'], e['tick_index']) for e in r.events])
    return {'runs': runs, 'identical_to_first': same_as_first,
            'equal_to_simulate': equal_to_physics,
            'event_ticks': sorted({json.dumps(t) for t in ticks}),
            'physics_event_ticks': [e['tick'] for e in ref.events],
            'load_average_before': before, 'load_average_after': _load()}


def idle_realtime(seconds: float) -> dict:
    before = _load()
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([str(Path(sys.executable).parent / 'eha-graph'), '--isolated',
                              '--mode', 'realtime', '--scenario', 'sine_0p1_5pi', '--duration',
                              str(seconds), '--json'], cwd=tmp, capture_output=True, text=True,
                             timeout=600)
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    timing = summary.get('timing', {})
    return {'exit': out.returncode, 'states': summary['states'],
            'ticks': int(round(seconds * 1000)) + 1, 'ticks_missing': summary['ticks_missing'],
            'data_complete': summary['data_complete'],
            'slipped': {n: float(v.get('Slipped ticks since startup', 0)) for n, v in
                        timing.items()},
            'on_time_pct': {n: float(v.get('On time since startup (%)', 0)) for n, v in
                            timing.items()},
            'discovery_s': summary['discovery_s'],
            'load_average_before': before, 'load_average_after': _load()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--runs', type=int, default=50, help='lockstep runs for the loss count')
    ap.add_argument('--event-runs', type=int, default=10)
    ap.add_argument('--realtime-s', type=float, default=10.0, help='0: no idle realtime run')
    ap.add_argument('--smoke', action='store_true', help='tiny counts: a check, no figure')
    args = ap.parse_args()
    if args.smoke:
        args.runs, args.event_runs, args.realtime_s = 1, 1, 0.5
    out = {'benchmark': 'rig', 'smoke': args.smoke, 'cores': os.cpu_count()}
    if args.runs:
        out['lossless'] = lossless(args.runs)
    if args.event_runs:
        out['events'] = events(args.event_runs)
    if args.realtime_s > 0:
        out['idle_realtime'] = idle_realtime(args.realtime_s)
    print(json.dumps(out))


if __name__ == '__main__':
    main()
