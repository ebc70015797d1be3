"""``controller``: PID on the jack position error, publishes the coil current command
(``ServovalveCommand``).

Realtime mode: each plant state clocks one control step (``trigger: state``, the default: the
sensor sample triggers the digital controller, so it runs at the plant's rate and no
timer of its own competes for the processor), or a wall-clock timer at ``rate_hz`` does
(``trigger: timer``); either uses the latest command and the latest sensor reading.

Lockstep mode: for each plant tick it waits for both the state and the command of
that tick (matching stamps), then answers with the current for that tick; a repeated tick
(the plant re-sending after a lost message) gets the same answer again.

``events``: gain changes on the simulation clock (``'T:kp_a_m=value'``), each applied at the
first tick whose time is at least T, before that tick's control update, and published on
``/eha/events``; live gain sets are published there too.

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
from eha_ros.physics.events import CONTROLLER_RUNTIME, EventSchedule, parse_event
from eha_ros.physics.params import replace
from eha_ros.physics.plant import PositionController

from .common import (advertise, apply_realtime_settings, at_start, begin_timing, declare,
                     declare_physics, declare_realtime, EventChannel, MODES, run_node,
                     stamp_to_ns, subscribe, TickTiming, TOPIC_COMMAND, TOPIC_SERVOVALVE,
                     TOPIC_STATE, validator)
from .handshake import Handshake

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
        declare(self, 'mode', 'realtime', 'timing mode', choices=MODES)
        self.trigger = declare(self, 'trigger', 'state', 'realtime: a control step per plant '
                               'state, or per tick of its own timer', choices=TRIGGERS)
        events = declare(self, 'events', [''], "gain changes on the simulation clock: "
                         "'T:name=value[,name=value]' entries, each applied at the first tick "
                         "whose time is at least T s (empty entries are ignored)")
        realtime = declare_realtime(self)
        if self.trigger not in TRIGGERS:
            raise ParameterError(f'trigger {self.trigger!r} must be one of {", ".join(TRIGGERS)}')
        self.mode = self.get_parameter('mode').value
        if self.mode not in MODES:
            raise ParameterError(f'mode {self.mode!r} must be one of {", ".join(MODES)}')
        self.period_s = 1.0 / self.get_parameter('rate_hz').value
        self.params = self._params({})
        self.period_ns = round(self.period_s * 1e9)
        self.schedule = EventSchedule([parse_event(e) for e in events if e.strip()],
                                      allowed=GAINS, period_ns=self.period_ns)
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
        self.timing = TickTiming(self, 1.0 / self.period_s, self.mode == 'realtime')
        self.handshake = Handshake(self, on_start=self._on_start)
        for entity, topic in ((self.pub, TOPIC_SERVOVALVE), (command_sub, TOPIC_COMMAND),
                              (state_sub, TOPIC_STATE), (self.timing.pub, TOPIC_DIAGNOSTICS)):
            self.handshake.watch(entity, topic)
        self._warm_up_s = (time.monotonic_ns() - init_ns) * 1e-9
        apply_realtime_settings(self, realtime)

    def _on_start(self, start_ns: int, mode: str) -> None:
        start_mono = self.handshake.start_monotonic_ns()
        begin_timing(self, self.timing, start_mono, self._warm_up_s)
        if self.mode == 'realtime' and self.trigger == 'timer':
            at_start(self, start_mono,
                     lambda: self.create_timer(self.period_s, self._on_own_timer))

    def _params(self, changes):
        values = {n: self.get_parameter(n).value for n in GAINS}
        values.update({k: v for k, v in changes.items() if k in GAINS})
        return replace(self.base, **values)

    def _on_set(self, changes):
        frozen = {'mode', 'rate_hz', 'params_file', 'trigger', 'events', 'thread_priority',
                  'cpu_affinity', 'lock_memory'} & set(changes)
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
            self.params = replace(self.params, **changes)
            self.pid.params = self.params
            self.events.publish(t_ns, 'schedule', ev.t_s, changes)
            self.events.mirror(changes)

    def _send(self, stamp, current_a):
        msg = ServovalveCommand()
        msg.header.stamp = stamp
        msg.header.frame_id = 'jack'
        msg.current_command_a = float(current_a)
        self.pub.publish(msg)
        self.published += 1

    # realtime -------------------------------------------------------------------------------
    def _on_timer(self):
        current = self.pid.update(self.command_m, self.measured_m)
        self._send(self.get_clock().now().to_msg(), current)

    def _on_own_timer(self):
        began = time.monotonic_ns()
        self.timing.on_schedule(began)
        self._on_timer()
        self.timing.busy(began)

    # both modes ----------------------------------------------------------------------------
    def _on_command(self, msg: ActuatorCommand):
        self.command_m = msg.position_setpoint_m
        if self.mode == 'lockstep':
            t_ns = stamp_to_ns(msg.header.stamp)
            self._commands[t_ns] = (msg.position_setpoint_m, msg.header.stamp)
            self._try_answer()

    def _on_state(self, msg: ActuatorState):
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
            return
        if self.mode == 'lockstep':
            t_ns = stamp_to_ns(msg.header.stamp)
            if t_ns == self._answered[0]:
                self._send(msg.header.stamp, self._answered[1])  # the plant asks again
                return
            self._state_ns = t_ns
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


def main(args=None) -> int:
    return run_node(Controller, args)


Controller.node_name = 'controller'
