"""``servovalve_plant``: the actuator (servovalve + jack) integrated between ticks; publishes
``ActuatorState`` every tick.

``model`` selects the fluid-dynamic block: ``hf`` (the high-fidelity chambers and metering
edges) or a surrogate shipped in ``eha_ros/surrogates/models``: the dynamic ones ``dlut``,
``dnn``, ``dga`` (metering-edge flows learned, chambers and jack physical: the recommended
in-loop surrogates) or the reference's algebraic ``lut``, ``ga``, ``nn``, ``nn2``.  Between ticks the plant takes ``1/rate_hz / dt_s`` steps of ``dt_s`` (1 us) with the
last coil-current command held.

Realtime mode: a wall-clock timer at ``rate_hz``; simulated time is locked to the wall clock:
when a timer call comes late (a busy machine) the plant catches up the ticks that fell due, up
to ``max_catch_up`` at once; a longer stall is a slip - the backlog beyond that is dropped, the
simulation resumes from where it was, and the slip is counted and logged.

Lockstep mode: the plant is the time source:
it publishes ``/clock`` and the state of tick k, and advances to tick k+1 only when the
``ServovalveCommand`` stamped with tick k arrives; if none comes within ``resend_s`` of wall
time it publishes tick k again.

Valve test (``valve_test: true``): before operating, the plant runs the diagnostic valve test of
:mod:`eha_ros.physics.valve_test` - the reference's map sweep at ``valve_test_flows_m3_s``, one
tick at a time, the jack clamped - and reports it with status ``STATUS_VALVE_TEST``; the health
monitor reads the wear from those curves.  Pre-flight check (``preflight_check: true``): then
(after the valve test, if any) the plant drives the coil open loop along
:data:`eha_ros.physics.valve_test.PREFLIGHT_PROFILE` from the actuator at rest, the jack free
and the controller's commands ignored, and reports it with status ``STATUS_PREFLIGHT``, the
tick's index in ``valve_test_point`` and ``valve_test_point_end`` on its last tick; the health
monitor reads the faults from that record.

Wear and degradation (overlap, clearance, eccentricity, Khsv, KGM, K_intas, backlash, friction,
hysteresis, offset, leakage) are parameters that can change while running; a non-physical value
is refused with the reason.
"""

from __future__ import annotations

import time

from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from eha_ros.msg import ActuatorState, ServovalveCommand
from eha_ros.physics import ParameterError, Plant, SimulationDiverged, load_params
from eha_ros.physics.params import replace
from eha_ros.physics.plant import S_P1, S_P2, S_XJ
from eha_ros.physics.valve_test import PreflightCheck, ValveTest

from eha_ros.graph import MODELS

from .common import (MODES, TOPIC_CLOCK, TOPIC_SERVOVALVE, TOPIC_STATE, TickTiming, advertise,
                     declare, declare_physics, ns_to_stamp, run_node, stamp_to_ns, subscribe,
                     validator)

#: Flows [m^3/s] of the valve test by default: three of the diagnostic grid (DB4).
DEFAULT_TEST_FLOWS_M3_S = (2.5714285714285714e-05, 4.285714285714286e-05, 6.0e-05)

#: Parameters that may change during a run (progressive degradation).
WEAR = ('overlap_supply_m', 'overlap_return_m', 'radial_clearance_m', 'eccentricity_ratio',
        'valve_degradation', 'demagnetisation', 'filter_clogging', 'feedback_backlash_m',
        'surface_backlash_m', 'jack_static_friction_n', 'jack_dynamic_friction_n',
        'spool_static_friction_n', 'spool_dynamic_friction_n', 'hysteresis_a', 'offset_a',
        'leakage_coeff_m3_s_pa', 'external_force_n')


def load_fluid(model: str, params):
    """The fluid block for ``model``: None for hf, else the shipped surrogate."""
    if model == 'hf':
        return None
    if model not in MODELS:
        raise ParameterError(f'model {model!r} must be one of {", ".join(MODELS)}')
    from eha_ros.surrogates.base import load_surrogate
    return load_surrogate(model, params)


class ServovalvePlant(Node):
    """The plant node."""

    def __init__(self, **kwargs):
        super().__init__('servovalve_plant', **kwargs)
        path = declare(self, 'params_file', '', 'physical parameter YAML (empty: the installed '
                       'config/eha_params.yaml)')
        base = load_params(path or None)
        declare_physics(self, base, WEAR)
        self.model = declare(self, 'model', 'hf', 'fluid-dynamic block', choices=MODELS)
        dt_s = declare(self, 'dt_s', 1e-6, 'plant integration step [s]', 1e-9, 1e-3)
        rate = declare(self, 'rate_hz', 1000.0, 'tick rate [Hz]', 1.0, 1e5)
        self.mode = declare(self, 'mode', 'realtime', 'timing mode', choices=MODES)
        seed = declare(self, 'seed', 0, 'seed of the torque-motor noise', 0, 2 ** 31 - 1)
        self.duration_s = declare(self, 'duration_s', 0.0, 'stop advancing after this simulated '
                                  'time [s] (0: never)', 0.0, 1e9)
        self.resend_s = declare(self, 'resend_s', 2.0, 'lockstep: re-publish the tick after '
                                'this long without its command [s]', 0.01, 60.0)
        self.start_subscribers = declare(self, 'start_subscribers', 1, 'lockstep: state '
                                         'subscribers to wait for before the first tick (the '
                                         'controller, plus recorders)', 1, 100)
        self.start_clock_subscribers = declare(
            self, 'start_clock_subscribers', 1, 'lockstep: /clock subscriptions to wait for '
            'before the first tick (the command generator, plus every sim-time node and '
            'recorder), so that none misses tick 0', 1, 100)
        valve_test = declare(self, 'valve_test', False, 'run the diagnostic valve test (map '
                             'sweep, jack clamped) before operating')
        flows = declare(self, 'valve_test_flows_m3_s', list(DEFAULT_TEST_FLOWS_M3_S),
                        'valve test: imposed load flows [m^3/s], one P12 curve each')
        preflight = declare(self, 'preflight_check', False, 'run the pre-flight check (open-'
                            'loop current steps and sines, jack free) before operating')
        self.max_catch_up = declare(self, 'max_catch_up', 50, 'realtime: most late ticks '
                                    'caught up at once; a longer stall slips', 1, 100000)
        if self.mode not in MODES:
            raise ParameterError(f'mode {self.mode!r} must be one of {", ".join(MODES)}')
        params = replace(base, **{n: self.get_parameter(n).value for n in WEAR})
        self.fluid = load_fluid(self.model, params)
        self.plant = Plant(params, dt_s=dt_s, seed=seed, fluid=self.fluid)
        Plant(params, dt_s=dt_s, seed=seed, fluid=self.fluid).advance(0.0, 1)  # JIT first
        period_ns = round(1e9 / rate)
        if period_ns % self.plant.dt_ns:
            raise ParameterError(f'the tick period {period_ns} ns must be a whole number of '
                                 f'dt_s = {dt_s:g} s')
        self.period_ns = period_ns
        self.steps_per_tick = period_ns // self.plant.dt_ns
        self.valve_test = ValveTest(flows, period_ns, dt_s) if valve_test else None
        self.test_tick = 0
        self.test_sample = None
        if self.valve_test is not None:
            self.valve_test.sample(1, params)  # JIT first
        self.preflight = (PreflightCheck(period_ns, params.current_limit_a) if preflight
                          else None)
        self.preflight_tick = 0
        self.preflight_last = -1   # self.ticks of the last pre-flight tick
        self.add_on_set_parameters_callback(validator(self._on_set))
        self.state_pub = advertise(self, ActuatorState, TOPIC_STATE)
        subscribe(self, ServovalveCommand, TOPIC_SERVOVALVE, self._on_command)
        self.current_a = 0.0
        self.done = False
        self.diverged = False
        self.ticks = 0
        self.timing = TickTiming(self, rate, self.mode == 'realtime')
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        if self.mode == 'lockstep':
            self.clock_pub = advertise(self, Clock, TOPIC_CLOCK)
            self._started = False
            self._last_pub_ns = 0
            self._watchdog = self.create_timer(0.01, self._on_watchdog, clock=steady)
        else:
            self._steady = steady
            self._t0_ns = None
            self._rt_ticks = 0
            self.slipped_ticks = 0
            self.create_timer(period_ns * 1e-9, self._on_timer, clock=steady)
        self.get_logger().info(f'model {self.model}, dt {dt_s:g} s, {self.steps_per_tick} '
                               f'steps per tick, {self.mode}')

    # parameters --------------------------------------------------------------------------
    def _on_set(self, changes):
        frozen = {'model', 'dt_s', 'rate_hz', 'mode', 'seed', 'params_file', 'valve_test',
                  'valve_test_flows_m3_s', 'preflight_check'} & set(changes)
        if frozen:
            raise ParameterError(f'{sorted(frozen)[0]} cannot change while running')
        wear = {k: v for k, v in changes.items() if k in WEAR}
        if wear:
            params = replace(self.plant.params, **wear)  # raises with the reason if bad
            if self.fluid is not None:
                self.fluid.check_params(params)
            self.plant.set_params(params)
            self.get_logger().info('parameters changed: ' + ', '.join(
                f'{k}={v:g}' for k, v in wear.items()))
        if 'duration_s' in changes:
            self.duration_s = float(changes['duration_s'])
        if 'max_catch_up' in changes:
            self.max_catch_up = int(changes['max_catch_up'])
        if 'resend_s' in changes:
            self.resend_s = float(changes['resend_s'])

    # stepping ----------------------------------------------------------------------------
    def _advance(self):
        if self.done or self.diverged:
            return False
        try:
            if self.valve_test is not None and self.test_tick < self.valve_test.n_ticks:
                self.test_tick += 1
                self.test_sample = self.valve_test.sample(self.test_tick, self.plant.params)
                self.plant.hold(self.steps_per_tick)
            elif self.preflight is not None and self.preflight_tick < self.preflight.n_ticks:
                if self.preflight_tick == 0:  # from the actuator at rest
                    self.plant.state[:] = self._rest_state()
                self.test_sample = None
                self.plant.advance(float(self.preflight.command_a[self.preflight_tick]),
                                   self.steps_per_tick)
                self.preflight_tick += 1
                self.preflight_last = self.ticks + 1
            else:
                self.test_sample = None
                self.plant.advance(self.current_a, self.steps_per_tick)
        except (SimulationDiverged, FloatingPointError) as exc:
            self.diverged = True
            self.get_logger().error(str(exc))
            return True
        self.ticks += 1
        if self.duration_s and self.plant.time_ns >= round(self.duration_s * 1e9):
            self.done = True
            self.get_logger().info(f'scenario complete at t = {self.plant.time_s:.6g} s')
        return True

    def _rest_state(self):
        from eha_ros.physics.plant import initial_state
        return initial_state(self.plant.params)

    def _state_msg(self) -> ActuatorState:
        s = self.plant.snapshot()
        p = self.plant.params
        msg = ActuatorState()
        ns_to_stamp(msg.header.stamp, self.plant.time_ns)
        msg.header.frame_id = 'jack'
        msg.jack_position_m = s['jack_position_m']
        msg.jack_position_measured_m = s['jack_position_measured_m']
        msg.jack_velocity_m_s = s['jack_velocity_m_s']
        msg.spool_position_m = s['spool_position_m']
        msg.flapper_position_m = s['flapper_position_m']
        msg.p1_pa = s['p1_pa']
        msg.p2_pa = s['p2_pa']
        msg.p12_pa = s['p12_pa']
        msg.load_flow_m3_s = s['load_flow_m3_s']
        msg.coil_current_a = s['coil_current_a']
        msg.torque_motor_force_n = s['torque_motor_force_n']
        msg.sim_time_s = self.plant.time_s
        msg.tick = self.plant.steps
        msg.model = self.model
        st = self.plant.state
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
        preflight = (self.preflight is not None and t is None
                     and self.preflight_tick > 0 and self.preflight_last == self.ticks)
        if preflight:
            msg.valve_test_point = self.preflight_tick - 1
            msg.valve_test_point_end = self.preflight_tick == self.preflight.n_ticks
        if self.diverged:
            msg.status = ActuatorState.STATUS_DIVERGED
        elif t is not None:
            msg.status = ActuatorState.STATUS_VALVE_TEST
        elif preflight:
            msg.status = ActuatorState.STATUS_PREFLIGHT
        elif abs(st[S_XJ]) >= p.jack_stroke_m:
            msg.status = ActuatorState.STATUS_END_STOP
        elif min(st[S_P1], st[S_P2]) <= p.vapour_pressure_pa:
            msg.status = ActuatorState.STATUS_CAVITATION
        else:
            msg.status = ActuatorState.STATUS_OK
        return msg

    def _publish_tick(self):
        if self.mode == 'lockstep':
            clock = Clock()
            ns_to_stamp(clock.clock, self.plant.time_ns)
            self.clock_pub.publish(clock)
        self.state_pub.publish(self._state_msg())
        self._last_pub_ns = RosClock(clock_type=ClockType.STEADY_TIME).now().nanoseconds

    # realtime ----------------------------------------------------------------------------
    def _now_ns(self) -> int:
        """Wall-clock time [ns] that realtime ticks fall due on (the steady clock)."""
        return self._steady.now().nanoseconds

    def _on_timer(self):
        now = self._now_ns()
        began = time.monotonic_ns()
        try:
            self._catch_up(now)
        finally:
            self.timing.busy(began)

    def _catch_up(self, now: int):
        if self._t0_ns is None:
            self._t0_ns = now - self.period_ns  # the first tick falls due now
        behind = (now - self._t0_ns) // self.period_ns - self._rt_ticks
        if behind > self.max_catch_up:
            slip = behind - self.max_catch_up
            self.slipped_ticks += slip
            self.timing.slip(slip)
            self._t0_ns += slip * self.period_ns
            behind = self.max_catch_up
            self.get_logger().warning(
                f'{slip} ticks behind the wall clock: slipped ({self.slipped_ticks} in all)',
                throttle_duration_sec=1.0)
        for _ in range(behind):
            self._rt_ticks += 1
            if not self._advance():
                return
            self.state_pub.publish(self._state_msg())
            # tick k fell due at t0 + k periods
            self.timing.tick(now, now - (self._t0_ns + self._rt_ticks * self.period_ns))

    def _on_command(self, msg: ServovalveCommand):
        if self.mode == 'realtime':
            self.current_a = msg.current_command_a
            return
        if stamp_to_ns(msg.header.stamp) != self.plant.time_ns:
            return  # an answer to a tick already advanced (a re-sent tick)
        self.current_a = msg.current_command_a
        began = time.monotonic_ns()
        if self._advance():
            self._publish_tick()
            self.timing.tick(began)
        self.timing.busy(began)

    # lockstep ----------------------------------------------------------------------------
    def _ready(self) -> bool:
        """Everyone the loop needs has matched: a state reader (controller) answering with
        servovalve commands, clock readers (command generator, sim-time nodes, recorders)."""
        return (self.state_pub.get_subscription_count() >= self.start_subscribers
                and self.clock_pub.get_subscription_count() >= self.start_clock_subscribers
                and self.count_publishers(TOPIC_SERVOVALVE) >= 1)

    def _on_watchdog(self):
        now = RosClock(clock_type=ClockType.STEADY_TIME).now().nanoseconds
        if not self._started:
            if self._ready():
                self._started = True
                self._publish_tick()
            return
        if self.done or self.diverged:
            return
        if now - self._last_pub_ns > self.resend_s * 1e9:
            self.get_logger().warning(f'no command for tick t = {self.plant.time_s:.6g} s: '
                                   're-publishing it')
            self._publish_tick()


def main(args=None) -> int:
    return run_node(ServovalvePlant, args)


ServovalvePlant.node_name = 'servovalve_plant'
