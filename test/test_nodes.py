"""The node graph: nodes alone (parameters, bad values), the closed loop in lockstep against
the physics-only simulation, run-time degradation seen by the health monitor, realtime ticks.

Every test that starts nodes runs in its own ROS domain with a temporary log folder
(``ros_env`` / ``eha_graph`` fixtures)."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from numpy.testing import assert_array_equal
import pytest

from eha_ros.physics import default_params, simulate

BIN = Path(sys.executable).parent


def _run_node(name, *ros_args, env, timeout=30):
    return subprocess.run([str(BIN / name), '--ros-args', *ros_args], env=env,
                          capture_output=True, text=True, timeout=timeout, cwd=env['ROS_LOG_DIR'])


@pytest.mark.parametrize('node, arg, words', [
    ('servovalve_plant', 'radial_clearance_m:=0.0', ['radial_clearance_m']),
    ('servovalve_plant', 'model:=warp', ['model', 'warp']),
    ('servovalve_plant', 'dt_s:=0.001', ['dt_s', 'stability limit']),
    ('servovalve_plant', 'integrator:=rk4', ['integrator', 'rk4', 'split']),
    ('servovalve_plant', ('integrator:=split', 'dt_s:=0.001'), ['dt_s', 'stability limit']),
    ('servovalve_plant', 'jack_dynamic_friction_n:=900.0', ['jack_dynamic_friction_n']),
    ('controller', 'kp_a_m:=-1.0', ['kp_a_m']),
    ('controller', 'mode:=sometimes', ['mode']),
    ('command_generator', 'scenario:=no_such', ['scenario', 'no_such']),
    ('health_monitor', 'thresholds_file:=/nonexistent.yaml', ['nonexistent.yaml']),
    ('servovalve_plant', ('valve_test:=true', 'rate_hz:=1250.0'),
     ['valve test', 'whole number of ticks']),
])
def test_bad_parameter_refused_at_start(ros_env, node, arg, words):
    args = [a for one in ((arg,) if isinstance(arg, str) else arg) for a in ('-p', one)]
    out = _run_node(node, *args, env=ros_env)
    assert out.returncode == 2, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith(f'{node}: error:')
    for w in words:
        assert w in last


def test_parameters_declared_with_descriptions_and_ranges(ros_env):
    import rclpy

    from eha_ros.nodes.servovalve_plant import ServovalvePlant
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = ServovalvePlant(context=ctx)
        for name in ('radial_clearance_m', 'overlap_supply_m', 'demagnetisation', 'model',
                     'dt_s', 'rate_hz'):
            d = node.describe_parameter(name)
            assert d.description, name
        d = node.describe_parameter('demagnetisation')
        assert '[1]' in d.description and d.floating_point_range[0].to_value == 1.0
        assert '[m]' in node.describe_parameter('radial_clearance_m').description
        # a run-time change: a non-physical value is refused with the reason, a good one taken
        from rclpy.parameter import Parameter
        bad = node.set_parameters([Parameter('radial_clearance_m', value=-1e-6)])[0]
        assert not bad.successful and 'radial_clearance_m' in bad.reason
        frozen = node.set_parameters([Parameter('model', value='nn')])[0]
        assert not frozen.successful and 'cannot change' in frozen.reason
        ok = node.set_parameters([Parameter('radial_clearance_m', value=4e-6)])[0]
        assert ok.successful and node.plant.params.radial_clearance_m == 4e-6
        # the valve test's default flows are those of the valve_test scenario (config)
        from eha_ros.physics import get_scenario
        assert (list(node.get_parameter('valve_test_flows_m3_s').value)
                == list(get_scenario('valve_test').valve_test_flows_m3_s))
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_plant_status_codes_name_the_physics_conditions():
    from eha_ros.graph import STATUS_NAMES
    from eha_ros.nodes.servovalve_plant import CONDITION_STATUS
    from eha_ros.physics.state import CAVITATION, END_STOP, OK
    assert set(CONDITION_STATUS) == {OK, END_STOP, CAVITATION}
    for condition, code in CONDITION_STATUS.items():
        assert STATUS_NAMES[code] == condition


def _reference(duration_s, seed=0, **changes):
    from eha_ros.physics.params import replace
    p = replace(default_params(), **changes) if changes else default_params()
    return simulate(p, 'step_0p1', duration_s=duration_s, controller_period_s=1e-3,
                    record_dt_s=None, seed=seed)


@pytest.mark.parametrize('processes', [False, True], ids=['one-process', 'processes'])
def test_lockstep_hf_step_equals_physics_simulation(eha_graph, processes):
    """Same scenario, parameters and seed: the graph's states are the physics-only closed
    loop's, bit for bit, tick by tick."""
    r = eha_graph(processes=processes, scenario='step_0p1', duration_s=0.15, seed=3)
    ref = _reference(0.15, seed=3)
    ticks = r.state['tick'] // 1000
    assert_array_equal(ticks, np.arange(ticks.size))  # every tick once, in order
    assert ticks.size == 151
    for field in ('jack_position_m', 'spool_position_m', 'p12_pa', 'coil_current_a'):
        assert_array_equal(r.state[field], ref[field][:ticks.size], err_msg=field)
    assert_array_equal(r.servovalve['current_command_a'][:150], ref['current_command_a'][:150])
    assert 0.9e-4 < r.state['jack_position_m'][-1] < 1.1e-4


def test_two_lockstep_runs_are_identical(eha_graph, monkeypatch):
    """Two runs, on the default (events) executor and on rclpy's single-threaded one, give
    the same data."""
    a = eha_graph(processes=False, scenario='sine_0p1_10pi', duration_s=0.08, seed=1)
    monkeypatch.setenv('EHA_ROS_EXECUTOR', 'single')
    b = eha_graph(processes=False, scenario='sine_0p1_10pi', duration_s=0.08, seed=1)
    assert a.state['tick'].size == 81
    for field in set(a.state) - {'arrival_s'}:  # all but the wall-clock receipt times
        assert_array_equal(a.state[field], b.state[field], err_msg=field)
    monkeypatch.setenv('EHA_ROS_EXECUTOR', 'turbo')
    from eha_ros.nodes.common import make_executor
    from eha_ros.physics import ParameterError
    with pytest.raises(ParameterError, match='EHA_ROS_EXECUTOR'):
        make_executor()


def test_runtime_degradation_is_picked_up_by_health_monitor(eha_graph):
    """Clearance raised from 2.5 um to 4.5 um at t = 1.0 s: before, the monitor finds the
    valve consistent with nominal (OK, the truth within its 2 sigma); once its 0.6 s window
    holds only worn-valve samples it raises WARN with the worn clearance within 2 sigma and
    the nominal one outside."""
    r = eha_graph(processes=False, scenario='sine_0p1_5pi', duration_s=2.1, health=True,
                  health_params={'window_s': 0.6, 'update_period_s': 0.5},
                  events=[(1.0, 'servovalve_plant', {'radial_clearance_m': 4.5e-6})])
    stamps = [h.header.stamp.sec + h.header.stamp.nanosec * 1e-9 for h in r.health]
    before = [h for h, t in zip(r.health, stamps) if t <= 1.0]
    after = [h for h, t in zip(r.health, stamps) if t >= 1.0 + 0.6 + 0.05]
    assert before and after
    for h in before:
        assert abs(h.radial_clearance_m - 2.5e-6) <= 2 * h.radial_clearance_std_m
        assert h.level == h.LEVEL_OK
    for h in after:
        assert abs(h.radial_clearance_m - 4.5e-6) <= 2 * h.radial_clearance_std_m
        assert abs(h.radial_clearance_m - 2.5e-6) > 2 * h.radial_clearance_std_m
        assert h.level == h.LEVEL_WARN
        assert h.method == 'steady-fit' and h.samples_used > 100


def test_realtime_mode_ticks_at_its_rate(eha_graph):
    """Realtime: wall-clock timers.  Each state is a whole tick of the simulation (1000 steps),
    and the plant keeps up with the command stream (the loop closes: the jack moves)."""
    r = eha_graph(processes=True, mode='realtime', scenario='step_1mm', duration_s=1.0,
                  timeout_s=60)
    t = r.state['sim_time_s']
    assert t.size > 100
    ticks = r.state['tick']
    assert np.all(ticks % 1000 == 0) and np.all(np.diff(ticks) > 0)
    # realtime QoS may drop a state for a subscriber that falls behind; nearly all arrive
    assert t.size >= 0.9 * (ticks[-1] - ticks[0]) / 1000
    assert r.state['jack_position_m'].max() > 0.5e-3


def test_realtime_plant_locks_simulated_time_to_the_wall_clock(ros_env):
    """The realtime plant's catch-up and slip, driven by a wall clock the test sets: a late
    wake of its loop publishes every tick that fell due, a stall beyond ``max_catch_up`` ticks
    slips
    (the backlog dropped and counted), and simulated time then follows the wall clock again."""
    import rclpy
    from rclpy.parameter import Parameter

    from eha_ros.msg import ActuatorState
    from eha_ros.nodes.servovalve_plant import ServovalvePlant
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = ServovalvePlant(context=ctx, parameter_overrides=[
            Parameter('mode', value='realtime'), Parameter('max_catch_up', value=20)])
        published = []  # what would go out (the plant fills one message object every tick)
        node.state_pub.publish = lambda m: published.append(
            (type(m), m.tick, m.sim_time_s))
        wall = [10_000_000_000]
        node._now_ns = lambda: wall[0]
        node._anchor(wall[0])  # the graph's start (the handshake's, in a graph)
        node._started = True
        ms = 1_000_000

        def call(dt_ns):
            wall[0] += dt_ns
            n = len(published)
            node._on_loop_wake(wall[0])
            return published[n:]

        assert [m[1] for m in call(0)] == [0]       # tick 0 falls due at the start
        assert len(call(ms)) == 1                   # on time: one tick
        assert len(call(ms // 2)) == 0              # early: nothing due yet
        late = call(7 * ms + ms // 2)               # 8 ms late: 8 ticks caught up
        assert len(late) == 8 and node.slipped_ticks == 0
        assert [m[1] for m in late] == [k * 1000 for k in range(2, 10)]
        assert len(call(100 * ms)) == 20 and node.slipped_ticks == 80   # a 0.1 s stall
        assert len(call(ms)) == 1 and len(call(3 * ms)) == 3           # back on the clock
        assert all(m[0] is ActuatorState for m in published)
        assert published[-1][2] == pytest.approx((len(published) - 1) * 1e-3)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_realtime_command_generator_publishes_every_sample_on_the_tick_grid(ros_env):
    """Realtime command generator, driven by a wall clock the test sets: sample k is the
    scenario's value at k periods, stamped with the start plus k periods;
    a late wake of its loop publishes every sample that fell due, a stall beyond
    ``max_catch_up`` slips (counted)."""
    import rclpy
    from rclpy.parameter import Parameter

    from eha_ros.nodes.command_generator import CommandGenerator
    from eha_ros.physics import get_scenario
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = CommandGenerator(context=ctx, parameter_overrides=[
            Parameter('mode', value='realtime'), Parameter('scenario', value='sine_0p1_10pi'),
            Parameter('max_catch_up', value=20)])
        sent = []
        node.pub.publish = lambda m: sent.append(
            (m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
             m.position_setpoint_m))
        wall, ms, start_ns = [5_000_000_000], 1_000_000, 1_700_000_000_000_000_000
        node._t0_ns = start_ns
        node._anchor(wall[0])

        def call(dt_ns):
            wall[0] += dt_ns
            n = len(sent)
            node._on_loop_wake(wall[0])
            return sent[n:]
        assert len(call(0)) == 1 and len(call(ms // 2)) == 0
        assert len(call(7 * ms + ms // 2)) == 8             # 8 ms late: every sample sent
        assert len(call(100 * ms)) == 20 and node.slipped_ticks == 80
        k = np.array([0, *range(1, 9)])
        sine = get_scenario('sine_0p1_10pi')
        assert [s for s, _ in sent[:9]] == [start_ns + int(i) * ms for i in k]
        assert [v for _, v in sent[:9]] == [sine.value(i * ms * 1e-9) for i in k]
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_a_catch_up_past_the_runs_end_reports_the_runs_samples_only(ros_env):
    """A late wake of the realtime command generator that publishes the run's last sample and
    later ones in one catch-up sends its final timing report right after the last sample: it
    counts the run's samples (as many as the plant's states), not those past the end."""
    import rclpy
    from rclpy.parameter import Parameter

    from eha_ros.graph import RUN_ENDED
    from eha_ros.nodes.command_generator import CommandGenerator
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = CommandGenerator(context=ctx, parameter_overrides=[
            Parameter('mode', value='realtime'), Parameter('scenario', value='step_0p1'),
            Parameter('duration_s', value=0.005), Parameter('max_catch_up', value=20)])
        node.pub.publish = lambda m: None
        reports = []
        node.timing._send = reports.append
        ms, wall = 1_000_000, 5_000_000_000
        node._t0_ns = 1_700_000_000_000_000_000
        node.timing.start(wall)
        node._anchor(wall)
        node._on_loop_wake(wall + 3 * ms)               # samples 0-3
        assert reports == [] and node.published == 4
        node._on_loop_wake(wall + 9 * ms)               # 4-9: the run ends at sample 5 (5 ms)
        assert node.published == 10 and len(reports) == 1
        assert reports[0][RUN_ENDED] == 1 and reports[0]['Events since startup'] == 6
        node._on_loop_wake(wall + 12 * ms)
        assert len(reports) == 1
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize('trigger, per_state', [('state', 1), ('timer', 0)])
def test_realtime_controller_trigger(ros_env, trigger, per_state):
    """Realtime controller: by default every plant state clocks one control step (current from
    the latest setpoint and this state's sensor reading); with ``trigger:=timer`` states only
    update the reading and its own loop (a thread of its own, from the start) publishes."""
    import rclpy
    from rclpy.parameter import Parameter

    from eha_ros.msg import ActuatorCommand, ActuatorState
    from eha_ros.nodes.controller import Controller
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = Controller(context=ctx, parameter_overrides=[
            Parameter('mode', value='realtime'), Parameter('trigger', value=trigger)])
        own = [t for t in node.timers if t is not node.handshake._timer]
        assert own == []  # no clock of its own before the graph's start
        sent = []
        node.pub.publish = sent.append
        node._on_command(ActuatorCommand(position_setpoint_m=1e-4))
        for k in range(3):
            node._on_state(ActuatorState(jack_position_measured_m=k * 1e-5))
        assert len(sent) == 3 * per_state  # before the start only states clock it
        node.handshake._begin(time.time_ns(), 'realtime')  # the start (already passed)
        kp = node.params.kp_a_m
        if not per_state:
            assert node.rt_loop is not None and node.rt_loop.loop.running
            for _ in range(500):  # the loop's thread publishes on its own
                if len(sent) >= 5:
                    break
                time.sleep(0.01)
            assert len(sent) >= 5
            from eha_ros.physics.plant import PositionController
            first = PositionController(node.params, node.period_s).update(1e-4, 2e-5)
            assert sent[0].current_command_a == pytest.approx(first)  # its first step
        else:
            assert node.rt_loop is None
            node._on_state(ActuatorState(jack_position_measured_m=2e-5))
            assert len(sent) == 4
            assert sent[-1].current_command_a == pytest.approx(kp * (1e-4 - 2e-5), rel=1e-6)
        assert [t for t in node.timers if t not in (node.timing.timer, node.handshake._timer,
                                                    *node.watchdog_timers)] == []
        node.close()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.parametrize('model', ['lut', 'ga', 'nn'])
def test_loop_with_each_surrogate_is_stable_and_matches_its_physics_run(eha_graph, model):
    """The plant with a surrogate fluid block closes the loop: the 0.1 mm step settles within
    the static band and the graph reproduces the physics-only run with that surrogate."""
    from eha_ros.surrogates.registry import load_surrogate
    r = eha_graph(processes=False, scenario='step_0p1', model=model, duration_s=0.2)
    assert set(r.state['status']) <= {0}
    x = r.state['jack_position_m']
    assert np.all(np.isfinite(x)) and abs(x[-1] - 1e-4) < 0.15e-4
    ref = simulate(default_params(), 'step_0p1', duration_s=0.2, controller_period_s=1e-3,
                   record_dt_s=None, fluid=load_surrogate(model))
    assert_array_equal(x, ref['jack_position_m'][:x.size])


def test_vocabulary_codes_equal_the_message_constants():
    """The graph's vocabulary (``eha_ros.graph``) is what the generated messages and the
    scenario file say: status and level codes, scenario names, node names."""
    from eha_ros import graph
    from eha_ros.msg import ActuatorState, HealthStatus
    from eha_ros.physics import get_scenario
    for k, name in enumerate(graph.STATUS_NAMES):
        assert getattr(ActuatorState, f'STATUS_{name}') == getattr(graph, f'STATUS_{name}') == k
    for k, name in enumerate(graph.LEVEL_NAMES):
        assert getattr(HealthStatus, f'LEVEL_{name}') == getattr(graph, f'LEVEL_{name}') == k
    for name in graph.REFERENCE_SCENARIOS:
        assert get_scenario(name).duration_s > 0
    assert set(graph.REFERENCE_MODELS) <= set(graph.MODELS)
    for node in graph.NODES:
        assert (BIN / node).is_file(), node


def test_run_graph_restores_everything_when_a_node_fails(ros_env, monkeypatch, tmp_path):
    """A node refusing its parameters in one-process mode, or an output that exists, raises
    GraphError / ParameterError with the environment restored and no context left running."""
    import os

    from eha_ros.harness import GraphConfig, GraphError, run_graph
    from eha_ros.physics import ParameterError
    env = dict(ros_env)
    monkeypatch.setenv('ROS_DOMAIN_ID', '0')
    before = dict(os.environ)
    exists = tmp_path / 'run.mcap'
    exists.write_bytes(b'keep')
    with pytest.raises(GraphError, match='exists'):
        run_graph(GraphConfig(duration_s=0.01, record=str(exists)), env=env)
    assert exists.read_bytes() == b'keep' and dict(os.environ) == before
    with pytest.raises(ParameterError, match='radial_clearance_m'):
        run_graph(GraphConfig(duration_s=0.01, plant={'radial_clearance_m': 0.0}),
                  processes=False, env=env)
    assert dict(os.environ) == before


def test_tick_timing_final_report_covers_the_run_and_ends_the_reports(ros_env):
    """A node whose run ended sends one last report at once, flagged ``Run ended`` and counting
    every tick; the window's timer then sends nothing more (no empty windows graded ERROR
    after the end), until the next :meth:`start`."""
    import time

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from eha_ros.graph import RUN_ENDED
    from eha_ros.nodes.common import subscribe
    from eha_ros.nodes.timing import TickTiming
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = Node('final_test', context=ctx)
        got = []
        subscribe(node, DiagnosticArray, '/diagnostics', lambda m: got.extend(m.status))
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        timing = TickTiming(node, 1000.0, realtime=True, window_s=0.05)
        end = time.monotonic() + 10.0
        while timing.pub.get_subscription_count() < 1 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)  # matched before anything is sent
        timing.start(time.monotonic_ns())
        for _ in range(7):
            timing.on_schedule()
        timing.publish_final()
        timing.publish_final()  # once only
        end = time.monotonic() + 5.0
        while not got and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        end = time.monotonic() + 0.3  # six windows of the timer
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        assert len(got) == 1, [s.message for s in got]
        values = {kv.key: kv.value for kv in got[0].values}
        assert values[RUN_ENDED] == '1' and values['Events since startup'] == '7'
        timing.start(time.monotonic_ns())  # a new run reports again
        end = time.monotonic() + 5.0
        while len(got) < 2 and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        assert len(got) >= 2 and RUN_ENDED not in {kv.key for kv in got[1].values}
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_tick_timing_counts_late_slipped_and_overrun_ticks(ros_env):
    """The timing report of a 1 kHz schedule fed with chosen times: a timer call 0.5 period
    late is on time, one 2.7 periods late slipped 2 ticks, a caught-up tick run 1.2 periods
    after it fell due is late, a callback of 1.5 periods is an overrun; rate and jitter
    follow, and the level is graded as diagnostic_updater's FrequencyStatus grades it."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.node import Node

    from eha_ros.nodes.timing import TickTiming
    ms = 1_000_000
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = Node('timing_test', context=ctx)
        timing = TickTiming(node, 1000.0, realtime=True)
        assert timing.name == 'timing_test: timing'
        timing._w_start = 0
        for t in (0, 1 * ms, 2 * ms + ms // 2, 5 * ms + 7 * ms // 10):
            timing.on_schedule(t)
        timing.tick(6 * ms, 12 * ms // 10)
        timing.busy(0, 3 * ms // 2)
        timing.busy(0, ms // 2)
        v = timing.values(now_ns=10 * ms)
        assert v['Events since startup'] == 5 and v['Events in window'] == 5
        assert v['Slipped ticks since startup'] == 2   # the ticks due at 3 and 4 ms
        assert v['Late ticks since startup'] == 1
        assert v['On time since startup (%)'] == pytest.approx(100 * 4 / 7, abs=1e-3)
        assert v['Overruns since startup'] == 1
        assert v['Actual frequency (Hz)'] == pytest.approx(500.0)
        assert v['Period jitter max (ms)'] == pytest.approx(2.2)  # 3.2 ms between two ticks
        assert v['Busy (core)'] == pytest.approx(0.2)
        assert timing._level[0] == DiagnosticStatus.WARN
        for t in range(1000):  # a clean second: OK
            timing.tick(20 * ms + t * ms, 0)
        timing.values(now_ns=20 * ms + 1000 * ms)
        assert timing._level == (DiagnosticStatus.OK, 'Desired frequency met.')
        timing.values(now_ns=3000 * ms)
        assert timing._level == (DiagnosticStatus.ERROR, 'No events recorded.')
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
