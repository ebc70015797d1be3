"""The graph as a rig: nothing lost at start-up (the handshake, under late discovery), faults on
the simulation clock (bit for bit against the physics-only loop), unknown parameters refused
whatever path they come by, real-time settings applied or refused with a warning, and the
synchronised start.

Every test that starts nodes runs in its own ROS domain with a temporary log folder. No test
passes or fails on wall-clock timing: waits are for events, with generous timeouts."""

import json
import os
from pathlib import Path
import subprocess
import sys
import time

import numpy as np
from numpy.testing import assert_array_equal
import pytest
import yaml

from eha_ros import graph
from eha_ros.harness import (COLLECTOR, GraphConfig, GraphConfigError, GraphError, GraphRun,
                             run_graph)
from eha_ros.nodes.handshake import evaluate
from eha_ros.physics import default_params, simulate

BIN = Path(sys.executable).parent
TIMEOUT_S = 180
INSTALLED_YAML = Path(sys.prefix) / 'share' / 'eha_ros' / 'config' / 'graph.yaml'
FAULT = (0.1, 'servovalve_plant', {'overlap_supply_m': 2.7e-6})


def _run(args, env, cwd, **kw):
    return subprocess.run([str(BIN / 'eha-graph'), *args], env=env, cwd=cwd, text=True,
                          capture_output=True, timeout=TIMEOUT_S, **kw)


def _error_line(stderr, prog):
    lines = [line for line in stderr.strip().splitlines() if line.startswith(f'{prog}: error')]
    assert len(lines) == 1, stderr
    return lines[0]


def _graph(ros_env, processes=True, **kw):
    options = {k: kw.pop(k) for k in ('delays', 'timeout_s', 'delay_after_start') if k in kw}
    return run_graph(GraphConfig(**kw), processes=processes, env=ros_env,
                     log_dir=ros_env['ROS_LOG_DIR'], **options)


# --- the handshake -----------------------------------------------------------------------------

def test_evaluate_names_the_node_endpoint_and_topic_short_of_its_peers():
    """The start condition: every writer has matched every reader among the nodes, and every
    reader every writer, each counted on its own side."""
    full = {'servovalve_plant': {'pub /eha/state': 2, 'sub /eha/servovalve_command': 1},
            'controller': {'pub /eha/servovalve_command': 2, 'sub /eha/state': 1},
            COLLECTOR: {'sub /eha/state': 1, 'sub /eha/servovalve_command': 1}}
    nodes = list(full)
    assert evaluate(full, nodes) is None
    assert 'recorder has not reported' in evaluate(full, nodes + ['recorder'])
    # the collector's reader has not matched the controller's writer on its own side, though
    # the writer has matched it: the one-sided discovery that loses the first messages
    one_sided = dict(full, **{COLLECTOR: {'sub /eha/state': 1, 'sub /eha/servovalve_command': 0}})
    assert evaluate(one_sided, nodes) == (
        f"{COLLECTOR}'s subscription to /eha/servovalve_command has matched 0 of its 1 "
        'writers (controller)')
    writer_side = dict(full, servovalve_plant={'pub /eha/state': 1,
                                               'sub /eha/servovalve_command': 1})
    assert evaluate(writer_side, nodes) == (
        "servovalve_plant's publisher of /eha/state has matched 1 of its 2 readers "
        f'(controller, {COLLECTOR})')
    # more matches than the nodes need (an eha-echo beside the graph) do not hold it up
    extra = dict(full, controller={'pub /eha/servovalve_command': 5, 'sub /eha/state': 3})
    assert evaluate(extra, nodes) is None


def test_a_recorder_that_lags_at_the_end_still_gets_the_whole_run(ros_env, tmp_path):
    """The recorder frozen (SIGSTOP) for 2 s from the 100th state of a lockstep run that ends
    well within that: the harness waits on the recorder's ``~/status`` until it holds every
    state and command the collector received before it stops the publishers, so the file has
    the whole run (stopping them at once lost the undelivered tail with its writers)."""
    import signal
    import threading

    from eha_ros.recording.reader import scan
    record = tmp_path / 'run.mcap'
    frozen = {}
    with GraphRun(GraphConfig(mode='lockstep', scenario='step_0p1', duration_s=0.5,
                              record=str(record)),
                  env=ros_env, log_dir=ros_env['ROS_LOG_DIR']) as run:
        def freeze():
            c = run.collector
            if not frozen and c is not None and c.n_states >= 100:
                pid = run.pids['recorder']
                os.kill(pid, signal.SIGSTOP)
                frozen['at'] = time.monotonic()
                threading.Timer(2.0, os.kill, (pid, signal.SIGCONT)).start()
            return False
        run.stop = freeze
        r = run.wait()
    assert frozen and time.monotonic() - frozen['at'] >= 2.0
    assert r.complete and r.messages[graph.TOPIC_STATE] == 501, r.loss_report()
    info = scan(record)
    assert info.lost_messages() == {t: 0 for t in info.message_counts}
    for topic in (graph.TOPIC_STATE, graph.TOPIC_COMMAND, graph.TOPIC_SERVOVALVE):
        assert info.message_counts[topic] == r.messages[topic], topic


@pytest.mark.parametrize('late', ['collector', 'recorder'])
def test_nothing_is_lost_when_an_endpoint_is_discovered_seconds_late(ros_env, tmp_path, late):
    """A listener created 3 s after the loop's nodes (the harness's collector, or the recorder
    process): the graph waits for it, and every tick from 0 arrives - states, position commands
    and current commands, with no sequence-number gap or message missed at the start."""
    record = tmp_path / 'run.mcap'
    r = _graph(ros_env, scenario='sine_0p01_10pi', duration_s=0.1, record=str(record),
               delays={COLLECTOR if late == 'collector' else 'recorder': 3.0})
    assert r.complete, r.loss_report()
    assert r.messages[graph.TOPIC_STATE] == r.messages[graph.TOPIC_SERVOVALVE] == 101
    assert r.messages[graph.TOPIC_COMMAND] == 101
    assert_array_equal(r.state['tick'] // 1000, np.arange(101))
    assert r.discovery_s > 3.0  # the start waited for the late node
    from eha_ros.recording.arrays import load_topic_arrays
    from eha_ros.recording.reader import scan
    info = scan(record)
    assert info.lost_messages() == {t: 0 for t in info.message_counts}
    assert info.message_counts[graph.TOPIC_STATE] == 101
    assert info.message_counts[graph.TOPIC_CLOCK] == 101
    assert info.message_counts[graph.TOPIC_SERVOVALVE] == 101
    state = load_topic_arrays(record, graph.TOPIC_STATE)
    assert_array_equal(np.sort(state['stamp_ns']) // 1_000_000, np.arange(101))


def test_a_listener_left_out_of_the_handshake_misses_the_start_and_the_run_says_so(ros_env):
    """The late-discovery test's control: with the plant told to wait only for the loop, and
    the collector created 1 s after the graph started (a 3 s realtime run), the first ticks
    are gone, and the result is not complete and says what was missed at the start."""
    r = _graph(ros_env, mode='realtime', scenario='sine_0p01_10pi', duration_s=3.0,
               delays={COLLECTOR: 1.0}, delay_after_start=True,
               node_params={'servovalve_plant': {'handshake_nodes': ['command_generator',
                                                                     'controller']}})
    assert not r.complete
    assert r.missed_at_start[graph.TOPIC_STATE] > 0 and r.state['tick'][0] > 0
    assert 'missed at the start' in r.loss_report()


def testmissing_ticks_are_named_by_tick():
    """The lockstep check itself: a tick without a current command makes the run incomplete,
    named by tick."""
    from eha_ros.harness import missing_ticks
    cfg = GraphConfig(mode='lockstep')
    ms = 1_000_000
    missing = missing_ticks(cfg, np.arange(5) * ms, np.arange(5) * ms,
                            np.array([0, 1, 3, 4]) * ms)
    assert missing == {'state': [], 'command': [], 'current command': [2]}
    realtime = missing_ticks(GraphConfig(mode='realtime'), np.array([3, 4, 6]) * ms,
                             np.zeros(0), np.zeros(0))
    assert realtime == {'state': [5]}


def test_a_stalled_handshake_fails_in_one_line_naming_what_never_matched(ros_env):
    """A node named in the handshake that never comes: the plant gives up after its timeout
    with one line naming it, and the harness raises that line."""
    start = time.monotonic()
    with pytest.raises(GraphError) as info:
        _graph(ros_env, duration_s=0.05, handshake_timeout_s=3.0, node_params={
            'servovalve_plant': {'handshake_nodes': ['command_generator', 'controller',
                                                     'ghost_recorder']}})
    text = str(info.value)
    assert text.startswith('servovalve_plant: error: start-up handshake incomplete after 3 s')
    assert 'ghost_recorder has not reported' in text and '\n' not in text
    assert time.monotonic() - start < TIMEOUT_S


# --- GraphRun: the harness as a context manager ------------------------------------------------

def test_graph_run_in_steps_gives_run_graphs_result_and_ends_its_context(ros_env):
    """``with GraphRun(...) as run: run.wait()`` is run_graph in steps: the same lockstep data;
    the ROS context runs until the block is left, the environment is restored after it."""
    cfg = dict(scenario='sine_0p01_10pi', duration_s=0.03)
    before = dict(os.environ)
    with GraphRun(GraphConfig(**cfg), processes=False, env=ros_env,
                  log_dir=ros_env['ROS_LOG_DIR']) as run:
        assert os.environ['ROS_DOMAIN_ID'] == ros_env['ROS_DOMAIN_ID']
        stepped = run.wait()
        assert run.context.ok() and run.pids == {}
    assert not run.context.ok() and dict(os.environ) == before
    assert stepped.complete and not stepped.interrupted
    assert_array_equal(stepped.state['tick'] // 1000, np.arange(31))
    whole = _graph(ros_env, processes=False, **cfg)
    for part in ('state', 'command', 'servovalve'):
        mine, theirs = getattr(stepped, part), getattr(whole, part)
        for name in ('stamp_ns', 'jack_position_m', 'position_setpoint_m', 'current_command_a'):
            if name in theirs:
                assert_array_equal(mine[name], theirs[name], err_msg=f'{part}.{name}')


def test_leaving_a_graph_run_by_an_exception_stops_every_node(ros_env, tmp_path):
    """An exception inside the ``with`` block (here before the run even waited) propagates,
    and every node process has ended by the time it does; nothing is left running."""
    before = dict(os.environ)
    with pytest.raises(KeyError, match='leave early'):
        with GraphRun(GraphConfig(duration_s=0.05, record=str(tmp_path / 'run.mcap')),
                      env=ros_env, log_dir=ros_env['ROS_LOG_DIR']) as run:
            assert set(run.pids) == {'command_generator', 'controller', 'servovalve_plant',
                                     'recorder'}
            assert all(proc.poll() is None for proc, _ in run.procs.values())
            raise KeyError('leave early')
    assert all(proc.returncode is not None for proc, _ in run.procs.values())
    assert not run.context.ok() and dict(os.environ) == before


# --- faults on the simulation clock -----------------------------------------------------------

def _reference(duration_s, events, scenario='sine_0p01_10pi'):
    return simulate(default_params(), scenario, duration_s=duration_s,
                    controller_period_s=1e-3, record_dt_s=None, events=events)


@pytest.mark.parametrize('processes', [False, True], ids=['one-process', 'processes'])
def test_lockstep_events_equal_the_physics_loop_bit_for_bit(ros_env, processes):
    """A wear fault on the plant and a gain change on the controller, between ticks and on a
    tick: the graph equals simulate(..., events=...) bit for bit; each event is published on
    /eha/events with the tick at which it took effect."""
    events = [(0.1004, 'servovalve_plant', {'overlap_supply_m': 2.7e-6,
                                            'radial_clearance_m': 3.5e-6}),
              (0.15, 'controller', {'kp_a_m': 12.0})]
    r = _graph(ros_env, processes=processes, scenario='sine_0p01_10pi', duration_s=0.25,
               events=events)
    ref = _reference(0.25, [(t, c) for t, _, c in events])
    n = r.state['tick'].size
    assert n == 251 and r.complete
    for field in ('jack_position_m', 'spool_position_m', 'p12_pa', 'coil_current_a'):
        assert_array_equal(r.state[field], ref[field][:n], err_msg=field)
    assert_array_equal(r.servovalve['current_command_a'][:250], ref['current_command_a'][:250])
    assert [(e['node'], e['tick_index'], e['source'], e['changes']) for e in r.events] == [
        ('servovalve_plant', 101, 'schedule', events[0][2]),
        ('controller', 150, 'schedule', events[1][2])]
    assert [e['tick'] for e in ref.events] == [101, 150]
    assert r.events[0]['stamp_ns'] == 101_000_000 and r.events[0]['scheduled_time_s'] == 0.1004


def test_lockstep_events_repeat_across_process_runs_and_the_scenarios_own(ros_env, tmp_path):
    """Three process-mode runs of a scenario with its own event (config/scenarios.yaml) and one
    more given by eha-graph --event: identical to each other and to the physics loop; the
    recording holds the events."""
    extra = '0.05:controller.kp_a_m=9.5'
    runs = []
    for k in range(3):
        record = tmp_path / f'run{k}.mcap'
        out = _run(['--scenario', 'step_0p1_overlap_fault', '--event', extra, '--record',
                    str(record), '--json'], ros_env, tmp_path)
        assert out.returncode == 0, out.stderr
        summary = json.loads(out.stdout.strip().splitlines()[-1])
        assert summary['data_complete'] and summary['states'] == 301
        assert [(e['node'], e['tick_index']) for e in summary['events']] == [
            ('controller', 50), ('servovalve_plant', 150)]
        from eha_ros.recording.arrays import load_topic_arrays
        from eha_ros.recording.reader import iter_decoded
        runs.append(load_topic_arrays(record, graph.TOPIC_STATE))
        recorded = [m.message for m in iter_decoded(str(record), topics=[graph.TOPIC_EVENTS])]
        assert sorted((m.node, m.tick_index) for m in recorded) == [
            ('controller', 50), ('servovalve_plant', 150)]
    ref = _reference(0.3, [(0.05, {'kp_a_m': 9.5})], scenario='step_0p1_overlap_fault')
    assert [e['tick'] for e in ref.events] == [50, 150]
    for state in runs:
        _, first = np.unique(state['stamp_ns'], return_index=True)
        assert first.size == 301
        assert_array_equal(state['jack_position_m'][first], ref['jack_position_m'][:301])
        assert_array_equal(state['p12_pa'][first], runs[0]['p12_pa'][
            np.unique(runs[0]['stamp_ns'], return_index=True)[1]])


def test_realtime_event_takes_effect_at_its_tick(ros_env):
    """Realtime: the event is applied at the first tick at or after its time too."""
    r = _graph(ros_env, mode='realtime', scenario='sine_0p01_10pi', duration_s=0.4,
               events=[(0.2, 'servovalve_plant', {'radial_clearance_m': 4e-6})])
    # (a loaded machine may also trip the plant's command watchdog: source 'watchdog')
    assert [(e['tick_index'], e['stamp_ns']) for e in r.events
            if e['source'] == 'schedule'] == [(200, 200_000_000)]
    assert r.state['tick'][0] == 0 and not r.missing['state']


def test_a_live_parameter_set_is_published_with_its_tick(ros_env):
    """A parameter set while the plant runs (here before its first tick) is published on the
    latched /eha/events as a live change, so a recorder joining later still has it."""
    import rclpy
    from rclpy.parameter import Parameter

    from eha_ros.msg import GraphEvent
    from eha_ros.nodes.common import make_executor
    from eha_ros.nodes.servovalve_plant import ServovalvePlant
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        plant = ServovalvePlant(context=ctx)
        ok = plant.set_parameters([Parameter('filter_clogging', value=0.2)])[0]
        assert ok.successful
        late = rclpy.create_node('late_reader', context=ctx)
        got = []
        late.create_subscription(GraphEvent, graph.TOPIC_EVENTS, got.append,
                                 graph.topic_qos(graph.TOPIC_EVENTS))
        ex = make_executor(ctx)
        ex.add_node(plant)
        ex.add_node(late)
        end = time.monotonic() + 10
        while not got and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        assert len(got) == 1
        msg = got[0]
        assert (msg.source, msg.node, msg.tick_index) == ('live', 'servovalve_plant', 0)
        assert list(msg.parameter_names) == ['filter_clogging']
        assert list(msg.parameter_values) == [0.2] and np.isnan(msg.scheduled_time_s)
        plant.destroy_node()
        late.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


# --- unknown parameters refused ------------------------------------------------------------------

@pytest.mark.parametrize('field, value, words', [
    ('plant', {'radial_clearnce_m': 4e-6}, ['servovalve_plant', "'radial_clearnce_m'",
                                            'radial_clearance_m']),
    ('node_params', {'controller': {'kp': 3.0}}, ['controller', "'kp'", 'kp_a_m']),
    ('node_params', {'recorder': {'topics': ['/eha/state']}}, ['no node', 'recorder']),
    ('health_params', {'window_s': 1.0}, ['health_params', 'health=True']),
    ('events', [(0.1, 'servovalve_plant', {'radial_clearnce_m': 4e-6})],
     ['radial_clearnce_m', 'radial_clearance_m']),
    ('events', [(0.1, 'servovalve_plant', {'supply_pressure_pa': 2e7})],
     ['supply_pressure_pa', 'fixed for a run', 'parameter file']),
    ('events', [(0.1, 'command_generator', {'amplitude_m': 1e-4})],
     ['command_generator', 'takes no events']),
    ('plant', {'supply_pressure_pa': 1e12}, ['supply_pressure_pa', 'physical parameter',
                                             'servovalve_plant.params_file']),
])
def test_graph_config_refuses_what_no_node_has_before_anything_starts(field, value, words):
    with pytest.raises(GraphConfigError) as info:
        run_graph(GraphConfig(**{field: value}), env={'ROS_DOMAIN_ID': '0'})
    text = str(info.value)
    assert '\n' not in text
    for w in words:
        assert w in text, text


@pytest.mark.parametrize('args, words', [
    (['--set', 'servovalve_plant.radial_clearnce_m=4e-6'],
     ['radial_clearnce_m', 'radial_clearance_m']),
    (['--set', 'servovalve_plant.supply_pressure_pa=1e12'],
     ['supply_pressure_pa', 'physical parameter', 'params_file']),
    (['--event', '0.1:servovalve_plant.radial_clearnce_m=4e-6'],
     ['radial_clearnce_m', 'radial_clearance_m']),
    (['--event', '0.1:servovalve_plant.supply_pressure_pa=2e7'],
     ['supply_pressure_pa', 'fixed for a run']),
    (['--event', '0.1:controller.kp_a_m'], ['--event', 'T:node.parameter=value']),
    (['--event', 'soon:controller.kp_a_m=3'], ['soon']),
    (['--event', '0.1:health_monitor.window_s=2'], ['health_monitor', 'takes no events']),
    (['--set', 'controller.kp_a_m=1', '--params-file', 'PARAMS'], ['kp_am', 'kp_a_m']),
    (['--params-file', 'WILDCARD'], ['no node declares', 'rate_hzz']),
])
def test_eha_graph_refuses_unknown_parameters_in_one_line(ros_env, tmp_path, args, words):
    """A misspelt fault from any path: --set, --event, a params file (node section or /**):
    one line naming it and the nearest declared names, exit 2, nothing started."""
    data = yaml.safe_load(INSTALLED_YAML.read_text())
    data['/controller']['ros__parameters']['kp_am'] = 3.0
    (tmp_path / 'params.yaml').write_text(yaml.safe_dump(data))
    (tmp_path / 'wild.yaml').write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'rate_hzz': 500.0}}}))
    args = [str(tmp_path / 'params.yaml') if a == 'PARAMS' else
            str(tmp_path / 'wild.yaml') if a == 'WILDCARD' else a for a in args]
    out = _run(args + ['--duration', '0.01'], ros_env, tmp_path)
    assert out.returncode == 2, out.stderr
    line = _error_line(out.stderr, 'eha-graph')
    for w in words:
        assert w in line, line
    assert 'running' not in out.stderr  # refused before any node started


@pytest.mark.parametrize('node, args, words', [
    ('servovalve_plant', ['-p', 'radial_clearnce_m:=4e-6'], ['radial_clearance_m']),
    ('servovalve_plant', ['-p', 'supply_pressure_pa:=1e7'], ['physical parameter',
                                                             'params_file']),
    ('controller', ['-p', 'kp:=3.0'], ['kp_a_m']),
    ('command_generator', ['-p', 'amplitude:=1e-4'], ['amplitude_m']),
    ('health_monitor', ['-p', 'window:=1.0'], ['window_s']),
    ('recorder', ['-p', 'output_file:=x.mcap'], ['output']),
    ('servovalve_plant', ['-p', "events:=['0.1:radial_clearnce_m=4e-6']"],
     ['radial_clearnce_m', 'radial_clearance_m']),
    ('controller', ['-p', "events:=['0.1:radial_clearance_m=4e-6']"],
     ['radial_clearance_m', 'may not change']),
])
def test_a_node_started_alone_refuses_undeclared_parameters(ros_env, tmp_path, node, args,
                                                            words):
    """ros2 run / --ros-args -p: ROS would ignore an undeclared parameter; each node refuses it
    with one line and exit 2."""
    out = subprocess.run([str(BIN / node), '--ros-args', *args], env=ros_env, cwd=tmp_path,
                         text=True, capture_output=True, timeout=TIMEOUT_S)
    assert out.returncode == 2, out.stderr
    line = out.stderr.strip().splitlines()[-1]
    assert line.startswith(f'{node}: error:')
    for w in words:
        assert w in line, line
    assert not list(tmp_path.glob('*.mcap'))


# --- real-time settings ------------------------------------------------------------------------

def _may_use_fifo() -> bool:
    probe = subprocess.run([sys.executable, '-c', 'import os; os.sched_setscheduler(0, '
                            'os.SCHED_FIFO, os.sched_param(1))'], capture_output=True)
    return probe.returncode == 0


def _start_until(cmd, env, cwd, words, timeout=TIMEOUT_S, **kw):
    """Start a node process and wait until its output has a line with ``words``."""
    proc = subprocess.Popen(cmd, env=env, cwd=cwd, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, **kw)
    lines, end = [], time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if words in line:
            return proc, lines
    proc.kill()
    proc.wait()
    raise AssertionError(f'no {words!r} in the output of {cmd[0]}: {"".join(lines)}')


def _stop(proc):
    proc.send_signal(2)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def test_thread_priority_and_locked_memory_read_back_from_the_node_process(ros_env, tmp_path):
    """Where this process may use SCHED_FIFO (root here): a lockstep plant (its ticks run in
    the executor, on the middleware's messages) with thread_priority 10 and lock_memory runs
    every thread of its process under SCHED_FIFO 10 with its memory locked, and says nothing
    against it.  (In realtime only its tick loop's thread gets the priority:
    ``test_tickloop.py``.)"""
    if not _may_use_fifo():
        pytest.skip('SCHED_FIFO refused here: the refusal test covers this machine')
    proc, lines = _start_until([str(BIN / 'servovalve_plant'), '--ros-args', '-p',
                                'thread_priority:=10', '-p', 'lock_memory:=true', '-p',
                                'mode:=lockstep'],
                               ros_env, tmp_path, 'waiting for')
    try:
        tids = [int(t) for t in os.listdir(f'/proc/{proc.pid}/task')]
        assert len(tids) > 1
        for tid in tids:
            assert os.sched_getscheduler(tid) == os.SCHED_FIFO, tid
            assert os.sched_getparam(tid).sched_priority == 10
        status = Path(f'/proc/{proc.pid}/status').read_text()
        locked_kb = int(next(line.split()[1] for line in status.splitlines()
                             if line.startswith('VmLck:')))
        assert locked_kb > 0
        assert not any('refused' in line for line in lines)
    finally:
        _stop(proc)


def test_refused_real_time_settings_give_one_warning_and_the_node_runs_on(ros_env, tmp_path):
    """Where the OS refuses them (RLIMIT_RTPRIO 0 and RLIMIT_MEMLOCK 0; as root, which passes
    both limits through CAP_SYS_NICE and CAP_IPC_LOCK, those two dropped before exec): one
    warning per setting saying what to change, and the node runs on under normal scheduling."""
    import ctypes
    import resource

    def drop():
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
        resource.setrlimit(resource.RLIMIT_MEMLOCK, (0, 0))
        if os.geteuid() == 0:
            libc = ctypes.CDLL(None, use_errno=True)
            for cap in (23, 14):  # CAP_SYS_NICE, CAP_IPC_LOCK out of the bounding set
                if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
                    raise OSError(ctypes.get_errno(), 'PR_CAPBSET_DROP')
    proc, lines = _start_until([str(BIN / 'servovalve_plant'), '--ros-args', '-p',
                                'thread_priority:=40', '-p', 'lock_memory:=true', '-p',
                                'mode:=lockstep'],
                               ros_env, tmp_path, 'waiting for', preexec_fn=drop)
    try:
        assert proc.poll() is None
        assert os.sched_getscheduler(proc.pid) == os.SCHED_OTHER
        text = ''.join(lines)
        assert 'thread_priority 40 refused' in text and 'rtprio' in text, text
        assert 'lock_memory refused' in text and 'memlock' in text, text
    finally:
        _stop(proc)


# --- the synchronised start ----------------------------------------------------------------------

def test_timing_reports_cover_the_run_from_the_synchronised_start(ros_env):
    """Every ticking node reports its start-up (JIT warm-up, discovery) beside timing counted
    from the common start: realtime reports its schedule's keys, lockstep the simulated seconds
    per wall second instead; the first state is tick 0 in both modes."""
    rt = _graph(ros_env, mode='realtime', scenario='step_0p1', duration_s=1.5)
    ls = _graph(ros_env, mode='lockstep', scenario='step_0p1', duration_s=1.5)
    for r, mode in ((rt, 'realtime'), (ls, 'lockstep')):
        assert r.state['tick'][0] == 0 and r.complete, (mode, r.loss_report())
        timing = {n: d['values'] for n, d in r.diagnostics.items()
                  if n.endswith(graph.TIMING_SUFFIX)}
        assert set(timing) == {f'{n}{graph.TIMING_SUFFIX}' for n in
                               ('command_generator', 'controller', 'servovalve_plant')}
        for name, values in timing.items():
            assert float(values['Discovery (s)']) >= 0 and float(values['JIT warm-up (s)']) > 0
            # the final report, sent when the node's run ended: a run shorter than the
            # reports' 1 s window is covered too, every tick counted
            assert values[graph.RUN_ENDED] == '1', (mode, name, values)
            # (the lockstep plant publishes tick 0 at the start and counts the ticks it advances)
            lockstep_plant = mode == 'lockstep' and name.startswith('servovalve_plant')
            assert (int(values['Events since startup'])
                    == len(r.state['tick']) - lockstep_plant), (mode, name, values)
            realtime_keys = {'On time since startup (%)', 'Slipped ticks since startup',
                             'Period jitter p99 since startup (ms)'}
            if mode == 'realtime':
                assert realtime_keys <= set(values)
            else:
                assert not realtime_keys & set(values)
                assert float(values['Simulated s per wall s']) > 0
        assert r.discovery_s > 0 and r.wall_s > 0
