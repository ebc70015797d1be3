"""``servovalve_plant``: the actuator (servovalve + jack) integrated between ticks; publishes
``ActuatorState`` every tick.

``model`` selects the fluid-dynamic block: ``hf`` (the high-fidelity chambers and metering
edges) or a surrogate shipped in ``eha_ros/surrogates/models``: the dynamic ones ``dlut``,
``dnn``, ``dga`` (metering-edge flows learned, chambers and jack physical: the recommended
in-loop surrogates) or the reference's algebraic ``lut``, ``ga``, ``nn``, ``nn2``.  Between
ticks the plant takes ``1/rate_hz / dt_s`` steps of ``dt_s`` (1 us) with the last coil-current
command held.  ``integrator``: ``explicit`` (the reference scheme, the default) or ``split``
(chamber pressures implicit, first stage and spool substepped at 1 us), which meets the in-loop
bounds at steps of 10 us and more (``bench/inloop.py``).

Start: the plant coordinates the start-up handshake (:mod:`.handshake`): its first tick waits
until every endpoint of the nodes in ``handshake_nodes`` has matched its peers, and in realtime
it publishes the common start time at which it and the other ticking nodes start their clocks.

``events``: faults on the simulation clock (``'T:name=value'``), each applied at the first
tick whose time is at least T, before that tick's steps, and published on ``/eha/events``
with its tick, as is every live parameter set.

Realtime mode: the tick runs in a thread of its own (:class:`eha_ros.nodes.common.NodeLoop`:
absolute-deadline sleeps on the monotonic clock from the graph's start, ``thread_priority``
and ``cpu_affinity`` for that thread only, the executor's and the middleware's threads at
``executor_priority``; ``trace_file`` records every tick's timing); simulated time is locked
to the wall clock: when a wake comes late (a busy machine) the plant catches up the ticks that
fell due, up to ``max_catch_up`` at once; a longer stall is a slip - the backlog beyond that
is dropped, the simulation resumes from where it was, and the slip is counted and logged.

Lockstep mode: the plant is the time source:
it publishes ``/clock`` and the state of tick k, and advances to tick k+1 only when the
``ServovalveCommand`` stamped with tick k arrives; if none comes within ``resend_s`` of wall
time it publishes tick k again.  If none has come ``command_wait_s`` after the state, the
command counts as missing: the plant advances on the last one, and while commands stay
missing it advances at the realtime pace (the ticks of each 10 ms watchdog period at once;
only the last state of each batch can be answered), so that the command watchdog below runs
its course on the simulation clock.

Command watchdog (:class:`eha_ros.watchdog.TickWatchdog`): every operating tick counts the
ticks since a current command last arrived for it (realtime: since the previous tick;
lockstep: the answer stamped with the tick), and the state carries that count in
``command_age_ticks``: a tick that ran on a stale command says so.  After
``command_timeout_s`` without one (lockstep: that many ticks; realtime: that long since the
first state published after the last command, so that the plant's own catch-up bursts do not
count), the plant applies ``command_timeout_action``: ``hold``
(the last command stays), ``null_current`` (the default: zero coil current, what a servo
amplifier does when it loses its command) or ``stop`` (that tick runs at null current, its
state has status ``STATUS_STOPPED``, and the plant advances no further).  The action in force
is in every state's ``safe_action``; ``/diagnostics`` shows ``servovalve_plant: command
watchdog`` as ERROR with the reason and the tick it began, and ``/eha/events`` records the
trip and the resumption (source ``watchdog``) with their ticks.  When commands return, the
plant resumes and says so the same way.  The valve test and the pre-flight check ignore
commands, so the watchdog counts only in operation.

Valve test (``valve_test: true``): before operating, the plant runs the diagnostic valve test of
:mod:`eha_ros.physics.maintenance` - its ``valve_test_procedure`` (the reference's map sweep, or
the settled test) at ``valve_test_flows_m3_s``, one tick at a time, the jack clamped - and
reports it with status ``STATUS_VALVE_TEST`` and the procedure in ``valve_test_procedure``; the
health monitor reads the wear from those curves.  Every state carries the test bench's
readings of the conditions (supply and return pressure, fluid temperature:
:class:`eha_ros.physics.bench.ConditionSensors`, seeded by ``seed``; one reading at start and
one per tick).  Pre-flight check (``preflight_check: true``): then
(after the valve test, if any) the plant drives the coil open loop along
:data:`eha_ros.physics.maintenance.PREFLIGHT_PROFILE` from the actuator at rest, the jack free
and the controller's commands ignored, and reports it with status ``STATUS_PREFLIGHT``, the
tick's index in ``valve_test_point`` and ``valve_test_point_end`` on its last tick; the health
monitor reads the faults from that record.

Wear and degradation (overlap, clearance, eccentricity, Khsv, KGM, K_intas, backlash, friction,
hysteresis, offset, leakage) are parameters that can change while running; a non-physical value
is refused with the reason.
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

from rclpy.clock import Clock as RosClock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from eha_ros.graph import MODELS, SNAPSHOT_FIELDS, WATCHDOG_SUFFIX
from eha_ros.msg import ActuatorState, ServovalveCommand
from eha_ros.physics import (ParameterError, Plant, SimulationDiverged, get_scenario,
                             load_params)
from eha_ros.physics.events import EventSchedule, parse_event, PLANT_RUNTIME
from eha_ros.physics.params import replace
from eha_ros.physics.stability import EXPLICIT, INTEGRATORS
from eha_ros.physics.state import (CAVITATION, END_STOP, initial_state, OK,
                                   operating_condition)
from eha_ros.physics.bench import ConditionSensors, load_bench
from eha_ros.physics.maintenance import PreflightCheck, ValveTest, VALVE_TEST_PROCEDURES
from eha_ros.watchdog import SAFE_ACTIONS, TickWatchdog

from .common import (advertise, apply_realtime_settings, check_choice, declare, declare_loop,
                     declare_physics, declare_realtime, EventChannel, locked, MODES, node_loop,
                     ns_to_stamp, publish_status, run_node, stamp_to_ns, subscribe, take_changes,
                     take_waiting, TOPIC_CLOCK, TOPIC_SERVOVALVE, TOPIC_STATE, validator)
from .handshake import StartCoordinator
from .timing import begin_timing, TickTiming

#: The status of each operating condition (:func:`eha_ros.physics.state.operating_condition`).
CONDITION_STATUS = {OK: ActuatorState.STATUS_OK, END_STOP: ActuatorState.STATUS_END_STOP,
                    CAVITATION: ActuatorState.STATUS_CAVITATION}

#: The nodes the plant waits for by default (the loop); the harness names every node it runs.
DEFAULT_HANDSHAKE_NODES = ('command_generator', 'controller')


def load_fluid(model: str, params):
    """The fluid block for ``model``: None for hf, else the shipped surrogate."""
    if model == 'hf':
        return None
    check_choice('model', model, MODELS)
    from eha_ros.surrogates.registry import load_surrogate
    return load_surrogate(model, params)


class ServovalvePlant(Node):
    """The plant node."""

    def __init__(self, **kwargs):
        init_ns = time.monotonic_ns()
        super().__init__('servovalve_plant', **kwargs)
        s = self._declare_parameters()
        dt_s, integrator, rate, seed = s.dt_s, s.integrator, s.rate, s.seed
        check_choice('mode', self.mode, MODES)
        params = replace(s.base, **{n: self.get_parameter(n).value for n in PLANT_RUNTIME})
        self.fluid = load_fluid(self.model, params)
        self.plant = Plant(params, dt_s=dt_s, seed=seed, fluid=self.fluid,
                           integrator=integrator)
        Plant(params, dt_s=dt_s, seed=seed, fluid=self.fluid,  # JIT first
              integrator=integrator).advance(0.0, 1)
        period_ns = round(1e9 / rate)
        if period_ns % self.plant.dt_ns:
            raise ParameterError(f'the tick period {period_ns} ns must be a whole number of '
                                 f'dt_s = {dt_s:g} s')
        self.period_ns = period_ns
        self.command_watchdog = TickWatchdog(s.command_timeout_s, period_ns, s.timeout_action)
        self._fresh = False      # a current command arrived since the last tick
        self._unanswered_since = None  # realtime: first state published since the last command
        self._missing = False    # lockstep: the last tick's command was missing
        self.stopped = False     # the watchdog's stop action ended the run
        self.schedule = EventSchedule([parse_event(e) for e in s.events if e.strip()],
                                      allowed=PLANT_RUNTIME, period_ns=period_ns)
        self.schedule.validate(params)
        for ev in self.schedule:
            if self.fluid is not None:
                self.fluid.check_params(replace(params, **ev.as_dict()))
        self.steps_per_tick = period_ns // self.plant.dt_ns
        check_choice('valve_test_procedure', s.procedure, VALVE_TEST_PROCEDURES)
        self.valve_test = (ValveTest.of(s.procedure, period_ns, dt_s, s.flows) if s.valve_test
                           else None)
        # the test bench's transducers of the conditions: one reading per published tick
        self.sensors = ConditionSensors(seed, load_bench())
        self.conditions = self.sensors.read(params)[0]
        self.test_tick = 0
        self.test_sample = None
        if self.valve_test is not None:
            self.valve_test.sample(1, params)  # JIT first
        self.preflight = (PreflightCheck(period_ns, params.current_limit_a) if s.preflight
                          else None)
        self.preflight_tick = 0
        self.preflight_last = -1   # self.ticks of the last pre-flight tick
        self.events = EventChannel(self, period_ns)
        self.add_on_set_parameters_callback(validator(self._on_set))
        self.state_pub = advertise(self, ActuatorState, TOPIC_STATE)
        self._command_node = None
        if self.mode == 'realtime':
            # read by the tick loop itself (take), on a node that no executor spins: the
            # executor's thread would otherwise take the GIL for every command, 1 kHz of
            # hand-overs with the loop's thread
            self._command_node = Node(self.get_name() + '_commands', context=self.context,
                                      start_parameter_services=False)
            command_sub = self._command_sub = subscribe(self._command_node, ServovalveCommand,
                                                        TOPIC_SERVOVALVE, lambda msg: None)
        else:
            command_sub = subscribe(self, ServovalveCommand, TOPIC_SERVOVALVE,
                                    self._on_command)
        self.current_a = 0.0
        self.done = False
        self.diverged = False
        self.ticks = 0
        self.fatal = None
        self._msg = None
        self.timing = TickTiming(self, rate, self.mode == 'realtime')
        self._steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self._started = False
        self._last_pub_ns = 0
        self._first_pub_ns, self._pub_tick_ns = 0, -1   # lockstep: the tick's first publication
        self.slipped_ticks = 0
        if self.mode == 'lockstep':
            self.clock_pub = advertise(self, Clock, TOPIC_CLOCK)
        self.handshake = StartCoordinator(self, s.handshake_nodes, self.mode,
                                          s.handshake_timeout_s, s.start_delay_s,
                                          on_start=self._on_start)
        for entity, topic in ((self.state_pub, TOPIC_STATE), (command_sub, TOPIC_SERVOVALVE),
                              (self.timing.pub, '/diagnostics')):
            self.handshake.watch(entity, topic)
        if self.mode == 'lockstep':
            self.handshake.watch(self.clock_pub, TOPIC_CLOCK)
        self._watchdog = self.create_timer(0.01, self._on_watchdog, clock=self._steady)
        # realtime: the tick in a thread of its own
        self.rt_loop = node_loop(self, self.mode == 'realtime', self._on_loop_wake, s.realtime,
                                 s.loop_options, 'a lockstep plant')
        self._warm_up_s = (time.monotonic_ns() - init_ns) * 1e-9
        if self.rt_loop is not None:
            self._state_msg()  # the state message's first fill now, not in tick 0
        apply_realtime_settings(self, s.realtime, self.rt_loop)
        self.get_logger().info(f'model {self.model}, dt {dt_s:g} s ({integrator}), '
                               f'{self.steps_per_tick} '
                               f'steps per tick, {self.mode}; waiting for '
                               f'{", ".join(self.handshake.nodes)}')

    def _declare_parameters(self) -> SimpleNamespace:
        """Declare every parameter of the node (the physical ones through
        :func:`.common.declare_physics`); returns the settings the constructor uses, the
        nominal parameters ``base`` among them."""
        s = SimpleNamespace()
        path = declare(self, 'params_file', '', 'physical parameter YAML (empty: the installed '
                       'config/eha_params.yaml)')
        s.base = load_params(path or None)
        declare_physics(self, s.base, PLANT_RUNTIME)
        self.model = declare(self, 'model', 'hf', 'fluid-dynamic block', choices=MODELS)
        s.dt_s = declare(self, 'dt_s', 1e-6, 'plant integration step [s]', 1e-9, 1e-3)
        s.integrator = declare(self, 'integrator', EXPLICIT, 'plant integration scheme '
                               '(explicit: the 1 us reference; split: implicit chambers, '
                               'for steps up to tens of us)', choices=INTEGRATORS)
        s.rate = declare(self, 'rate_hz', 1000.0, 'tick rate [Hz]', 1.0, 1e5)
        self.mode = declare(self, 'mode', 'realtime', 'timing mode', choices=MODES)
        s.seed = declare(self, 'seed', 0, 'seed of the torque-motor noise', 0, 2 ** 31 - 1)
        self.duration_s = declare(self, 'duration_s', 0.0, 'stop advancing after this simulated '
                                  'time [s] (0: never)', 0.0, 1e9)
        self.resend_s = declare(self, 'resend_s', 2.0, 'lockstep: re-publish the tick after '
                                'this long without its command [s]', 0.01, 60.0)
        s.handshake_nodes = declare(self, 'handshake_nodes', list(DEFAULT_HANDSHAKE_NODES),
                                    'start-up handshake: nodes whose endpoints must all have '
                                    'matched before the first tick (this node is always one)')
        s.handshake_timeout_s = declare(self, 'handshake_timeout_s', 0.0, 'start-up handshake: '
                                        'fail after this long without a start [s] (0: wait)',
                                        0.0, 3600.0)
        s.start_delay_s = declare(self, 'start_delay_s', 0.25, 'realtime: the common start '
                                  'lies this long after the handshake completes, so that every '
                                  'node has it in time [s]', 0.0, 10.0)
        s.events = declare(self, 'events', [''], "faults on the simulation clock: 'T:name=value"
                           "[,name=value]' entries, each applied at the first tick whose time "
                           "is at least T s (empty entries are ignored)")
        s.realtime = declare_realtime(self)
        s.loop_options = declare_loop(self)
        s.valve_test = declare(self, 'valve_test', False, 'run the diagnostic valve test (map '
                               'sweep, jack clamped) before operating')
        s.flows = declare(self, 'valve_test_flows_m3_s',  # those of the valve_test scenario
                          list(get_scenario('valve_test').valve_test_flows_m3_s),
                          'valve test: imposed load flows [m^3/s], one P12 curve each')
        s.procedure = declare(self, 'valve_test_procedure', 'reference', 'valve test: settled '
                              '(every point held 0.1 s, fitted by the valve model) or reference '
                              '(the reference\'s 10 ms map transient)',
                              choices=VALVE_TEST_PROCEDURES)
        s.preflight = declare(self, 'preflight_check', False, 'run the pre-flight check (open-'
                              'loop current steps and sines, jack free) before operating')
        self.max_catch_up = declare(self, 'max_catch_up', 50, 'realtime: most late ticks '
                                    'caught up at once; a longer stall slips', 1, 100000)
        s.command_timeout_s = declare(self, 'command_timeout_s', 0.02, 'command watchdog: the '
                                      'safe action follows this long without a current '
                                      'command [s] (lockstep: in ticks; realtime: since the '
                                      'first state left unanswered)', 1e-6, 60.0)
        s.timeout_action = declare(self, 'command_timeout_action', 'null_current', 'command '
                                   'watchdog: what follows the timeout', choices=SAFE_ACTIONS)
        self.command_wait_s = declare(self, 'command_wait_s', 10.0, 'lockstep: a tick whose '
                                      'command has not come this long after its state counts '
                                      'as missing [s]', 0.01, 3600.0)
        return s

    # parameters --------------------------------------------------------------------------
    @locked
    def _on_set(self, changes):
        frozen = {'model', 'dt_s', 'integrator', 'rate_hz', 'mode', 'seed', 'params_file',
                  'valve_test',
                  'command_timeout_s', 'command_timeout_action', 'command_wait_s',
                  'valve_test_flows_m3_s', 'valve_test_procedure', 'preflight_check',
                  'handshake_nodes',
                  'handshake_timeout_s', 'start_delay_s', 'events', 'thread_priority',
                  'cpu_affinity', 'lock_memory', 'executor_priority', 'switch_interval_s',
                  'trace_file', 'trace_ticks'} & set(changes)
        if frozen:
            raise ParameterError(f'{sorted(frozen)[0]} cannot change while running')
        wear = {k: v for k, v in changes.items() if k in PLANT_RUNTIME}
        if wear and not self.events.applying:
            params = replace(self.plant.params, **wear)  # raises with the reason if bad
            if self.fluid is not None:
                self.fluid.check_params(params)
            self.plant.set_params(params)
            self.events.publish(self.plant.time_ns, 'live', math.nan, wear)
        take_changes(self, changes, duration_s=float, max_catch_up=int, resend_s=float)

    # command watchdog --------------------------------------------------------------------
    def _operating_current(self) -> float:
        """Step the command watchdog for an operating tick; the current it runs on."""
        overdue = None
        if self.mode == 'realtime':
            since = self._unanswered_since
            overdue = 0.0 if since is None else (self._now_ns() - since) * 1e-9
        tr = self.command_watchdog.step(self._fresh, overdue)
        self._fresh = False
        if tr is not None:
            self._report_watchdog(tr)
        action = self.command_watchdog.in_force
        if action == 'stop':
            self.done = self.stopped = True
        return self.current_a if action in (None, 'hold') else 0.0

    def _report_watchdog(self, tr) -> None:
        """A trip or a resumption: logged, on ``/eha/events`` and on ``/diagnostics``."""
        wd = self.command_watchdog
        t_ns = self.plant.time_ns
        if tr.kind == 'tripped':
            self.get_logger().error(
                f'no current command for {tr.age} ticks ({tr.age * self.period_ns * 1e-9:g} s) '
                f'at t = {t_ns * 1e-9:.6g} s (tick {t_ns // self.period_ns}): {wd.action}')
        else:
            self.get_logger().warning(
                f'current commands resumed at t = {t_ns * 1e-9:.6g} s (tick '
                f'{t_ns // self.period_ns}) after {tr.age} ticks without one')
        self._watchdog_began = (t_ns // self.period_ns, t_ns) if tr.kind == 'tripped' else None
        self.events.publish(t_ns, 'watchdog', math.nan,
                            {'safe_action': wd.code, 'command_age_ticks': tr.age})
        self._publish_watchdog()

    @locked
    def _publish_watchdog(self) -> None:
        """``servovalve_plant: command watchdog`` on ``/diagnostics``: ERROR while an action is
        in force (with the reason and the tick it began), WARN once it has tripped and
        resumed, else OK (with the count of ticks that ran on a stale command)."""
        from diagnostic_msgs.msg import DiagnosticStatus
        wd = self.command_watchdog
        began = getattr(self, '_watchdog_began', None)
        if wd.in_force is not None and began is not None:
            level = DiagnosticStatus.ERROR
            message = (f'no current command for {wd.timeout_ticks} ticks: {wd.action} since '
                       f'tick {began[0]} (t = {began[1] * 1e-9:.6g} s)')
        elif wd.trips:
            level = DiagnosticStatus.WARN
            message = (f'tripped {wd.trips} times since startup, resumed; {wd.stale_ticks} '
                       'ticks ran on a stale command')
        else:
            level = DiagnosticStatus.OK
            message = f'{wd.stale_ticks} ticks ran on a stale command since startup'
        values = {'Action': wd.action, 'Action in force': wd.in_force or 'none',
                  'Timeout (ticks)': wd.timeout_ticks, 'Command age (ticks)': wd.age,
                  'Stale ticks since startup': wd.stale_ticks,
                  'Trips since startup': wd.trips,
                  'Began at tick': began[0] if began else -1}
        publish_status(self, self.timing.pub, self.get_name() + WATCHDOG_SUFFIX, level,
                       message, values)

    def _apply_due_events(self) -> None:
        """Scheduled events due at this tick (time at least T) take effect before its steps;
        the node's parameters are updated to match."""
        for ev in self.schedule.due(self.plant.time_ns):
            changes = ev.as_dict()
            self.plant.set_params(replace(self.plant.params, **changes))
            self.events.publish(self.plant.time_ns, 'schedule', ev.t_s, changes)
            self.events.mirror(changes)

    # stepping ----------------------------------------------------------------------------
    def _advance(self):
        if self.done or self.diverged:
            return False
        try:
            if self.schedule.pending:
                self._apply_due_events()
            if self.valve_test is not None and self.test_tick < self.valve_test.n_ticks:
                self.test_tick += 1
                self.test_sample = self.valve_test.sample(self.test_tick, self.plant.params)
                self.plant.hold(self.steps_per_tick)
            elif self.preflight is not None and self.preflight_tick < self.preflight.n_ticks:
                if self.preflight_tick == 0:  # from the actuator at rest
                    self.plant.state[:] = initial_state(self.plant.params)
                self.test_sample = None
                self.plant.advance(float(self.preflight.command_a[self.preflight_tick]),
                                   self.steps_per_tick)
                self.preflight_tick += 1
                self.preflight_last = self.ticks + 1
            else:
                self.test_sample = None
                self.plant.advance(self._operating_current(), self.steps_per_tick)
        except (SimulationDiverged, FloatingPointError) as exc:
            self.diverged = True
            self.get_logger().error(str(exc))
            return True
        self.ticks += 1
        self.conditions = self.sensors.read(self.plant.params)[0]
        if self.stopped:
            self.get_logger().error(f'stopped at t = {self.plant.time_s:.6g} s by the command '
                                    'watchdog')
        elif self.duration_s and self.plant.time_ns >= round(self.duration_s * 1e9):
            self.done = True
            self.get_logger().info(f'scenario complete at t = {self.plant.time_s:.6g} s')
        return True

    def _state_msg(self) -> ActuatorState:
        """The tick's state. One message object is filled every tick (publishing serializes
        it at once): no allocation per tick beyond the numbers themselves."""
        s = self.plant.snapshot()
        p = self.plant.params
        msg = self._msg
        if msg is None:
            msg = self._msg = ActuatorState()
            msg.header.frame_id = 'jack'
            msg.model = self.model
        ns_to_stamp(msg.header.stamp, self.plant.time_ns)
        msg.valve_test_point = 0
        msg.valve_test_point_end = False
        msg.valve_test_procedure = 0
        msg.command_age_ticks = 0
        msg.safe_action = 0
        msg.final_state = self.done
        c = self.conditions
        msg.supply_pressure_measured_pa = float(c[0])
        msg.return_pressure_measured_pa = float(c[1])
        msg.fluid_temperature_measured_k = float(c[2])
        for name in SNAPSHOT_FIELDS:
            setattr(msg, name, s[name])
        msg.sim_time_s = self.plant.time_s
        msg.tick = self.plant.steps
        t = self.test_sample
        if t is not None:
            msg.spool_position_m = t.spool_position_m
            msg.load_flow_m3_s = t.load_flow_m3_s
            msg.p1_pa = t.p1_pa
            msg.p2_pa = t.p2_pa
            msg.p12_pa = t.p1_pa - t.p2_pa
            msg.jack_velocity_m_s = 0.0
            msg.valve_test_point = t.point
            msg.valve_test_point_end = t.point_end
            msg.valve_test_procedure = (ActuatorState.VALVE_TEST_SETTLED
                                        if self.valve_test.procedure == 'settled'
                                        else ActuatorState.VALVE_TEST_REFERENCE)
        preflight = (self.preflight is not None and t is None
                     and self.preflight_tick > 0 and self.preflight_last == self.ticks)
        if preflight:
            msg.valve_test_point = self.preflight_tick - 1
            msg.valve_test_point_end = self.preflight_tick == self.preflight.n_ticks
        if t is None and not preflight:
            msg.command_age_ticks = min(self.command_watchdog.age, 2 ** 32 - 1)
            msg.safe_action = self.command_watchdog.code
        if self.diverged:
            msg.status = ActuatorState.STATUS_DIVERGED
        elif self.stopped:
            msg.status = ActuatorState.STATUS_STOPPED
        elif t is not None:
            msg.status = ActuatorState.STATUS_VALVE_TEST
        elif preflight:
            msg.status = ActuatorState.STATUS_PREFLIGHT
        else:
            msg.status = CONDITION_STATUS[operating_condition(self.plant.state, p)]
        return msg

    def _publish_tick(self):
        if self.mode == 'lockstep':
            clock = Clock()
            ns_to_stamp(clock.clock, self.plant.time_ns)
            self.clock_pub.publish(clock)
        self.state_pub.publish(self._state_msg())
        self._last_pub_ns = self._now_ns()
        if self.plant.time_ns != self._pub_tick_ns:  # a new tick, not a re-sent one
            self._pub_tick_ns, self._first_pub_ns = self.plant.time_ns, self._last_pub_ns

    # start -------------------------------------------------------------------------------
    def _on_start(self, start_ns: int, mode: str) -> None:
        """The handshake is complete: lockstep publishes tick 0 now; realtime publishes tick 0
        at the common start time and tick k k periods later."""
        start_mono = (self.handshake.start_monotonic_exact_ns
                      or self.handshake.start_monotonic_ns())
        begin_timing(self, self.timing, start_mono, self._warm_up_s)
        self._started = True
        self.create_timer(1.0, self._publish_watchdog, clock=self._steady)
        if self.mode == 'lockstep':
            self._publish_tick()
            return
        self._watchdog.cancel()  # realtime: it only watched the handshake
        self._anchor(start_mono)
        self.rt_loop.start(start_mono, self.timing.gc)

    def _anchor(self, start_mono_ns: int) -> None:
        """Realtime: tick k falls due at ``start_mono_ns`` plus k periods."""
        self._rt_anchor = start_mono_ns
        self._rt_next = 0

    # realtime ----------------------------------------------------------------------------
    def _now_ns(self) -> int:
        """The steady clock's time [ns] (realtime ticks fall due on it)."""
        return self._steady.now().nanoseconds

    def _take_commands(self) -> None:
        """Realtime: every current command that arrived since the last wake, the latest
        kept."""
        for msg, _ in take_waiting(self._command_sub, ServovalveCommand):
            self.current_a = msg.current_command_a
            self._fresh, self._unanswered_since = True, None

    def _on_loop_wake(self, now: int):
        """The tick loop woke (its thread, the lock held): take the commands that arrived,
        run the ticks due by ``now``."""
        began = time.monotonic_ns()
        try:
            if self._started:
                self._take_commands()
            self._catch_up(now)
        finally:
            self.timing.busy(began)
        self._end_timing()

    def _end_timing(self) -> None:
        """After the tick that ended the run (the end, a stop or a divergence): the final
        timing report (:meth:`TickTiming.publish_final`)."""
        if self.done or self.diverged:
            self.timing.publish_final()

    def _catch_up(self, now: int):
        """Run every tick due by ``now``: tick k falls due at the start plus k periods (plus
        the periods slipped so far); at most ``max_catch_up`` at once, the rest slips."""
        if now < self._rt_anchor:
            return  # before the start (the timer runs from the handshake on)
        due = (now - self._rt_anchor) // self.period_ns
        behind = due - self._rt_next + 1
        if behind <= 0:
            return
        if behind > self.max_catch_up:
            slip = behind - self.max_catch_up
            self.slipped_ticks += slip
            self.timing.slip(slip)
            self._rt_anchor += slip * self.period_ns
            behind = self.max_catch_up
            self.get_logger().warning(
                f'{slip} ticks behind the wall clock: slipped ({self.slipped_ticks} in all)',
                throttle_duration_sec=1.0)
        mono = time.monotonic_ns
        for _ in range(behind):
            k = self._rt_next
            if k > 0 and not self._advance():
                return
            self._rt_next += 1
            msg = self._state_msg()
            work_end = mono()
            self.state_pub.publish(msg)
            due = self._rt_anchor + k * self.period_ns
            self.rt_loop.record(k, due, work_end, mono())
            if self._unanswered_since is None:
                self._unanswered_since = now
            self.timing.tick(now, now - due)

    def _on_command(self, msg: ServovalveCommand):
        """Lockstep: the answer to the tick waiting advances it (realtime commands are taken
        by the tick loop, :meth:`_take_commands`)."""
        if stamp_to_ns(msg.header.stamp) != self.plant.time_ns:
            return  # an answer to a tick already advanced (a re-sent tick)
        self.current_a = msg.current_command_a
        self._fresh, self._missing = True, False
        began = time.monotonic_ns()
        if self._advance():
            self._publish_tick()
            self.timing.tick(began)
        self.timing.busy(began)
        self._end_timing()

    # lockstep ----------------------------------------------------------------------------
    def _on_watchdog(self):
        if not self._started:
            if self.handshake.error and not self.fatal:
                self.fatal = self.handshake.error
                self.get_logger().error(self.fatal)
            return
        if self.mode != 'lockstep' or self.done or self.diverged:
            return
        now = self._now_ns()
        waited = now - (self._last_pub_ns if self._missing else self._first_pub_ns)
        if waited > (0.009 if self._missing else self.command_wait_s) * 1e9:
            # the command of this tick is missing: advance on the last one (the watchdog counts)
            if not self._missing:
                self.get_logger().error(f'no command for tick t = {self.plant.time_s:.6g} s in '
                                        f'{waited * 1e-9:.3g} s: advancing without it')
            # while commands stay missing, at the realtime pace: the ticks of the wait at once
            n = max(1, min(10, waited // self.period_ns)) if self._missing else 1
            self._missing = True
            began = time.monotonic_ns()
            for _ in range(n):
                if not self._advance():
                    break
                self._publish_tick()
                self.timing.tick(began)
            self.timing.busy(began)
            self._end_timing()
            return
        if now - self._last_pub_ns > self.resend_s * 1e9 and not self._missing:
            self.get_logger().warning(f'no command for tick t = {self.plant.time_s:.6g} s: '
                                      're-publishing it')
            self.timing.resent += 1
            self._publish_tick()

    def close(self) -> None:
        """Stop the tick loop (and write its timing trace), then its command reader."""
        if self.rt_loop is not None:
            self.rt_loop.close()
        if self._command_node is not None:
            self._command_node.destroy_node()
            self._command_node = None


def main(args=None) -> int:
    return run_node(ServovalvePlant, args)


ServovalvePlant.node_name = 'servovalve_plant'
