"""The rig under faults mid-run: the watchdogs' core (property tests), and the graph when a node
dies or hangs after the start - which node, when and how, the safe action on the simulation
clock, the flags in the states, the recording complete up to the fault, the exit status - and
a lockstep run with a dropped controller, bit for bit the same every time.

Every test that starts nodes runs in its own ROS domain with a temporary log folder.  Faults
are injected at a count of states the harness has received (not at a wall time), and no test
passes or fails on wall-clock timing."""

import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

from eha_ros import graph
from eha_ros.harness import GraphConfig, GraphDataLoss, GraphFault, GraphRun
from eha_ros.physics import default_params, ParameterError
from eha_ros.testing import SignalAfter
from eha_ros.watchdog import SAFE_ACTIONS, SAFE_CODES, TickWatchdog, timeout_ticks, Transition

BIN = Path(sys.executable).parent
TIMEOUT_S = 180
NULL = SAFE_CODES['null_current']


# --- the core ----------------------------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(fresh=st.lists(st.booleans(), max_size=200), timeout=st.integers(1, 12),
       action=st.sampled_from(SAFE_ACTIONS))
def test_the_watchdog_counts_ticks_since_the_last_input_and_trips_at_its_timeout(
        fresh, timeout, action):
    """For any sequence of ticks with and without input: the age is the ticks since the last
    fresh one (or the start), the action is in force exactly while the age has reached the
    timeout since, once armed by a first input, and each trip and resumption is reported
    once, at its tick."""
    wd = TickWatchdog(timeout * 1e-3, 1_000_000, action)
    assert wd.timeout_ticks == timeout
    age, tripped, stale, armed = 0, False, 0, False
    for k, f in enumerate(fresh):
        tr = wd.step(f)
        if f:
            expect = ('resumed', k, age) if tripped else None
            age, tripped, armed = 0, False, True
        else:
            age += 1
            stale += 1
            expect = ('tripped', k, age) if armed and age == timeout else None
            tripped = tripped or (armed and age >= timeout)
        assert (None if tr is None else (tr.kind, tr.tick, tr.age)) == expect
        assert wd.age == age
        assert wd.in_force == (action if tripped else None)
        assert wd.code == (SAFE_CODES[action] if tripped else 0)
    assert wd.stale_ticks == stale


@settings(max_examples=200, deadline=None)
@given(ticks=st.lists(st.tuples(st.booleans(), st.floats(0.0, 0.1)), max_size=100))
def test_in_realtime_the_timeout_counts_the_wall_time_a_state_waited(ticks):
    """With ``overdue_s`` (realtime), the ages still count ticks, but it trips when the wall
    time the oldest unanswered output waited reaches the timeout, not on a count of ticks."""
    wd = TickWatchdog(0.02, 1_000_000)
    armed = tripped = False
    for k, (fresh, overdue) in enumerate(ticks):
        tr = wd.step(fresh, overdue)
        if fresh:
            assert tr == (Transition('resumed', k, tr.age) if tripped else None)
            armed, tripped = True, False
        elif armed and not tripped and overdue >= 0.02:
            assert tr is not None and tr.kind == 'tripped' and tr.tick == k
            tripped = True
        else:
            assert tr is None
        assert wd.in_force == ('null_current' if tripped else None)


@given(st.one_of(st.floats(max_value=0.0), st.just(float('nan')), st.just(float('inf')),
                 st.booleans(), st.text(max_size=3)))
def test_a_non_physical_timeout_is_refused_naming_it(bad):
    with pytest.raises(ParameterError, match='watchdog timeout'):
        timeout_ticks(bad, 1_000_000)


@given(st.floats(1e-9, 10.0), st.integers(1, 10 ** 8))
def test_the_timeout_rounds_up_to_whole_ticks(timeout_s, period_ns):
    n = timeout_ticks(timeout_s, period_ns)
    assert n >= 1 and n * period_ns >= round(timeout_s * 1e9)
    assert n == 1 or (n - 1) * period_ns < round(timeout_s * 1e9)


def test_an_unknown_action_is_refused_naming_the_choices():
    with pytest.raises(ParameterError, match="'brake' must be one of hold, null_current, stop"):
        TickWatchdog(0.02, 1_000_000, 'brake')


# --- the graph: a node dies or hangs mid-run ---------------------------------------------------

def _fault_run(ros_env, victim, *, after=300, sig=signal.SIGKILL, cont_after_s=None,
               expect=GraphFault, **fields):
    """Run the processes layout and send ``sig`` to ``victim`` once the harness has received
    ``after`` states (SIGCONT ``cont_after_s`` later); returns (result, exception, pids)."""
    fields.setdefault('duration_s', 3.0)
    fields.setdefault('mode', 'realtime')
    with GraphRun(GraphConfig(**fields), env=ros_env, log_dir=ros_env['ROS_LOG_DIR'],
                  timeout_s=TIMEOUT_S) as run:
        run.stop = SignalAfter(run, victim, sig, after, cont_after_s)
        pids = dict(run.pids)
        if expect is None:
            return run.wait(), None, pids
        with pytest.raises(expect) as info:
            run.wait()
    return info.value.result, info.value, pids


def _assert_stale_ticks_are_flagged(result):
    """Every state after the last fresh command counts its age up by one per tick."""
    age = result.state['command_age_ticks']
    tick = result.state['stamp_ns'] // 1_000_000
    last_fresh = int(np.flatnonzero(age == 0)[-1])
    assert np.array_equal(age[last_fresh:], tick[last_fresh:] - tick[last_fresh])


@pytest.mark.parametrize('action', ['null_current', 'hold'])
def test_a_dead_controller_trips_the_plants_command_watchdog(ros_env, tmp_path, action):
    """SIGKILL of the controller mid-run (realtime, processes): the harness names it and how
    it ended, and stops the rest cleanly; the plant ran every tick after its last command
    flagged stale, applied its safe action after command_timeout_s without one, said so
    on /diagnostics and /eha/events, and the recording holds everything up to the fault."""
    record = tmp_path / 'run.mcap'
    result, exc, _ = _fault_run(ros_env, 'controller', record=str(record),
                                scenario='sine_0p1_5pi',
                                plant={'command_timeout_action': action})
    assert result.fault['node'] == 'controller' and result.fault['how'] == 'killed by SIGKILL'
    assert 'controller' in str(exc) and 'SIGKILL' in str(exc) and not result.complete
    assert result.fault['sim_s'] > 0.2
    st = result.state
    _assert_stale_ticks_are_flagged(result)
    safe = st['safe_action'] != 0
    assert safe.any(), 'the harness stopped the plant before its watchdog acted'
    assert safe[-1] and set(st['safe_action'][safe]) == {SAFE_CODES[action]}
    # the last trip: (a command still in flight when the controller died may resume it once)
    first = int(np.flatnonzero(~safe)[-1]) + 1
    # realtime: 20 ms after the first state left unanswered (fewer ticks when the plant itself
    # ran late meanwhile)
    assert st['command_age_ticks'][first] >= 1
    trips = [e for e in result.events if e['source'] == 'watchdog']
    # stamped, as every event, with the start of the first tick's steps that it changed
    begun = int(st['stamp_ns'][first]) - 1_000_000
    assert trips[-1] == {'stamp_ns': begun, 'tick_index': begun // 1_000_000,
                         'node': 'servovalve_plant', 'source': 'watchdog',
                         'scheduled_time_s': trips[-1]['scheduled_time_s'],
                         'changes': {'safe_action': float(SAFE_CODES[action]),
                                     'command_age_ticks': float(st['command_age_ticks'][first])}}
    assert [e['changes']['safe_action'] for e in trips][-1] == SAFE_CODES[action]
    diag = result.diagnostics['servovalve_plant: command watchdog']
    assert diag['level'] == 2
    assert f'{action} since tick {trips[-1]["tick_index"]}' in diag['message']
    assert safe[first + 10:].size >= 50
    if action == 'null_current':  # the spool returns to null (a few ms): the jack stops
        # against its speed while no safe action was in force (on a loaded machine the ticks
        # just before the last trip can hold earlier trips, the jack already stopped; and a
        # controller answering a tick late leaves commands one tick old, not stale)
        controlled = ~safe[:first]
        moving = np.mean(np.abs(st['jack_velocity_m_s'][:first][controlled]))
        assert controlled.sum() >= 100 and moving > 0
        assert np.median(np.abs(st['jack_velocity_m_s'][first + 20:])) < 0.2 * moving
    else:  # the coil stays where the command in force put it: the tick that took it, the
        # stale ticks before the trip and every tick after it ran on that one command, so the
        # coil current (its hysteresis play state unchanged, plus the torque motor's noise) is
        # the same level.  (Under load the last command can answer a state over the timeout
        # old, and the trip then follows it within a tick or two: few ticks before it.)
        noise = default_params().noise_std_a
        last_fresh = int(np.flatnonzero(st['command_age_ticks'] == 0)[-1])
        before, held = st['coil_current_a'][last_fresh:first], st['coil_current_a'][first:]
        assert before.size >= 1 and held.size >= 50
        # 6 sigma of the two means' difference, and never below 2.5 noise (a coil settling
        # on the command's last small change)
        bound = max(2.5, 6.0 * math.sqrt(1.0 / before.size + 1.0 / held.size)) * noise
        assert abs(np.mean(held) - np.mean(before)) < bound, (before.size, held.size)
        assert np.std(held) < 1.5 * noise
    from eha_ros.recording.reader import scan
    info = scan(str(record), strict=True)
    assert info.complete and info.message_counts[graph.TOPIC_STATE] >= st['tick'].size


@pytest.mark.parametrize('victim', ['servovalve_plant', 'command_generator', 'health_monitor'])
def test_any_node_killed_mid_run_is_named_with_how_and_when(ros_env, victim):
    """SIGKILL of the plant, the command generator or the health monitor mid-run: GraphFault
    names the node, the signal, the wall time since the start and the last simulated time;
    the partial result is flagged incomplete."""
    result, exc, _ = _fault_run(ros_env, victim, health=True)
    assert result.fault['node'] == victim and result.fault['how'] == 'killed by SIGKILL'
    assert 0 < result.fault['wall_s'] < 60 and result.fault['sim_s'] >= 0.299
    assert not result.complete and victim in result.loss_report()
    assert result.state['tick'].size >= 300


def test_a_plant_that_hangs_is_called_hung_within_a_second(ros_env):
    """SIGSTOP of the plant (never continued): no state for 1 s is a hung plant; the harness
    names it, kills it (a stopped process cannot stop itself) and stops the rest."""
    t0 = time.monotonic()
    result, exc, _ = _fault_run(ros_env, 'servovalve_plant', sig=signal.SIGSTOP)
    assert result.fault['node'] == 'servovalve_plant'
    assert result.fault['how'] == 'no state for 1 s (hung)'
    assert time.monotonic() - t0 < TIMEOUT_S


def test_a_plant_stopped_for_half_a_second_is_survived_and_said(ros_env):
    """SIGSTOP of the plant for 0.5 s, then SIGCONT: the controller's state watchdog (0.25 s)
    stops commanding with one flagged null current and resumes with the states; the plant
    catches up (50 ticks at once, with no command between them: flagged stale), its own stall
    is not a controller's silence (a trip, where one comes, alternates with resumptions); the
    run ends without a fault."""
    result, _, _ = _fault_run(ros_env, 'servovalve_plant', sig=signal.SIGSTOP,
                              cont_after_s=0.5, expect=None, duration_s=2.0)
    assert result.fault is None and result.sim_s >= 2.0 - 1e-9
    assert result.servovalve['state_timeout'].sum() == 1
    assert result.state['command_age_ticks'].max() >= 40   # the catch-up burst, flagged
    kinds = [e['changes']['safe_action'] for e in result.events if e['source'] == 'watchdog']
    # trips and resumptions alternate (on a loaded machine a live controller can answer late
    # by more than the timeout again, so the run may end tripped)
    assert kinds == [float(NULL) if k % 2 == 0 else 0.0 for k in range(len(kinds))]
    log = Path(ros_env['ROS_LOG_DIR'], 'controller.log').read_text()
    assert 'no plant state for' in log and 'plant states resumed' in log


# --- lockstep: a dropped controller, repeatable ------------------------------------------------

SILENCE = dict(scenario='step_0p1', mode='lockstep', duration_s=0.4,
               events=[(0.2, 'controller', {'silent': 1.0})],
               node_params={'servovalve_plant': {'command_wait_s': 0.5}})


def _silenced(ros_env, **plant):
    cfg = dict(SILENCE, plant=plant)
    with GraphRun(GraphConfig(**cfg), env=ros_env, log_dir=ros_env['ROS_LOG_DIR'],
                  timeout_s=TIMEOUT_S) as run:
        with pytest.raises(GraphDataLoss) as info:
            run.wait()
    return info.value.result


def test_a_lockstep_run_with_a_dropped_controller_is_bit_identical():
    """The controller silenced at tick 200 by an event: the plant waits command_wait_s for the
    command of tick 200, then runs on, every tick flagged with its command's age, null current
    from the 20th (tick 220); three process-mode runs are bit for bit the same, and the run
    says which ticks had no current command."""
    from eha_ros.isolation import ros_environment
    runs = []
    for _ in range(3):
        with ros_environment() as env:
            runs.append(_silenced(env))
    st = runs[0].state
    tick = st['stamp_ns'] // 1_000_000
    assert np.array_equal(tick, np.arange(401))
    assert np.array_equal(st['command_age_ticks'], np.maximum(0, tick - 200))
    assert np.array_equal(st['safe_action'], np.where(tick >= 220, NULL, 0))
    assert runs[0].missing['current command'][0] == 200
    for other in runs[1:]:
        for name in ('jack_position_m', 'spool_position_m', 'coil_current_a', 'p12_pa',
                     'command_age_ticks', 'safe_action'):
            assert np.array_equal(other.state[name], st[name]), name
    events = [(e['tick_index'], e['source']) for e in runs[0].events]
    assert (200, 'schedule') in events and (219, 'watchdog') in events


def test_the_stop_action_ends_the_run_at_the_timeout(ros_env):
    """``command_timeout_action: stop``: the tick at the timeout is the last, with status
    STOPPED; the result says the plant was stopped."""
    result = _silenced(ros_env, command_timeout_action='stop')
    st = result.state
    assert int(st['stamp_ns'][-1] // 1_000_000) == 220 and result.stopped
    assert st['status'][-1] == graph.STATUS_STOPPED and not result.complete
    assert 'stopped by its command watchdog' in result.loss_report()


def test_eha_graph_exits_1_naming_the_dead_node_and_keeps_the_recording(ros_env, tmp_path):
    """``eha-graph`` with the controller SIGKILLed mid-run: exit 1, one error line naming the
    node and the signal, the summary printed, the recording complete."""
    record = tmp_path / 'run.mcap'
    proc = subprocess.Popen([str(BIN / 'eha-graph'), '--processes', '--mode', 'realtime',
                             '--duration', '60', '--record', str(record)], env=ros_env,
                            cwd=tmp_path, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        line = proc.stderr.readline()
        pid = int(line.split('controller (pid ')[1].split(')')[0])
        from eha_ros.recording import RecordingError
        from eha_ros.recording.reader import scan
        deadline = time.monotonic() + TIMEOUT_S
        while True:  # until the recording holds states: the graph runs
            try:
                if scan(str(record)).message_counts.get(graph.TOPIC_STATE, 0) > 0:
                    break
            except (OSError, RecordingError):
                pass
            assert time.monotonic() < deadline
            time.sleep(0.1)
        os.kill(pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 1
    errors = [x for x in (line + err).splitlines() if x.startswith('eha-graph: error')]
    assert len(errors) == 1 and 'controller' in errors[0] and 'SIGKILL' in errors[0], err
    assert 'DATA INCOMPLETE' in out
    assert scan(str(record), strict=True).complete


def test_no_node_outlives_a_harness_killed_by_sigkill(ros_env, tmp_path):
    """``eha-graph`` itself SIGKILLed mid-run (it cannot stop anything): every node process it
    started ends too (they get SIGINT when their parent dies) instead of running on."""
    proc = subprocess.Popen([str(BIN / 'eha-graph'), '--processes', '--mode', 'realtime',
                             '--duration', '60'], env=ros_env, cwd=tmp_path, text=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        line = proc.stderr.readline()
        pids = [int(p.split(')')[0]) for p in line.split('pid ')[1:]]
        assert len(pids) == 3, line
        proc.kill()
        proc.wait(timeout=TIMEOUT_S)

        def alive(pid):
            try:
                return Path(f'/proc/{pid}/stat').read_text().split()[2] != 'Z'
            except OSError:
                return False
        deadline = time.monotonic() + TIMEOUT_S
        while any(alive(p) for p in pids):
            assert time.monotonic() < deadline, [p for p in pids if alive(p)]
            time.sleep(0.1)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.fixture(scope='module')
def collector():
    """The harness's collector node in a context of its own (no graph: its callbacks are fed
    by the test)."""
    import rclpy
    from eha_ros.harness import Collector
    from eha_ros.isolation import ros_environment
    with ros_environment() as env:
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=int(env['ROS_DOMAIN_ID']))
        c = Collector(ctx)
        try:
            yield c
        finally:
            c.destroy()
            rclpy.shutdown(context=ctx)


@settings(max_examples=150, deadline=None)
@given(codes=st.lists(st.sampled_from([0, 0, 0, NULL, SAFE_CODES['hold']]), min_size=1,
                      max_size=60),
       arrived=st.floats(0.0, 1.0), event_t=st.lists(st.integers(0, 80), max_size=4),
       status=st.sampled_from(['none', 'behind', 'current', 'ahead']))
def test_the_collector_waits_for_the_events_its_states_say_were_published(
        collector, codes, arrived, event_t, status):
    """For any run of states (the watchdog's flag changing at random) and scheduled plant
    events: the events in flight are the flag's changes and the events due before the last
    state, less those that arrived, so the harness waits for an event whose sample the
    middleware still has to repeat instead of stopping without it; and, once the flag has
    been raised, for the command watchdog's status that shows its last trip or resumption
    (one the plant published ahead of a lost state counts as arrived)."""
    from eha_ros.msg import ActuatorState, GraphEvent
    from eha_ros.nodes.common import ns_to_stamp
    on_state = next(cb for _, cls, _, cb in collector._subs if cls is ActuatorState)
    for col in collector.state_cols.values():
        del col[:]
    collector.events.clear()
    collector._watchdog_changes = collector._watchdog_trips = 0
    collector.diagnostics.clear()
    times = sorted({t * 1e-3 for t in event_t})
    config = GraphConfig(events=[(t, 'servovalve_plant', {'clearance_m': 1e-6})
                                 for t in times])
    changes, prev = [], 0
    for k, code in enumerate(codes):
        msg = ActuatorState(tick=k, safe_action=code)
        ns_to_stamp(msg.header.stamp, (k + 1) * 1_000_000)
        on_state(msg, 0.0)
        if code != prev:
            changes.append((k * 1_000_000, 'watchdog'))
        prev = code
    due = [(round(t * 1e9), 'schedule') for t in times
           if round(t * 1e9) + 1_000_000 <= len(codes) * 1_000_000]
    sent = changes + due
    n_arrived = int(arrived * len(sent))
    for stamp_ns, source in sent[:n_arrived]:
        ev = GraphEvent(node='servovalve_plant', source=source)
        ns_to_stamp(ev.header.stamp, stamp_ns)
        collector._on_event(ev)
    trips = sum(1 for a, b in zip([0] + codes, codes) if b and not a)
    if status != 'none':
        shown = {'behind': (trips - 1, bool(codes[-1])) if trips > 1 else (trips, not codes[-1]),
                 'current': (trips, bool(codes[-1])), 'ahead': (trips + 1, False)}[status]
        collector.diagnostics['servovalve_plant: command watchdog'] = {'level': 0, 'values': {
            'Trips since startup': str(shown[0]),
            'Action in force': 'hold' if shown[1] else 'none'}}
    behind = trips > 0 and status in ('none', 'behind')
    assert collector.events_in_flight(config) == len(sent) - n_arrived + behind
