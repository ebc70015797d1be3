"""``controller``: PID on the jack position error, publishes the coil current command
(``ServovalveCommand``).

Realtime mode: each plant state clocks one control step (``trigger: state``, the default: the
sensor sample triggers the digital controller, so it runs at the plant's rate and no
timer of its own competes for the processor), or a wall-clock timer at ``rate_hz`` does
(``trigger: timer``); either uses the latest command and the latest sensor reading.

Lockstep mode: for each plant tick it waits for both the state and the command of
that tick (matching stamps), then answers with the current for that tick; a repeated tick
(the plant re-sending after a lost message) gets the same answer again.

The arithmetic is :class:`eha_ros.physics.plant.PositionController`, the same as the
physics-only closed loop.  Parameters: ``kp_a_m``, ``ki_a_m_s``, ``kd_a_s_m``,
``current_limit_a`` (defaults from ``params_file``), ``rate_hz``, ``mode``, ``trigger``,
``params_file``.
"""

from __future__ import annotations

import time

from rclpy.node import Node

from eha_ros.msg import ActuatorCommand, ActuatorState, ServovalveCommand
from eha_ros.physics import ParameterError, load_params
from eha_ros.physics.params import replace
from eha_ros.physics.plant import PositionController

from .common import (MODES, TOPIC_COMMAND, TOPIC_SERVOVALVE, TOPIC_STATE, TickTiming, advertise,
                     declare, declare_physics, run_node, stamp_to_ns, subscribe, validator)

GAINS = ('kp_a_m', 'ki_a_m_s', 'kd_a_s_m', 'current_limit_a')


#: What clocks the realtime controller.
TRIGGERS = ('state', 'timer')


class Controller(Node):
    """Position controller node."""

    def __init__(self, **kwargs):
        super().__init__('controller', **kwargs)
        path = declare(self, 'params_file', '', 'physical parameter YAML (empty: the installed '
                       'config/eha_params.yaml)')
        self.base = load_params(path or None)
        declare_physics(self, self.base, GAINS)
        declare(self, 'rate_hz', 1000.0, 'control rate [Hz]', 1.0, 1e5)
        declare(self, 'mode', 'realtime', 'timing mode', choices=MODES)
        self.trigger = declare(self, 'trigger', 'state', 'realtime: a control step per plant '
                               'state, or per tick of its own timer', choices=TRIGGERS)
        if self.trigger not in TRIGGERS:
            raise ParameterError(f'trigger {self.trigger!r} must be one of {", ".join(TRIGGERS)}')
        self.mode = self.get_parameter('mode').value
        if self.mode not in MODES:
            raise ParameterError(f'mode {self.mode!r} must be one of {", ".join(MODES)}')
        self.period_s = 1.0 / self.get_parameter('rate_hz').value
        self.params = self._params({})
        self.pid = PositionController(self.params, self.period_s)
        PositionController(self.params, self.period_s).update(0.0, 0.0)  # JIT before tick 0
        self.add_on_set_parameters_callback(validator(self._on_set))
        self.pub = advertise(self, ServovalveCommand, TOPIC_SERVOVALVE)
        subscribe(self, ActuatorCommand, TOPIC_COMMAND, self._on_command)
        subscribe(self, ActuatorState, TOPIC_STATE, self._on_state)
        self.command_m = 0.0
        self.measured_m = 0.0
        self._commands = {}  # lockstep: stamp ns -> setpoint, for ticks not yet answered
        self._state_ns = None  # lockstep: tick waiting for its command
        self._answered = (None, 0.0)  # lockstep: last tick answered and its current
        self.published = 0
        self.timing = TickTiming(self, 1.0 / self.period_s, self.mode == 'realtime')
        if self.mode == 'realtime' and self.trigger == 'timer':
            self.create_timer(self.period_s, self._on_own_timer)

    def _params(self, changes):
        values = {n: self.get_parameter(n).value for n in GAINS}
        values.update({k: v for k, v in changes.items() if k in GAINS})
        return replace(self.base, **values)

    def _on_set(self, changes):
        if {'mode', 'rate_hz', 'params_file', 'trigger'} & set(changes):
            raise ParameterError('mode, rate_hz, trigger and params_file cannot change while '
                                 'running')
        if set(changes) & set(GAINS):
            self.params = self._params(changes)
            self.pid.params = self.params

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
