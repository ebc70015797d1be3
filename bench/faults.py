"""The rig under faults mid-run, measured: a dropped controller in lockstep, bit for bit over
many runs, and each node killed or hung in realtime - detected how fast, the safe action, the
flags in the states.

Prints one JSON object:

* ``dropped``: ``--runs`` process-mode lockstep runs of ``step_0p1`` (0.4 s) with the
  controller silenced at 0.2 s (``T:silent=1``) and ``command_wait_s`` 0.5 s: whether every
  run's states are bit-identical to the first's, the tick of the first state without a current
  command, the tick at which the null current was first in force and the wall time per run;
* ``killed``: per node (controller, command generator, plant, health monitor), a realtime
  processes run of ``sine_0p1_5pi`` SIGKILLed once the harness has received 300 states: the
  fault the harness reports, how long after the signal it reported it (wall), and, for the
  controller, the ticks from its last command to the plant's null current, the wall time from
  the signal to the first state on the safe action, and whether every tick after its last
  command was flagged stale;
* ``hung``: the plant SIGSTOPped the same way: the fault and the wall time to it;
* ``paused``: the plant SIGSTOPped for 0.5 s, then SIGCONT: the controller's flagged null
  currents, the plant's trips and resumptions, whether the run ended without a fault.

Every section records the load averages before and after (``os.getloadavg``).

    python bench/faults.py [--runs 10] [--smoke]

``--smoke``: two dropped runs and the controller killed once: a check, no figure.
"""

import argparse
import json
import os
import signal
import sys
import time

import numpy as np

from eha_ros.harness import GraphConfig, GraphDataLoss, GraphRun
from eha_ros.isolation import ros_environment
from eha_ros.testing import SignalAfter

DROPPED = dict(scenario='step_0p1', mode='lockstep', duration_s=0.4,
               events=[(0.2, 'controller', {'silent': 1.0})],
               node_params={'servovalve_plant': {'command_wait_s': 0.5}})
AFTER_STATES = 300


def _load():
    return [round(x, 2) for x in os.getloadavg()]


def dropped(runs: int) -> dict:
    load0 = _load()
    first, out = None, {'runs': runs, 'identical': True, 'wall_s': []}
    for _ in range(runs):
        with ros_environment() as env:
            t0 = time.monotonic()
            with GraphRun(GraphConfig(**DROPPED), env=env, log_dir=env['ROS_LOG_DIR']) as run:
                try:
                    run.wait()
                    raise SystemExit('dropped: the run came back complete without commands')
                except GraphDataLoss as exc:
                    r = exc.result
            out['wall_s'].append(round(time.monotonic() - t0, 2))
        st = r.state
        if r.fault is not None or 'current command' not in r.missing:
            raise SystemExit(f'dropped: the run ended otherwise than by the dropped controller: '
                             f'fault {r.fault}, {st["stamp_ns"].size} states')
        data = np.concatenate([st[k].astype(float) for k in (
            'jack_position_m', 'spool_position_m', 'coil_current_a', 'p12_pa',
            'command_age_ticks', 'safe_action')])
        if first is None:
            first = data
            tick = st['stamp_ns'] // 1_000_000
            out['first_tick_without_current_command'] = int(r.missing['current command'][0])
            out['null_current_from_tick'] = int(tick[np.flatnonzero(st['safe_action'])[0]])
            out['states'] = int(tick.size)
        elif not np.array_equal(first, data):
            out['identical'] = False
    out.update(load_before=load0, load_after=_load())
    return out


def _signal_run(victim, sig, cont_after_s=None, **fields):
    """A realtime processes run; ``sig`` to ``victim`` once ``AFTER_STATES`` states are in."""
    fields = dict(dict(scenario='sine_0p1_5pi', mode='realtime', duration_s=3.0), **fields)
    with ros_environment() as env:
        with GraphRun(GraphConfig(**fields), env=env, log_dir=env['ROS_LOG_DIR']) as run:
            run.stop = inject = SignalAfter(run, victim, sig, AFTER_STATES, cont_after_s)
            try:
                r = run.wait()
            except GraphDataLoss as exc:
                r = exc.result
            reported = time.monotonic()
            start = run.collector.handshake.start_monotonic_ns() * 1e-9
    return r, inject.sent_at, reported, start


def killed(victims) -> dict:
    load0 = _load()
    out = {}
    for victim in victims:
        r, at, reported, start = _signal_run(victim, signal.SIGKILL, health=True)
        row = {'fault': r.fault,
               'reported_after_signal_s': (round(r.fault['wall_s'] - (at - start), 3)
                                           if r.fault else None)}
        if victim == 'controller':
            st = r.state
            age = st['command_age_ticks']
            last = int(np.flatnonzero(age == 0)[-1])
            safe = np.flatnonzero(st['safe_action'][last:])
            row['ticks_last_command_to_safe_action'] = int(safe[0]) if safe.size else None
            row['signal_to_safe_state_s'] = (round(float(st['arrival_s'][last + safe[0]]) - at, 4)
                                             if safe.size else None)
            tick = st['stamp_ns'] // 1_000_000
            row['every_stale_tick_flagged'] = bool(np.array_equal(age[last:],
                                                                  tick[last:] - tick[last]))
            row['safe_action_ticks'] = int(np.count_nonzero(st['safe_action']))
        out[victim] = row
    out.update(load_before=load0, load_after=_load())
    return out


def hung() -> dict:
    load0 = _load()
    r, at, reported, start = _signal_run('servovalve_plant', signal.SIGSTOP)
    return {'fault': r.fault, 'reported_after_signal_s': round(r.fault['wall_s'] - (at - start), 3)
            if r.fault else None, 'load_before': load0, 'load_after': _load()}


def paused() -> dict:
    load0 = _load()
    r, *_ = _signal_run('servovalve_plant', signal.SIGSTOP, cont_after_s=0.5, duration_s=2.0)
    kinds = [e['changes']['safe_action'] for e in r.events if e['source'] == 'watchdog']
    return {'fault': r.fault, 'simulated_s': r.sim_s,
            'controller_state_timeouts': int(r.servovalve['state_timeout'].sum()),
            'plant_trips': sum(1 for k in kinds if k), 'plant_resumptions':
            sum(1 for k in kinds if not k), 'stale_ticks': r.stale_ticks,
            'load_before': load0, 'load_after': _load()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--runs', type=int, default=10)
    ap.add_argument('--smoke', action='store_true')
    args = ap.parse_args(argv)
    if args.smoke:
        out = {'benchmark': 'faults', 'smoke': True, 'dropped': dropped(2),
               'killed': killed(['controller'])}
    else:
        out = {'benchmark': 'faults', 'smoke': False, 'dropped': dropped(args.runs),
               'killed': killed(['controller', 'command_generator', 'servovalve_plant',
                                 'health_monitor']),
               'hung': hung(), 'paused': paused()}
    print(json.dumps(out, default=float))
    ok = out['dropped']['identical'] and all(v['fault'] for k, v in out['killed'].items()
                                             if isinstance(v, dict))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
