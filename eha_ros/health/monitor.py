"""The health monitor's logic without ROS: the same code runs live (``health_monitor``) and
offline (``eha-diagnose``), so both give the same estimates from the same states, bit for bit.

:class:`MonitorCore` takes the plant's states one by one (:meth:`MonitorCore.on_state`) and
returns the estimates that fall due as :class:`Job` objects; running a job
(:meth:`Job.run`) gives a :class:`HealthReport`.  A job holds copies of its inputs, so the
node can run it on a worker thread while states keep arriving.

Three kinds of estimate:

* ``in-service``: every ``update_period_s`` of state time, the valve model fitted to the
  (XS, Q, P12) samples of the last ``window_s`` (:class:`.posterior.InServiceEstimator`):
  radial clearance and overlap;
* ``valve-test``: each time a valve-test curve completes, on the curves so far: for the
  reference's procedure the diagnostic network (:class:`.valve_test.ValveTestEstimator`):
  clearance and overlap; for the settled procedure the valve fit at the measured test
  conditions (:class:`.valve_fit.ValveFitEstimator`): clearance, overlap, Khsv and the
  jack's piston leakage;
* ``preflight``: at the end of a pre-flight check, the fault network
  (:mod:`.preflight`) on its record and measured conditions: demagnetisation, filter
  clogging, spool and jack friction, current offset.

The test conditions are the mean of the bench's readings over the test's states (supply and
return pressure, fluid temperature); where the states carry none (NaN), nominal conditions are
assumed, the estimate says so and its deviations widen.  An estimate whose model does not
explain the test (its ``mismatch``) gives items of level ``CANNOT_ASSESS`` with the reason.

Every report carries one :class:`Item` per monitored parameter, under the plant's parameter
names (:data:`ITEMS`), with value, standard deviation, level and reason; parameters a
report does not estimate keep the last estimate made (or none).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np

from eha_ros.graph import (LEVEL_CANNOT_ASSESS, LEVEL_NAMES, STATUS_DIVERGED,
                           STATUS_PREFLIGHT, STATUS_VALVE_TEST)
from eha_ros.physics.bench import mean_conditions
from eha_ros.physics.params import ParameterError, PlantParams
from eha_ros.physics.maintenance import MAP_POINTS, PREFLIGHT_SIGNALS, valve_test_schedule

from eha_ros.health.posterior import InServiceEstimator
from eha_ros.health.thresholds import (ERROR, OK, WARN, HealthEstimate, HealthThresholds,
                                       classify, classify_fault)
from eha_ros.health.valve_test import ValveTestEstimator

__all__ = ['ITEMS', 'ITEM_UNITS', 'Item', 'HealthReport', 'Job', 'MonitorCore',
           'STATUS_DIVERGED', 'STATUS_VALVE_TEST', 'STATUS_PREFLIGHT', 'LEVEL_NAMES',
           'WINDOW_S', 'UPDATE_PERIOD_S', 'SETTLE_S']

#: The monitor's settings, their one default (the node's parameters and ``eha-diagnose``'s
#: flags of the same names read them here): the in-service fit's window of state time [s]
#: (about ten periods of the slowest test sine, enough flow reversals to separate clearance
#: from overlap), the state time between estimates [s] (twice a second: wear moves over
#: hours) and the state time ignored at start [s] (the start-up transient of the loop).
WINDOW_S = 1.0
UPDATE_PERIOD_S = 0.5
SETTLE_S = 0.05


#: Monitored parameters (plant names) and their units.
ITEMS = ('radial_clearance_m', 'overlap_supply_m', 'demagnetisation', 'filter_clogging',
         'spool_static_friction_n', 'jack_static_friction_n', 'offset_a', 'valve_degradation',
         'leakage_coeff_m3_s_pa')
ITEM_UNITS = {'radial_clearance_m': 'm', 'overlap_supply_m': 'm', 'demagnetisation': '1',
              'filter_clogging': '1', 'spool_static_friction_n': 'N',
              'jack_static_friction_n': 'N', 'offset_a': 'A', 'valve_degradation': '1',
              'leakage_coeff_m3_s_pa': 'm^3/(s Pa)'}
CANNOT_ASSESS = LEVEL_CANNOT_ASSESS
#: Severity of the levels, for the worst of several: an item that cannot be assessed ranks
#: above OK (it is not shown healthy) and below a shown degradation.
SEVERITY = {0: 0, CANNOT_ASSESS: 1, 1: 2, 2: 3}
_CONDITION_FIELDS = ('supply_pressure_measured_pa', 'return_pressure_measured_pa',
                     'fluid_temperature_measured_k')


@dataclasses.dataclass
class Item:
    """Estimate of one monitored parameter."""

    name: str
    value: float
    std: float
    level: int
    message: str
    method: str
    stamp_ns: int

    def to_dict(self) -> dict:
        return {'value': self.value, 'std': self.std, 'level': LEVEL_NAMES[self.level],
                'message': self.message, 'method': self.method, 'stamp_ns': self.stamp_ns}


@dataclasses.dataclass
class HealthReport:
    """One estimate: the HealthStatus content and the items it (re)estimated."""

    stamp_ns: int
    kind: str                  # in-service, valve-test, preflight
    method: str
    level: int
    message: str
    radial_clearance_m: float = 0.0
    radial_clearance_std_m: float = 0.0
    overlap_m: float = 0.0
    overlap_std_m: float = 0.0
    pressure_residual_pa: float = 0.0
    samples_used: int = 0
    items: dict = dataclasses.field(default_factory=dict)   # name -> Item

    conditions: dict = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in (
            'stamp_ns', 'kind', 'method', 'radial_clearance_m', 'radial_clearance_std_m',
            'overlap_m', 'overlap_std_m', 'pressure_residual_pa', 'samples_used', 'message',
            'conditions')}
        d['level'] = LEVEL_NAMES[self.level]
        d['estimates'] = {k: v.to_dict() for k, v in self.items.items()}
        return d


def _wear_items(est: HealthEstimate, level: int, text: str, limits: HealthThresholds,
                stamp_ns: int) -> dict:
    """Clearance and overlap items of a wear estimate, each with its own level."""
    extra = [(n, *est.extra[n]) for n in ITEMS if n in est.extra]
    if est.mismatch:
        why = f'cannot be assessed: {est.mismatch}'
        return {n: Item(n, float(v), float(s), CANNOT_ASSESS, why, est.method, stamp_ns)
                for n, v, s in [('radial_clearance_m', est.radial_clearance_m,
                                 est.radial_clearance_std_m),
                                ('overlap_supply_m', est.overlap_m, est.overlap_std_m)] + extra}
    out = {n: Item(n, float(v), float(s), *classify_fault(n, v, s, limits), est.method, stamp_ns)
           for n, v, s in extra}
    for name, v, s, warn, err, sign in (
            ('radial_clearance_m', est.radial_clearance_m, est.radial_clearance_std_m,
             limits.clearance_warn_m, limits.clearance_error_m, 1.0),
            ('overlap_supply_m', est.overlap_m, est.overlap_std_m, limits.overlap_warn_m,
             limits.overlap_error_m, -1.0)):
        if level == OK:
            lv, why = OK, text
        elif est.beyond:
            key = 'clearance' if sign > 0 else 'overlap'
            pe = limits.evidence_probability
            lv = (ERROR if est.beyond[f'{key}_error'] >= pe
                  else WARN if est.beyond[f'{key}_warn'] >= pe else OK)
            why = text if lv else f'{name} not shown beyond its limits; {text}'
        else:
            lv = (ERROR if sign * (v - err) >= 0 else WARN if sign * (v - warn) >= 0 else OK)
            why = text
        out[name] = Item(name, float(v), float(s), lv, why, est.method, stamp_ns)
    return out


def _load(make) -> tuple:
    """``(make(), '')``, or ``(None, why)`` where it fails (``why`` on one line)."""
    try:
        return make(), ''
    except (OSError, ValueError) as exc:  # SurrogateError is a ValueError too
        return None, ' '.join(str(exc).split())


class Job:
    """One estimate due: its inputs (copies) and the code that makes it."""

    def __init__(self, core: 'MonitorCore', kind: str, stamp_ns: int, data):
        self.core, self.kind, self.stamp_ns, self.data = core, kind, stamp_ns, data

    def run(self) -> HealthReport:
        return self.core.make_report(self)


class MonitorCore:
    """State-by-state health logic (see the module docstring).

    Parameters
    ----------
    params : PlantParams
        Physics of the valve (nominal wear for the in-service evidence test).
    limits : HealthThresholds
    window_s, update_period_s, settle_s : float
        In-service window, state time between estimates, state time ignored at start [s].
    in_service : InServiceEstimator, optional
    valve_test : ValveTestEstimator or None, optional
        None: the diagnostic network is unavailable (``valve_test_error`` says why).
    faults : FaultModel or None, optional
    valve_fit : ValveFitEstimator or None, optional
        The settled valve test's estimator; None: unavailable (``valve_fit_error``).
    """

    def __init__(self, params: PlantParams, limits: HealthThresholds,
                 window_s: float = WINDOW_S, update_period_s: float = UPDATE_PERIOD_S,
                 settle_s: float = SETTLE_S, in_service=None,
                 valve_test='default', faults='default', valve_fit='default'):
        self.params = params
        self.limits = limits
        self.window_s = float(window_s)
        self.update_period_s = float(update_period_s)
        self.settle_s = float(settle_s)
        self.in_service = (in_service if in_service is not None
                           else InServiceEstimator(params, limits=limits))
        self.valve_test_error = self.faults_error = self.valve_fit_error = ''
        if valve_test == 'default':
            valve_test, self.valve_test_error = _load(lambda: ValveTestEstimator(params))
        self.valve_test = valve_test
        if faults == 'default':
            from eha_ros.health.preflight import load_faults
            faults, self.faults_error = _load(load_faults)
        self.faults = faults
        if valve_fit == 'default':
            from eha_ros.health.valve_fit import ValveFitEstimator
            valve_fit, self.valve_fit_error = _load(lambda: ValveFitEstimator(params))
        self.valve_fit = valve_fit
        self.readings = []            # the bench's readings of the conditions in a test
        self.procedure = 'reference'
        self._point, self._before = None, math.nan
        self._trace = deque(maxlen=4096)   # (sim time, P12) of the point held
        self.samples = deque()
        self.next_ns = None
        self.mode = None              # None (in service), 'valve-test', 'preflight'
        self.curves, self.curves_done = {}, []
        self.record = {}
        self.scheduled = 0            # in-service estimates that fell due
        self.items = {}               # name -> last Item
        self.have_valve_test = False

    # --- states ----------------------------------------------------------------------------
    def on_state(self, t_ns: int, s) -> list:
        """Take one state (an ``ActuatorState`` or any object with its fields); return the
        jobs that fall due."""
        status = int(s.status)
        if status == STATUS_VALVE_TEST:
            return self._on_valve_test(t_ns, s)
        if status == STATUS_PREFLIGHT:
            return self._on_preflight(t_ns, s)
        if self.mode is not None:  # a test is over: the in-service window starts afresh
            self.mode = None
            self.next_ns = None
            self.samples.clear()
        if status == STATUS_DIVERGED or s.sim_time_s < self.settle_s:
            return []
        self.samples.append((t_ns, s.spool_position_m, s.load_flow_m3_s, s.p12_pa))
        while self.samples and self.samples[0][0] < t_ns - self.window_s * 1e9:
            self.samples.popleft()
        if self.next_ns is None:
            self.next_ns = t_ns + int(self.update_period_s * 1e9)
        if t_ns < self.next_ns:
            return []
        self.next_ns = t_ns + int(self.update_period_s * 1e9)
        self.scheduled += 1
        arr = np.array([x[1:] for x in self.samples], dtype=float).reshape(-1, 3)
        return [Job(self, 'in-service', t_ns, arr)]

    def _read_conditions(self, s) -> None:
        r = [float(getattr(s, f, float('nan'))) for f in _CONDITION_FIELDS]
        if all(np.isfinite(r)):
            self.readings.append(r)

    def _conditions(self):
        """The mean measured conditions of the test so far, or None (none recorded)."""
        return mean_conditions(self.readings) if self.readings else None

    def _on_valve_test(self, t_ns, s) -> list:
        if self.mode != 'valve-test':
            self.mode = 'valve-test'
            self.curves, self.curves_done = {}, []
            self.samples.clear()
            self.readings = []
            # ActuatorState.VALVE_TEST_REFERENCE = 0 (also where a recording has no field),
            # VALVE_TEST_SETTLED = 1
            self.procedure = 'settled' if int(getattr(s, 'valve_test_procedure', 0)) else \
                'reference'
        self._read_conditions(s)
        reading = float(s.p12_pa)
        if self.procedure == 'settled':   # the mean of the hold's last READING_S, and before
            from eha_ros.health.valve_fit import READING_S, window_mean
            key = (float(s.load_flow_m3_s), int(s.valve_test_point))
            if key != self._point:
                self._point, self._before = key, math.nan
                self._trace.clear()
            self._trace.append((float(s.sim_time_s), float(s.p12_pa)))
            if s.valve_test_point_end:
                t_end = float(s.sim_time_s)
                last = [p for t, p in self._trace if t > t_end - READING_S + 1e-7]
                before = [p for t, p in self._trace
                          if t_end - 2 * READING_S + 1e-7 < t <= t_end - READING_S + 1e-7]
                reading = window_mean(last)
                self._before = window_mean(before)
        if not s.valve_test_point_end:
            return []
        n_points = (valve_test_schedule('settled')['n_points'] if self.procedure == 'settled'
                    else MAP_POINTS)
        q = float(s.load_flow_m3_s)
        curve = self.curves.setdefault(q, {})
        curve[int(s.valve_test_point)] = (float(s.spool_position_m), reading,
                                          self._before if self.procedure == 'settled'
                                          else math.nan)
        if int(s.valve_test_point) != n_points - 1:
            return []
        if len(curve) < n_points:
            return [Job(self, 'valve-test-incomplete', t_ns, (q, len(curve), n_points))]
        # spool positions, readings and (settled test) the readings before, point by point
        cols = [np.array(c) for c in zip(*(curve[k] for k in sorted(curve)))]
        self.curves_done.append((q, *cols[:3 if self.procedure == 'settled' else 2]))
        return [Job(self, 'valve-test', t_ns, (self.procedure, list(self.curves_done),
                                               self._conditions()))]

    def _on_preflight(self, t_ns, s) -> list:
        if self.mode != 'preflight':
            self.mode = 'preflight'
            self.record = {}
            self.samples.clear()
            self.readings = []
        self._read_conditions(s)
        k = int(s.valve_test_point)
        self.record[k] = (float(s.coil_current_a), float(s.spool_position_m),
                          float(s.flapper_position_m), float(s.p12_pa),
                          float(s.jack_position_m), float(s.jack_velocity_m_s))
        if not s.valve_test_point_end:
            return []
        rec, self.record = self.record, {}
        return [Job(self, 'preflight', t_ns, (k + 1, rec, self._conditions()))]

    # --- estimates -------------------------------------------------------------------------
    def make_report(self, job: Job) -> HealthReport:
        """Run ``job``: the estimate, its level, and the items it updates."""
        lim = self.limits
        t = job.stamp_ns
        if job.kind == 'valve-test-incomplete':
            q, n, n_points = job.data
            return HealthReport(t, 'valve-test', ValveTestEstimator.method, ERROR,
                                f'no estimate: valve test curve at q = {q:g} m^3/s has {n} of '
                                f'{n_points} points (states lost)')
        if job.kind == 'preflight':
            return self._preflight_report(job)
        try:
            if job.kind == 'in-service':   # the columns XS, Q, P12
                est = self.in_service.estimate(*job.data.T)
            else:
                procedure, curves, conditions = job.data
                if procedure == 'settled':
                    if self.valve_fit is None:
                        raise ParameterError(f'the settled valve test\'s fit is not usable: '
                                             f'{self.valve_fit_error}')
                    est = self.valve_fit.estimate(curves, conditions)
                elif self.valve_test is None:
                    raise ParameterError(f'the diagnostic network is not usable: '
                                         f'{self.valve_test_error}')
                else:
                    est = self.valve_test.estimate(curves)
                    if conditions is not None:
                        est.conditions = conditions.as_dict()
        except ValueError as exc:
            method = (self.in_service.method if job.kind == 'in-service'
                      else 'settled-valve-fit' if job.data[0] == 'settled'
                      else ValveTestEstimator.method)
            return HealthReport(t, job.kind, method, ERROR, f'no estimate: {exc}')
        level, text = ((CANNOT_ASSESS, f'cannot be assessed: {est.mismatch}') if est.mismatch
                       else classify(est, lim))
        if est.note:
            text = f'{text} ({est.note})'
        items = _wear_items(est, level, text, lim, t)
        if job.kind == 'valve-test':
            self.have_valve_test = True
        if job.kind == 'valve-test' or not self.have_valve_test:
            self.items.update(items)
        return HealthReport(t, job.kind, est.method, level, text, est.radial_clearance_m,
                            est.radial_clearance_std_m, est.overlap_m, est.overlap_std_m,
                            est.pressure_residual_pa, est.samples_used, items,
                            dict(est.conditions))

    def _preflight_report(self, job: Job) -> HealthReport:
        from eha_ros.health.preflight import FAULTS
        t = job.stamp_ns
        n, rec, conditions = job.data
        method = 'preflight-network'
        if self.faults is None:
            return HealthReport(t, 'preflight', method, ERROR,
                                f'no estimate: the pre-flight network is not usable: '
                                f'{self.faults_error}')
        from eha_ros.physics.maintenance import PREFLIGHT_S, PREFLIGHT_TICK_S, preflight_command
        expected = int(round(PREFLIGHT_S / PREFLIGHT_TICK_S))
        if n != expected or len(rec) != n:
            return HealthReport(t, 'preflight', method, ERROR,
                                f'no estimate: pre-flight check has {len(rec)} of {expected} '
                                f'ticks (states lost, or not at {1 / PREFLIGHT_TICK_S:g} Hz)')
        arr = np.array([rec[k] for k in range(n)])
        record = {name: arr[:, j] for j, name in enumerate(PREFLIGHT_SIGNALS)}
        record['command_a'] = preflight_command(n, PREFLIGHT_TICK_S, self.params.current_limit_a)
        if conditions is None:
            from eha_ros.physics.bench import load_bench, true_conditions
            conditions = dataclasses.replace(true_conditions(self.params, load_bench()),
                                             assumed=True)
        est = self.faults.estimate(record, conditions)
        mismatch, note = est.mismatch, est.note
        items = {}
        for f in FAULTS:
            v, sd = est.values[f.name], est.stds[f.name]
            lv, why = ((CANNOT_ASSESS, f'cannot be assessed: {mismatch}') if mismatch
                       else classify_fault(f.name, v, sd, self.limits))
            if note:
                why = f'{why} ({note})'
            items[f.name] = Item(f.name, v, sd, lv, why, method, t)
        self.items.update(items)
        # the verdict covers every parameter known, the valve test's included
        worst = max(self.items.values(), key=lambda i: SEVERITY[i.level])
        flagged = [i.name for i in self.items.values() if i.level in (WARN, ERROR)]
        unknown = [i.name for i in self.items.values() if i.level == CANNOT_ASSESS]
        if mismatch:
            text = f'pre-flight check cannot be assessed: {mismatch}'
        elif flagged:
            text = f'pre-flight check: {", ".join(flagged)} degraded; {worst.message}'
        elif unknown:
            text = (f'pre-flight check: no degradation shown; {", ".join(unknown)} cannot be '
                    f'assessed; {worst.message}')
        else:
            text = 'pre-flight check: no degradation shown'
        c, o = self.items.get('radial_clearance_m'), self.items.get('overlap_supply_m')
        return HealthReport(t, 'preflight', method, worst.level, text,
                            c.value if c else 0.0, c.std if c else 0.0,
                            o.value if o else 0.0, o.std if o else 0.0, 0.0, n, items,
                            conditions.as_dict())
