"""``health_monitor``: estimates the servovalve's wear (radial clearance, overlap) from the
plant's ``ActuatorState`` and publishes ``HealthStatus`` and ``/diagnostics``.

Every ``update_period_s`` of state time it fits the valve model to the (XS, Q, P12) samples of
the last ``window_s`` (:class:`eha_ros.surrogates.health.InServiceEstimator`, method
``steady-fit``, or ``surrogate-fit`` with ``model`` naming a shipped 4-input surrogate) and
grades the estimate with the thresholds of ``config/health.yaml``.

During a diagnostic valve test (states with ``STATUS_VALVE_TEST``, see
:mod:`eha_ros.physics.valve_test`) it collects P12 at the end of every point's hold instead;
each time a curve (133 spool positions at one flow) is complete it publishes the wear the
diagnostic network reads from the curves of the test so far (method ``diagnostic-network``,
:class:`eha_ros.surrogates.health.ValveTestEstimator`).  The in-service window ignores test
samples.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from eha_ros.graph import LEVEL_ERROR, LEVEL_NAMES, LEVEL_OK, LEVEL_WARN
from eha_ros.msg import ActuatorState, HealthStatus
from eha_ros.physics import ParameterError, load_params
from eha_ros.physics.valve_test import MAP_POINTS
from eha_ros.surrogates.base import SurrogateError
from eha_ros.surrogates.health import (HealthThresholds, InServiceEstimator, ValveTestEstimator,
                                       classify)

from .common import (TOPIC_DIAGNOSTICS, TOPIC_HEALTH, TOPIC_STATE, advertise, declare,
                     run_node, stamp_to_ns, subscribe, validator)

_LEVEL_BYTES = {LEVEL_OK: DiagnosticStatus.OK, LEVEL_WARN: DiagnosticStatus.WARN,
                LEVEL_ERROR: DiagnosticStatus.ERROR}


class HealthMonitor(Node):
    """Wear estimation node."""

    def __init__(self, **kwargs):
        super().__init__('health_monitor', **kwargs)
        path = declare(self, 'params_file', '', 'physical parameter YAML (empty: installed)')
        limits = declare(self, 'thresholds_file', '', 'health threshold YAML (empty: the '
                         'installed config/health.yaml)')
        self.model_name = declare(self, 'model', 'steady', 'valve model fitted: steady (the '
                                  'steady-state valve) or a shipped 4-input surrogate (nn, lut)',
                                  choices=('steady', 'nn', 'lut'))
        self.window_s = declare(self, 'window_s', 1.0, 'samples of the last window_s [s] are '
                                'fitted', 0.01, 3600.0)
        self.update_s = declare(self, 'update_period_s', 0.5, 'state time between estimates '
                                '[s]', 0.001, 3600.0)
        self.settle_s = declare(self, 'settle_s', 0.05, 'state time ignored at start [s]', 0.0,
                                3600.0)
        self.params = load_params(path or None)
        self.limits = HealthThresholds.load(limits or None)
        model = None
        if self.model_name != 'steady':
            from eha_ros.surrogates.base import load_surrogate
            model = load_surrogate(self.model_name, self.params).p12
        self.estimator = InServiceEstimator(self.params, model=model)
        try:
            self.test_estimator = ValveTestEstimator(self.params)
            self.test_error = ''
        except (SurrogateError, OSError) as exc:  # in-service estimation still works
            self.test_estimator = None
            self.test_error = ' '.join(str(exc).split())
        self._warm_up()
        self.curves = {}          # flow -> {point: (xs, p12)} of the running valve test
        self.curves_done = []     # (q, xs, p12) of its complete curves
        self.in_test = False
        self.add_on_set_parameters_callback(validator(self._on_set))
        self.health_pub = advertise(self, HealthStatus, TOPIC_HEALTH)
        self.diag_pub = advertise(self, DiagnosticArray, TOPIC_DIAGNOSTICS)
        subscribe(self, ActuatorState, TOPIC_STATE, self._on_state)
        self.samples = deque()
        self.next_ns = None
        self.last = None
        self.published = 0

    def _warm_up(self):
        """Compile (or load from numba's cache) the kernels the estimates call, before the
        first state arrives: an estimate then takes milliseconds, not a compilation."""
        xs = np.linspace(-1e-4, 1e-4, 12)
        q = np.zeros(12)
        self.estimator.estimate(xs, q, self.estimator._predict(
            xs, q, self.params.overlap_supply_m, self.params.radial_clearance_m))
        if self.test_estimator is not None:
            from eha_ros.physics.maps import transient_map
            grid = self.test_estimator.model.xs_m
            self.test_estimator.estimate([(1e-5, grid, transient_map(
                grid, 1e-5, params=self.params, t_end_s=1e-5)['p12_pa'])])

    def _on_set(self, changes):
        if {'params_file', 'thresholds_file', 'model'} & set(changes):
            raise ParameterError('params_file, thresholds_file and model cannot change while '
                                 'running')
        if 'window_s' in changes:
            self.window_s = float(changes['window_s'])
        if 'update_period_s' in changes:
            self.update_s = float(changes['update_period_s'])

    def _on_state(self, msg: ActuatorState):
        t_ns = stamp_to_ns(msg.header.stamp)
        if msg.status == ActuatorState.STATUS_VALVE_TEST:
            self._on_valve_test(msg)
            return
        if self.in_test:  # the test is over: the in-service window starts afresh
            self.in_test = False
            self.next_ns = None
        if msg.status == ActuatorState.STATUS_DIVERGED or msg.sim_time_s < self.settle_s:
            return
        self.samples.append((t_ns, msg.spool_position_m, msg.load_flow_m3_s, msg.p12_pa))
        while self.samples and self.samples[0][0] < t_ns - self.window_s * 1e9:
            self.samples.popleft()
        if self.next_ns is None:
            self.next_ns = t_ns + int(self.update_s * 1e9)
        if t_ns >= self.next_ns:
            self.next_ns = t_ns + int(self.update_s * 1e9)
            self.publish_estimate(msg.header.stamp)

    def _on_valve_test(self, msg: ActuatorState):
        if not self.in_test:
            self.in_test = True
            self.curves, self.curves_done = {}, []
            self.samples.clear()
        if not msg.valve_test_point_end:
            return
        q = msg.load_flow_m3_s
        curve = self.curves.setdefault(q, {})
        curve[msg.valve_test_point] = (msg.spool_position_m, msg.p12_pa)
        n = MAP_POINTS
        if msg.valve_test_point != n - 1:
            return
        if len(curve) < n:  # points lost (realtime): the network needs the whole curve
            self.get_logger().warning(f'valve test curve at q = {q:g} m^3/s has {len(curve)} of '
                                      f'{n} points: not used')
            return
        pts = [curve[k] for k in sorted(curve)]
        self.curves_done.append((q, np.array([x for x, _ in pts]),
                                 np.array([p for _, p in pts])))
        self.publish_estimate(msg.header.stamp, valve_test=True)

    def publish_estimate(self, stamp, valve_test: bool = False):
        """Estimate from the buffered samples (or the valve test's curves) and publish
        HealthStatus and /diagnostics."""
        _, xs, q, p12 = zip(*self.samples) if self.samples else ((), (), (), ())
        out = HealthStatus()
        out.header.stamp = stamp
        out.header.frame_id = 'servovalve'
        estimator = self.test_estimator if valve_test else self.estimator
        try:
            if not valve_test:
                est = self.estimator.estimate(xs, q, p12)
            elif estimator is None:
                raise ParameterError(f'the diagnostic network is not usable: {self.test_error}')
            else:
                est = estimator.estimate(self.curves_done)
        except ValueError as exc:  # ParameterError included
            out.level = HealthStatus.LEVEL_ERROR
            out.method = ValveTestEstimator.method if valve_test else self.estimator.method
            out.message = f'no estimate: {exc}'
        else:
            level, text = classify(est, self.limits)
            out.radial_clearance_m = est.radial_clearance_m
            out.radial_clearance_std_m = est.radial_clearance_std_m
            out.overlap_m = est.overlap_m
            out.overlap_std_m = est.overlap_std_m
            out.pressure_residual_pa = est.pressure_residual_pa
            out.samples_used = est.samples_used
            out.level = level
            out.method = est.method
            out.message = text
        self.last = out
        self.health_pub.publish(out)
        arr = DiagnosticArray()
        arr.header.stamp = stamp
        st = DiagnosticStatus()
        st.level = _LEVEL_BYTES[int(out.level)]
        st.name = 'eha_ros/servovalve'
        st.message = out.message
        st.hardware_id = 'servovalve'
        st.values = [KeyValue(key=k, value=f'{v:.6g}') for k, v in (
            ('radial_clearance_m', out.radial_clearance_m),
            ('radial_clearance_std_m', out.radial_clearance_std_m),
            ('overlap_m', out.overlap_m), ('overlap_std_m', out.overlap_std_m),
            ('pressure_residual_pa', out.pressure_residual_pa))]
        st.values.append(KeyValue(key='method', value=out.method))
        arr.status = [st]
        self.diag_pub.publish(arr)
        self.published += 1
        self.get_logger().info(f'[{LEVEL_NAMES[out.level]}] {out.message}')


def main(args=None) -> int:
    return run_node(HealthMonitor, args)


HealthMonitor.node_name = 'health_monitor'
