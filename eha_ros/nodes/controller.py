"""``controller``: PID on the jack position error, publishes the coil current command
(``ServovalveCommand``).

Realtime mode: each plant state clocks one control step (``trigger: state``, the default: the
sensor sample triggers the digital controller, so it runs at the plant's rate and no
timer of its own competes for the processor), or a loop at ``rate_hz`` in a thread of its own
does (``trigger: timer``; absolute deadlines from the graph's start,
:class:`eha_ros.nodes.common.NodeLoop`); either uses the latest command and the latest sensor
reading.

Lockstep mode: for each plant tick it waits for both the state and the command of
that tick (matching stamps), then answers with the current for that tick; a repeated tick
(the plant re-sending after a lost message) gets the same answer again.

``events``: gain changes on the simulation clock (``'T:kp_a_m=value'``), each applied at the
first tick whose time is at least T, before that tick's control update, and published on
``/eha/events``; live gain sets are published there too.

``silent`` (an event switch, ``'T:silent=1'``): from the first tick whose time is at least T
the controller publishes no current command (a dropped controller, on the simulation clock, so
a lockstep run with it is repeatable); ``'T:silent=0'`` resumes.  The plant's command watchdog
takes over meanwhile.

State watchdog: once the graph has started, when no plant state has arrived for
``state_timeout_s`` of wall time (a dead or hung plant; not after the plant's last state,
``final_state``), the controller stops commanding: in realtime it publishes one null current
command flagged ``state_timeout`` (in lockstep it answers states only, so it sends nothing),
logs the tick of the last state and shows ``controller: state watchdog`` as ERROR on
``/diagnostics``; the next state resumes control, and it says so.

The arithmetic is :class:`eha_ros.physics.plant.PositionController`, the same as the
physics-only closed loop.  Parameters: ``kp_a_m``, ``ki_a_m_s``, ``kd_a_s_m``,
``current_limit_a`` (defaults from ``params_file``), ``rate_hz``, ``mode``, ``trigger``,
``params_file``.
"""

from __future__ import annotations

import math
import time

from rclpy.node import Node

from eha_ros.graph import TOPIC_DIAGNOSTICS
from eha_ros.msg import ActuatorCommand, ActuatorState, ServovalveCommand
from eha_ros.physics import ParameterError, load_params
from eha_ros.physics.events import CONTROLLER_RUNTIME, EventSchedule, parse_event, SWITCHES
from eha_ros.physics.params import replace
from eha_ros.physics.plant import PositionController

from .common import (advertise, apply_realtime_settings, check_choice, declare, declare_loop,
                     declare_physics, declare_realtime, EventChannel, locked, MODES, node_loop,
                     publish_status, run_node, stamp_to_ns, subscribe, TOPIC_COMMAND,
                     TOPIC_SERVOVALVE, TOPIC_STATE, validator)
from .handshake import Handshake
from .timing import begin_timing, TickTiming

GAINS = CONTROLLER_RUNTIME


#: What clocks the realtime controller.
TRIGGERS = ('state', 'timer')


class Controller(Node):
    """Position controller node."""

    def __init__(self, **kwargs):
        init_ns = time.monotonic_ns()
        super().__init__('controller', **kwargs)
        path = declare(self, 'params_file', '', 'physical parameter YAML (empty: the installed '
                       'config/eha_params.yaml)')
        self.base = load_params(path or None)
        declare_physics(self, self.base, GAINS)
        declare(self, 'rate_hz', 1000.0, 'control rate [Hz]', 1.0, 1e5)
        self.mode = declare(self, 'mode', 'realtime', 'timing mode', choices=MODES)
        self.trigger = declare(self, 'trigger', 'state', 'realtime: a control step per plant '
                               'state, or per tick of its own timer', choices=TRIGGERS)
        events = declare(self, 'events', [''], "gain changes on the simulation clock: "
                         "'T:name=value[,name=value]' entries, each applied at the first tick "
                         "whose time is at least T s (empty entries are ignored)")
        self.state_timeout_s = declare(self, 'state_timeout_s', 0.25, 'state watchdog: stop '
                                       'commanding after this long without a plant state [s] '
                                       '(wall time)', 1e-3, 3600.0)
        realtime = declare_realtime(self)
        loop_options = declare_loop(self)
        check_choice('trigger', self.trigger, TRIGGERS)
        check_choice('mode', self.mode, MODES)
        self.period_s = 1.0 / self.get_parameter('rate_hz').value
        self.params = self._params({})
        self.period_ns = round(self.period_s * 1e9)
        self.schedule = EventSchedule([parse_event(e) for e in events if e.strip()],
                                      allowed=GAINS + ('silent',), period_ns=self.period_ns)
        self.schedule.validate(self.params)
        self.pid = PositionController(self.params, self.period_s)
        PositionController(self.params, self.period_s).update(0.0, 0.0)  # JIT before tick 0
        self.events = EventChannel(self, self.period_ns)
        self.add_on_set_parameters_callback(validator(self._on_set))
        self._stamp_ns = 0  # the tick being served (its state's stamp)
        self.pub = advertise(self, ServovalveCommand, TOPIC_SERVOVALVE)
        command_sub = subscribe(self, ActuatorCommand, TOPIC_COMMAND, self._on_command)
        state_sub = subscribe(self, ActuatorState, TOPIC_STATE, self._on_state)
        self.command_m = 0.0
        self.measured_m = 0.0
        self._commands = {}  # lockstep: stamp ns -> setpoint, for ticks not yet answered
        self._state_ns = None  # lockstep: tick waiting for its command
        self._answered = (None, 0.0)  # lockstep: last tick answered and its current
        self.published = 0
        self.silent = False          # the silent switch is on: no current commands
        self._last_state_ns = None   # time.monotonic_ns of the last state
        self._state_timed_out = False
        self._plant_done = False     # the plant's last state came: nothing more to wait for
        self.watchdog_timers = ()
        self.timing = TickTiming(self, 1.0 / self.period_s, self.mode == 'realtime')
        self.handshake = Handshake(self, on_start=self._on_start)
        for entity, topic in ((self.pub, TOPIC_SERVOVALVE), (command_sub, TOPIC_COMMAND),
                              (state_sub, TOPIC_STATE), (self.timing.pub, TOPIC_DIAGNOSTICS)):
            self.handshake.watch(entity, topic)
        self.fatal = None
        self.rt_loop = node_loop(  # realtime, trigger: timer: a thread of its own
            self, self.mode == 'realtime' and self.trigger == 'timer', self._on_loop_wake,
            realtime, loop_options, 'a controller clocked by states (trigger: state) or in '
            'lockstep')
        self._warm_up_s = (time.monotonic_ns() - init_ns) * 1e-9
        apply_realtime_settings(self, realtime, self.rt_loop)

    def _on_start(self, start_ns: int, mode: str) -> None:
        from rclpy.clock import Clock as RosClock, ClockType
        start_mono = self.handshake.start_monotonic_ns()
        self._last_state_ns = max(start_mono, time.monotonic_ns())
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.watchdog_timers = (
            self.create_timer(min(0.05, self.state_timeout_s / 4), self._on_state_watchdog,
                              clock=steady),
            self.create_timer(1.0, self._publish_state_watchdog, clock=steady))
        begin_timing(self, self.timing, start_mono, self._warm_up_s)
        if self.rt_loop is not None:
            self._rt_anchor = start_mono
            self.rt_loop.start(start_mono, self.timing.gc)

    def _params(self, changes):
        values = {n: self.get_parameter(n).value for n in GAINS}
        values.update({k: v for k, v in changes.items() if k in GAINS})
        return replace(self.base, **values)

    @locked
    def _on_set(self, changes):
        frozen = {'mode', 'rate_hz', 'params_file', 'trigger', 'events', 'thread_priority',
                  'cpu_affinity', 'lock_memory', 'state_timeout_s', 'executor_priority',
                  'switch_interval_s', 'trace_file', 'trace_ticks'} & set(changes)
        if frozen:
            raise ParameterError(f'{sorted(frozen)[0]} cannot change while running')
        gains = {k: v for k, v in changes.items() if k in GAINS}
        if gains and not self.events.applying:
            self.params = self._params(gains)
            self.pid.params = self.params
            self.events.publish(self._stamp_ns, 'live', math.nan, gains)

    def _apply_due_events(self, t_ns: int) -> None:
        """Gain changes due at the tick stamped ``t_ns`` take effect before its update."""
        for ev in self.schedule.due(t_ns):
            changes = ev.as_dict()
            gains = {k: v for k, v in changes.items() if k not in SWITCHES}
            if 'silent' in changes:
                self.silent = bool(changes['silent'])
            if gains:
                self.params = replace(self.params, **gains)
                self.pid.params = self.params
            self.events.publish(t_ns, 'schedule', ev.t_s, changes)
            if gains:
                self.events.mirror(gains)

    def _send(self, stamp, current_a, state_timeout: bool = False):
        if self.silent:
            return
        msg = ServovalveCommand()
        msg.header.stamp = stamp
        msg.header.frame_id = 'jack'
        msg.current_command_a = float(current_a)
        msg.state_timeout = state_timeout
        self.pub.publish(msg)
        self.published += 1

    # state watchdog -------------------------------------------------------------------------
    def _on_state_watchdog(self):
        if self._last_state_ns is None or self._state_timed_out or self._plant_done:
            return
        quiet_s = (time.monotonic_ns() - self._last_state_ns) * 1e-9
        if quiet_s < self.state_timeout_s:
            return
        self._state_timed_out = True
        self.get_logger().error(f'no plant state for {quiet_s:.3g} s (the last at t = '
                                f'{self._stamp_ns * 1e-9:.6g} s): null current, control stopped')
        # lockstep answers states only: a command stamped now would be taken as the answer
        # to the tick the plant waits on
        if self.mode == 'realtime':
            self._send(self.get_clock().now().to_msg(), 0.0, state_timeout=True)
        self._publish_state_watchdog()

    def _publish_state_watchdog(self):
        from diagnostic_msgs.msg import DiagnosticStatus
        if self._state_timed_out:
            level = DiagnosticStatus.ERROR
            message = (f'no plant state for {self.state_timeout_s:g} s since t = '
                       f'{self._stamp_ns * 1e-9:.6g} s: null current, control stopped')
        else:
            level, message = DiagnosticStatus.OK, 'plant states arriving'
        publish_status(self, self.timing.pub, self.get_name() + ': state watchdog', level,
                       message, {'Timeout (s)': self.state_timeout_s,
                                 'Last state (s)': self._stamp_ns * 1e-9})

    # realtime -------------------------------------------------------------------------------
    def _on_timer(self):
        if self._state_timed_out:
            return  # no plant state: control stopped (the null current is sent)
        current = self.pid.update(self.command_m, self.measured_m)
        self._send(self.get_clock().now().to_msg(), current)

    def _on_loop_wake(self, now: int):
        """The control loop woke (its thread, the lock held): one step on the latest
        setpoint and reading (a late wake runs one step: the timer's ticks in between slip)."""
        began = time.monotonic_ns()
        self.timing.on_schedule(now)
        self._on_timer()
        due = self.rt_loop.deadline_ns
        end = time.monotonic_ns()
        self.rt_loop.record((due - self._rt_anchor) // self.period_ns, due, end, end)
        self.timing.busy(began)

    def close(self) -> None:
        """Stop the control loop (and write its timing trace)."""
        if self.rt_loop is not None:
            self.rt_loop.close()

    # both modes ----------------------------------------------------------------------------
    @locked
    def _on_command(self, msg: ActuatorCommand):
        self.command_m = msg.position_setpoint_m
        if self.mode == 'lockstep':
            t_ns = stamp_to_ns(msg.header.stamp)
            self._commands[t_ns] = (msg.position_setpoint_m, msg.header.stamp)
            self._try_answer()

    @locked
    def _on_state(self, msg: ActuatorState):
        self._last_state_ns = time.monotonic_ns()
        self._plant_done = msg.final_state
        if self._state_timed_out:
            self._state_timed_out = False
            self.get_logger().warning(f'plant states resumed at t = '
                                      f'{stamp_to_ns(msg.header.stamp) * 1e-9:.6g} s: control '
                                      'resumes')
            self._publish_state_watchdog()
        self.measured_m = msg.jack_position_measured_m
        self._stamp_ns = stamp_to_ns(msg.header.stamp)
        if self.schedule.pending:
            self._apply_due_events(self._stamp_ns)
        if self.mode == 'realtime':
            if self.trigger == 'state':
                began = time.monotonic_ns()
                self.timing.tick(began)  # paced by the plant's states: no schedule of its own
                self._on_timer()
                self.timing.busy(began)
            if self._plant_done:
                self.timing.publish_final()  # the plant's last state: the run has ended
            return
        if self._stamp_ns == self._answered[0]:  # lockstep: the plant asks again
            self._send(msg.header.stamp, self._answered[1])
            return
        self._state_ns = self._stamp_ns
        self._state_measured = msg.jack_position_measured_m
        self._try_answer()

    def _try_answer(self):
        t_ns = self._state_ns
        if t_ns is None or t_ns not in self._commands:
            return
        setpoint, stamp = self._commands.pop(t_ns)
        for old in [k for k in self._commands if k < t_ns]:
            del self._commands[old]
        began = time.monotonic_ns()
        current = self.pid.update(setpoint, self._state_measured)
        self._answered = (t_ns, current)
        self._state_ns = None
        self._send(stamp, current)
        self.timing.tick(began)
        self.timing.busy(began)
        if self._plant_done:
            self.timing.publish_final()  # the answer to the plant's last state


def main(args=None) -> int:
    return run_node(Controller, args)


Controller.node_name = 'controller'
