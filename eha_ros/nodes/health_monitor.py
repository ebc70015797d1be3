"""``health_monitor``: the servovalve's health from the plant's ``ActuatorState``, published
as ``HealthStatus`` on ``/eha/health`` and as ``/diagnostics``.

The logic is :class:`eha_ros.health.monitor.MonitorCore`, shared with ``eha-diagnose``:

* in service, every ``update_period_s`` of state time, the wear (radial clearance, overlap)
  from the (XS, Q, P12) samples of the last ``window_s`` - a posterior over the steady-state
  valve table whose deviation says what the motion supports;
* during a diagnostic valve test (``STATUS_VALVE_TEST``), the wear from each completed curve
  by the diagnostic network;
* at the end of a pre-flight check (``STATUS_PREFLIGHT``), demagnetisation, filter clogging,
  spool and jack friction and current offset by the pre-flight network.

Estimates run on a worker thread: the subscription callback only buffers states and hands
each estimate that falls due (with a copy of its inputs) to the worker, so a fit never delays
the 1 kHz states.  An estimate still waiting when the next one falls due is dropped and
counted (``estimates_dropped``).  What is published depends only on the states, not on the
timing: in lockstep a recording's ``/eha/health`` equals ``eha-diagnose``'s replay of its
``/eha/state`` bit for bit.

``/diagnostics``: one ``DiagnosticStatus`` per monitored parameter (names
``health_monitor: <parameter>``, ``hardware_id`` from the parameter of that name), its level
graded with ``config/health.yaml`` and the reason as message, key-values ``value``, ``std``,
``unit``, ``method``, ``stamp``; plus ``health_monitor: estimate``, the latest estimate as a
whole.  Parameters not estimated yet are STALE ("not estimated yet").  When no state has
arrived for ``stale_after_s`` of wall time every status goes STALE.
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node

from eha_ros.graph import LEVEL_CANNOT_ASSESS, LEVEL_ERROR, LEVEL_NAMES, LEVEL_OK, LEVEL_WARN
from eha_ros.msg import ActuatorState, HealthStatus
from eha_ros.physics import ParameterError, load_params
from eha_ros.health.posterior import InServiceEstimator
from eha_ros.health.thresholds import HealthThresholds
from eha_ros.health.monitor import (ITEM_UNITS, ITEMS, SETTLE_S, UPDATE_PERIOD_S, WINDOW_S,
                                    MonitorCore)

from .common import (advertise, apply_realtime_settings, declare, declare_realtime,
                     ns_to_stamp, run_node, stamp_to_ns, subscribe, take_changes,
                     TOPIC_DIAGNOSTICS, TOPIC_HEALTH, TOPIC_STATE, validator)
from .handshake import Handshake

#: CANNOT_ASSESS is a WARN on /diagnostics (a maintainer must look), with its reason.
_LEVEL_BYTES = {LEVEL_OK: DiagnosticStatus.OK, LEVEL_WARN: DiagnosticStatus.WARN,
                LEVEL_ERROR: DiagnosticStatus.ERROR, LEVEL_CANNOT_ASSESS: DiagnosticStatus.WARN}
#: Prefix of this node's DiagnosticStatus names.
STATUS_PREFIX = 'health_monitor: '


def health_message(report, core: MonitorCore) -> HealthStatus:
    """The ``HealthStatus`` of a report (every monitored parameter's last estimate)."""
    out = HealthStatus()
    ns_to_stamp(out.header.stamp, report.stamp_ns)
    out.header.frame_id = 'servovalve'
    out.radial_clearance_m = float(report.radial_clearance_m)
    out.radial_clearance_std_m = float(report.radial_clearance_std_m)
    out.overlap_m = float(report.overlap_m)
    out.overlap_std_m = float(report.overlap_std_m)
    out.pressure_residual_pa = float(report.pressure_residual_pa)
    out.samples_used = int(report.samples_used)
    out.level = int(report.level)
    out.method = report.method
    out.message = report.message
    items = [core.items.get(name) for name in ITEMS]
    out.parameter_names = list(ITEMS)
    out.parameter_values = [float(item.value) if item else math.nan for item in items]
    out.parameter_stds = [float(item.std) if item else math.nan for item in items]
    out.parameter_levels = [int(item.level) if item else 0 for item in items]
    return out


def _kv(key, value) -> KeyValue:
    return KeyValue(key=key, value=value if isinstance(value, str) else f'{value:.6g}')


class HealthMonitor(Node):
    """Health monitoring node."""

    def __init__(self, **kwargs):
        super().__init__('health_monitor', **kwargs)
        path = declare(self, 'params_file', '', 'physical parameter YAML (empty: installed)')
        limits = declare(self, 'thresholds_file', '', 'health threshold YAML (empty: the '
                         'installed config/health.yaml)')
        self.model_name = declare(self, 'model', 'steady', 'valve model fitted in service: '
                                  'steady (the steady-state valve table) or a shipped 4-input '
                                  'surrogate (nn, lut)', choices=('steady', 'nn', 'lut'))
        window_s = declare(self, 'window_s', WINDOW_S, 'samples of the last window_s [s] are '
                           'fitted', 0.01, 3600.0)
        update_period_s = declare(self, 'update_period_s', UPDATE_PERIOD_S, 'state time '
                                  'between estimates [s]', 0.001, 3600.0)
        settle_s = declare(self, 'settle_s', SETTLE_S, 'state time ignored at start [s]', 0.0,
                           3600.0)
        self.hardware_id = declare(self, 'hardware_id', 'eha/servovalve', 'hardware_id of the '
                                   'DiagnosticStatus messages (the monitored unit)')
        realtime = declare_realtime(self)
        self.params = load_params(path or None)
        self.limits = HealthThresholds.load(limits or None)
        stale = declare(self, 'stale_after_s', float(self.limits.stale_after_s), 'wall time '
                        'without states after which every diagnostic goes STALE [s]', 0.01,
                        3600.0)
        self.stale_after_s = stale
        model = None
        if self.model_name != 'steady':
            from eha_ros.surrogates.registry import load_surrogate
            model = load_surrogate(self.model_name, self.params).p12
        self.core = MonitorCore(self.params, self.limits, window_s, update_period_s, settle_s,
                                in_service=InServiceEstimator(self.params, model=model,
                                                              limits=self.limits))
        self._warm_up()
        self.add_on_set_parameters_callback(validator(self._on_set))
        self.health_pub = advertise(self, HealthStatus, TOPIC_HEALTH)
        self.diag_pub = advertise(self, DiagnosticArray, TOPIC_DIAGNOSTICS)
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix='health_fit')
        self._pending = 0
        # in lockstep (sim time) every estimate is made, whatever it waits: the published
        # data must not depend on timing; in realtime a late in-service fit is dropped
        self._may_drop = not self.get_parameter('use_sim_time').value
        self._lock = threading.Lock()
        self.last = None
        self.published = 0
        self.dropped = 0
        self._last_state_wall = None
        self._stale = False
        state_sub = subscribe(self, ActuatorState, TOPIC_STATE, self._on_state)
        self.handshake = Handshake(self)
        for entity, topic in ((state_sub, TOPIC_STATE), (self.health_pub, TOPIC_HEALTH),
                              (self.diag_pub, TOPIC_DIAGNOSTICS)):
            self.handshake.watch(entity, topic)
        self.create_timer(0.5, self._check_stale,
                          clock=RosClock(clock_type=ClockType.STEADY_TIME))
        apply_realtime_settings(self, realtime)

    def _warm_up(self):
        """Compile (or load from numba's cache) what the estimates call before the first
        state arrives: an estimate then takes milliseconds, not a compilation."""
        import numpy as np
        if self.core.valve_test is not None:
            from eha_ros.physics.maps import transient_map
            grid = self.core.valve_test.model.xs_m
            self.core.valve_test.estimate([(1e-5, grid, transient_map(
                grid, 1e-5, params=self.params, t_end_s=1e-5)['p12_pa'])])
        if self.core.in_service.table is None:
            xs = np.linspace(-1e-5, 1e-5, 12)
            self.core.in_service.estimate(xs, np.zeros(12), np.zeros(12))

    def _on_set(self, changes):
        frozen = {'params_file', 'thresholds_file', 'model', 'thread_priority', 'cpu_affinity',
                  'lock_memory'} & set(changes)
        if frozen:
            raise ParameterError(f'{sorted(frozen)[0]} cannot change while running')
        take_changes(self.core, changes, window_s=float, update_period_s=float)
        take_changes(self, changes, stale_after_s=float, hardware_id=str)

    def _on_state(self, msg: ActuatorState):
        self._last_state_wall = time.monotonic()
        self._stale = False
        for job in self.core.on_state(stamp_to_ns(msg.header.stamp), msg):
            with self._lock:
                if self._may_drop and job.kind == 'in-service' and self._pending > 0:
                    self.dropped += 1   # the worker is still on the previous one
                    continue
                self._pending += 1
            self.worker.submit(self._run, job)

    def _run(self, job):
        try:
            report = job.run()
            self.publish_report(report)
        except Exception as exc:  # never let the worker die silently
            self.get_logger().error(f'estimate failed: {type(exc).__name__}: {exc}')
        finally:
            with self._lock:
                self._pending -= 1

    def publish_report(self, report):
        """Publish HealthStatus and /diagnostics for one report."""
        out = health_message(report, self.core)
        self.last = out
        self.health_pub.publish(out)
        self.diag_pub.publish(self._diagnostics(out, report.stamp_ns))
        self.published += 1
        self.get_logger().info(f'[{LEVEL_NAMES[out.level]}] {out.method}: {out.message}')

    def _diagnostics(self, out: HealthStatus, stamp_ns: int, stale_reason: str = ''
                     ) -> DiagnosticArray:
        arr = DiagnosticArray()
        ns_to_stamp(arr.header.stamp, stamp_ns)
        summary = DiagnosticStatus(name=STATUS_PREFIX + 'estimate',
                                   hardware_id=self.hardware_id)
        if out is None:
            summary.level, summary.message = DiagnosticStatus.STALE, 'no estimate yet'
        else:
            summary.level = _LEVEL_BYTES[int(out.level)]
            summary.message = out.message
            summary.values = [_kv('method', out.method), _kv('samples_used', out.samples_used),
                              _kv('pressure_residual_pa', out.pressure_residual_pa),
                              _kv('stamp_ns', str(stamp_ns))]
        statuses = [summary]
        for name in ITEMS:
            item = self.core.items.get(name)
            st = DiagnosticStatus(name=STATUS_PREFIX + name, hardware_id=self.hardware_id)
            if item is None:
                st.level = DiagnosticStatus.STALE
                st.message = ('not estimated yet' + (
                    ' (needs a pre-flight check: scenario preflight_check or maintenance_test)'
                    if name not in ('radial_clearance_m', 'overlap_supply_m') else ''))
            else:
                st.level = _LEVEL_BYTES[int(item.level)]
                st.message = item.message
                st.values = [_kv('value', item.value), _kv('std', item.std),
                             _kv('unit', ITEM_UNITS[name]), _kv('method', item.method),
                             _kv('stamp_ns', str(item.stamp_ns))]
            statuses.append(st)
        if stale_reason:
            for st in statuses:
                st.level = DiagnosticStatus.STALE
                st.message = f'{stale_reason}; last: {st.message}'
        arr.status = statuses
        return arr

    def _check_stale(self):
        if self._last_state_wall is None and not self.handshake.started:
            return  # before the graph's start there is nothing to be stale about
        if self._last_state_wall is None:
            silent = True
            reason = 'no actuator state received yet'
        else:
            gap = time.monotonic() - self._last_state_wall
            silent = gap > self.stale_after_s
            reason = f'no actuator state for {gap:.1f} s'
        if not silent or self._stale:
            return
        self._stale = self._last_state_wall is not None  # once per silence
        stamp = self.get_clock().now().nanoseconds
        self.diag_pub.publish(self._diagnostics(self.last, stamp, reason))

    def close(self):
        self.worker.shutdown(wait=True)


def main(args=None) -> int:
    return run_node(HealthMonitor, args)


HealthMonitor.node_name = 'health_monitor'
