"""``command_generator``: publishes the jack position command (``ActuatorCommand``).

Realtime mode: a loop in a thread of its own (:class:`eha_ros.nodes.common.NodeLoop`) wakes
at absolute deadlines from the graph's common start (the start-up handshake,
:mod:`eha_ros.nodes.handshake`): sample k, the command of time k/rate_hz, falls due at the
start plus k periods, as the plant's state of that time, and is stamped with that wall-clock
time; sample 0 is due at the start itself.  A late wake publishes every sample that fell due
(at most ``max_catch_up``; a longer stall slips, counted and logged), so the command sequence
does not depend on the machine's load.
Lockstep mode: one command per ``/clock`` tick published by the plant, stamped with that tick
and evaluated at exactly its time.

Parameters: ``scenario`` (a name from ``config/scenarios.yaml``; empty: the waveform below),
``waveform``, ``amplitude_m``, ``frequency_rad_s``, ``start_s``, ``ramp_time_s``, ``f0_hz``,
``f1_hz``, ``sweep_time_s``, ``rate_hz``, ``mode``.
"""

from __future__ import annotations

import time

from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from eha_ros.msg import ActuatorCommand
from eha_ros.physics import ParameterError, Scenario, load_scenarios
from eha_ros.physics.commands import WAVEFORMS

from eha_ros.graph import TOPIC_DIAGNOSTICS

from .common import (advertise, apply_realtime_settings, check_choice, declare, declare_loop,
                     declare_realtime, locked, MODES, node_loop, ns_to_stamp, run_node,
                     stamp_to_ns, subscribe, take_changes, TOPIC_CLOCK, TOPIC_COMMAND, validator)
from .handshake import Handshake
from .timing import begin_timing, TickTiming

#: The waveform's parameters and their descriptions.
_WAVE_PARAMS = {'amplitude_m': 'amplitude [m]',
                'frequency_rad_s': 'sine angular frequency [rad/s]',
                'start_s': 'start time [s]', 'ramp_time_s': 'ramp time [s]',
                'f0_hz': 'chirp start frequency [Hz]', 'f1_hz': 'chirp end frequency [Hz]',
                'sweep_time_s': 'chirp sweep time [s]'}


class CommandGenerator(Node):
    """Publishes ``ActuatorCommand`` at the fixed rate or on every lockstep tick."""

    def __init__(self, **kwargs):
        init_ns = time.monotonic_ns()
        super().__init__('command_generator', **kwargs)
        self._scenarios = load_scenarios()
        declare(self, 'scenario', 'step_0p1', 'named scenario of config/scenarios.yaml; empty: '
                'use the waveform parameters', choices=sorted(self._scenarios) + [''])
        declare(self, 'waveform', 'step', 'waveform when scenario is empty', choices=WAVEFORMS)
        for name, text in _WAVE_PARAMS.items():
            declare(self, name, 0.0, text)
        rate = declare(self, 'rate_hz', 1000.0, 'publication rate in realtime mode [Hz]', 1.0,
                       1e5)
        self.mode = declare(self, 'mode', 'realtime', 'timing mode', choices=MODES)
        self.max_catch_up = declare(self, 'max_catch_up', 50, 'realtime: most late samples '
                                    'published at once; a longer stall slips', 1, 100000)
        self.duration_s = declare(self, 'duration_s', 0.0, "the run's end [s]: the sample of "
                                  'this time sends the final timing report (0: the '
                                  "scenario's duration; a custom waveform's is 1e9 s)", 0.0, 1e9)
        realtime = declare_realtime(self)
        loop_options = declare_loop(self)
        self.scenario = self._build()
        self.scenario.value(0.0)  # compile the command kernel now, not in the first tick
        check_choice('mode', self.mode, MODES)
        self.add_on_set_parameters_callback(validator(self._on_set))
        self.pub = advertise(self, ActuatorCommand, TOPIC_COMMAND)
        self.published = 0
        self.timing = TickTiming(self, rate, self.mode == 'realtime')
        self.period_ns = round(1e9 / rate)
        self.handshake = Handshake(self, on_start=self._on_start)
        self.handshake.watch(self.pub, TOPIC_COMMAND)
        self.handshake.watch(self.timing.pub, TOPIC_DIAGNOSTICS)
        if self.mode == 'lockstep':
            clock_sub = subscribe(self, Clock, TOPIC_CLOCK, self._on_clock)
            self.handshake.watch(clock_sub, TOPIC_CLOCK)
        self._t0_ns = None
        self.fatal = None
        # realtime: the samples in a thread of their own
        self.rt_loop = node_loop(self, self.mode == 'realtime', self._on_loop_wake, realtime,
                                 loop_options, 'a lockstep command generator')
        self._warm_up_s = (time.monotonic_ns() - init_ns) * 1e-9
        apply_realtime_settings(self, realtime, self.rt_loop)

    def _on_start(self, start_ns: int, mode: str) -> None:
        """The graph starts: realtime commands are timed from the common start."""
        start_mono = self.handshake.start_monotonic_ns()
        begin_timing(self, self.timing, start_mono, self._warm_up_s)
        if self.mode == 'realtime':
            self._t0_ns = start_ns
            self._anchor(start_mono)
            self.rt_loop.start(start_mono, self.timing.gc)  # sample 0 at the start itself

    def _anchor(self, start_mono_ns: int) -> None:
        """Realtime: sample k falls due at ``start_mono_ns`` plus k periods."""
        self._rt_anchor = start_mono_ns
        self._rt_next = 0
        self.slipped_ticks = 0

    def _build(self, changes=None) -> Scenario:
        """The scenario the node's parameters (with ``changes`` applied) name or describe."""
        d = {n: self.get_parameter(n).value for n in ('scenario', 'waveform', *_WAVE_PARAMS)}
        d.update(changes or {})
        if d['scenario']:
            if d['scenario'] not in self._scenarios:
                raise ParameterError(f'unknown scenario {d["scenario"]!r} (known: '
                                     f'{", ".join(sorted(self._scenarios))})')
            return self._scenarios[d['scenario']]
        return Scenario(name='custom', waveform=d['waveform'], duration_s=1e9,
                        **{k: float(d[k]) for k in _WAVE_PARAMS})

    @locked
    def _on_set(self, changes):
        if 'mode' in changes:
            check_choice('mode', changes['mode'], MODES)
            raise ParameterError('mode cannot change while running')
        if 'rate_hz' in changes and changes['rate_hz'] != self.get_parameter('rate_hz').value:
            raise ParameterError('rate_hz cannot change while running')
        take_changes(self, changes, max_catch_up=int, duration_s=float)
        if set(changes) & (set(_WAVE_PARAMS) | {'scenario', 'waveform'}):
            self.scenario = self._build(changes)

    def _publish(self, t_ns: int, stamp=None, stamp_ns=None) -> int:
        """The command of scenario time ``t_ns``, stamped ``stamp`` (a message) or
        ``stamp_ns`` (default: ``t_ns``); returns when its value was computed
        (``time.monotonic_ns``)."""
        msg = ActuatorCommand()
        if stamp is not None:
            msg.header.stamp = stamp
        else:
            ns_to_stamp(msg.header.stamp, t_ns if stamp_ns is None else stamp_ns)
        msg.header.frame_id = 'jack'
        msg.position_setpoint_m = float(self.scenario.value(t_ns * 1e-9))
        computed = time.monotonic_ns()
        self.pub.publish(msg)
        self.published += 1
        return computed

    def _on_clock(self, msg: Clock):
        began = time.monotonic_ns()
        t_ns = stamp_to_ns(msg.clock)
        self._publish(t_ns, stamp=msg.clock)
        self.timing.tick(began)
        self._end_timing(t_ns, began)
        self.timing.busy(began)

    def _on_loop_wake(self, now: int):
        """The sample loop woke (its thread, the lock held): publish every sample due by
        ``now``."""
        began = time.monotonic_ns()
        due = (now - self._rt_anchor) // self.period_ns
        behind = due - self._rt_next + 1
        if behind > self.max_catch_up:
            slip = behind - self.max_catch_up
            self.slipped_ticks += slip
            self.timing.slip(slip)
            self._rt_next += slip
            behind = self.max_catch_up
            self.get_logger().warning(f'{slip} samples behind the wall clock: slipped '
                                      f'({self.slipped_ticks} in all)',
                                      throttle_duration_sec=1.0)
        for _ in range(max(0, behind)):
            k = self._rt_next
            self._rt_next += 1
            computed = self._publish(k * self.period_ns,
                                     stamp_ns=self._t0_ns + k * self.period_ns)
            due = self._rt_anchor + k * self.period_ns
            self.rt_loop.record(k, due, computed, time.monotonic_ns())
            self.timing.tick(now, now - due)
            # the final report right after the run's last sample, before a later one of the
            # same catch-up counts in it
            self._end_timing(k * self.period_ns, began)
        self.timing.busy(began)

    def _end_timing(self, t_ns: int, began: int) -> None:
        """After the sample of scenario time ``t_ns`` (its callback began at ``began``): the
        final timing report once it reaches the run's end (:meth:`TickTiming.publish_final`)."""
        if not self.timing.ended and t_ns >= round((self.duration_s or self.scenario.duration_s)
                                                   * 1e9):
            self.timing.busy(began)
            self.timing.publish_final()

    def close(self) -> None:
        """Stop the sample loop (and write its timing trace)."""
        if self.rt_loop is not None:
            self.rt_loop.close()


def main(args=None) -> int:
    return run_node(CommandGenerator, args)


CommandGenerator.node_name = 'command_generator'
