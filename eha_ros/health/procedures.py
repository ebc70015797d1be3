"""The sweep's procedures of the health checks: the pre-flight check and the valve test.

* :class:`PreflightProcedure` (``preflight_check``): the pre-flight check
  (:func:`eha_ros.physics.maintenance.run_preflight`); the pre-flight network's estimates and
  deviations, the check's features (signal ``preflight_features``) on request.
* :class:`ValveTestProcedure` (``valve_test``): the valve test's P12 curves (the map
  transients the plant reports at the end of each hold, or the settled test's readings) and
  the diagnostic network's or the valve fit's wear estimate.

Both are :class:`eha_ros.procedure.Procedure`; :data:`eha_ros.sweep.procedures.PROCEDURES`
lists them by name.
"""

from __future__ import annotations

import time

import numpy as np

from eha_ros.health.preflight import (CONDITION_READINGS, FAULT_NAMES, load_faults,
                                      preflight_features)
from eha_ros.health.valve_fit import (READING_S, ValveFitEstimator, load_calibration,
                                      window_mean)
from eha_ros.health.valve_test import ValveTestEstimator, load_diagnostic
from eha_ros.physics import ParameterError, default_params
from eha_ros.physics.bench import load_bench, mean_conditions, measure_conditions
from eha_ros.physics.maintenance import (PREFLIGHT_SIGNALS, PREFLIGHT_TICK_S, run_preflight,
                                         valve_test_schedule)
from eha_ros.physics.maps import spool_grid, steady_map, stepped_trace, transient_map
from eha_ros.physics.params import replace
from eha_ros.procedure import Procedure, status_of
from eha_ros.surrogates.base import relative_error

__all__ = ['PreflightProcedure', 'ValveTestProcedure']


class PreflightProcedure(Procedure):
    """The pre-flight check (see the module's docstring).  The network reads each case with
    the conditions the bench measures for it (:data:`eha_ros.health.preflight.
    CONDITION_READINGS` readings seeded by the case's seed, averaged); ``ood_score`` and
    ``mismatch`` (the estimate's refusal is set) come with its estimates."""

    SIGNALS = ('command_a',) + PREFLIGHT_SIGNALS + ('preflight_features',)
    RECORD_DT_S = PREFLIGHT_TICK_S
    #: Metrics of the network besides ``est_*`` and ``std_*``.
    ESTIMATE_METRICS = ('ood_score', 'mismatch')

    @classmethod
    def metrics(cls, compare=None) -> tuple:
        return (tuple((f'{k}_{n}', 'float') for k in ('est', 'std') for n in FAULT_NAMES)
                + (('ood_score', 'float'), ('mismatch', 'bool'), ('p12_rel_error', 'float'),
                   ('spool_rel_error', 'float')))

    def _estimates(self) -> bool:
        """Whether the spec wants the network's metrics."""
        return any(m in self.ESTIMATE_METRICS or m.startswith(('est_', 'std_'))
                   for m, _ in self.wanted())

    def check(self, where: str) -> None:
        super().check(where)
        if self._estimates():
            try:
                load_faults()
            except ValueError as exc:
                raise ValueError(f'{where}: {exc}') from None

    def warm_up(self) -> None:
        super().warm_up()
        if self._estimates():
            load_faults()

    def _signals(self, arrays: dict) -> dict:
        out = {}
        if 'preflight_features' in self.spec.signals:
            out['signal_preflight_features'] = np.asarray(preflight_features(arrays),
                                                          dtype=float)
        rest = [s for s in self.spec.signals if s != 'preflight_features']
        every = int(round(self.spec.signal_dt_s / self.RECORD_DT_S))
        out.update({f'signal_{s}': np.array(arrays[s], dtype=float)[every - 1::every]
                    for s in rest})
        return out

    def run_point(self, point) -> list:
        wanted = {m for m, _ in self.wanted()}
        estimate = self._estimates()
        t0 = time.perf_counter()
        rows, ref = [], None
        try:
            p = point.params(self.spec)
        except ParameterError as exc:
            return [{'case_id': c.case_id, 'model': c.model, 'dt_s': c.dt_s,
                     **dict(zip(('status', 'error'), status_of(exc)))} for c in point.cases]
        for c in sorted(point.cases, key=lambda c: c.model != 'hf'):
            t = time.perf_counter()
            row = {'case_id': c.case_id, 'model': c.model, 'dt_s': c.dt_s}
            try:
                rec = run_preflight(p, seed=point.seed, dt_s=c.dt_s, fluid=self.model(c.model),
                                    integrator=self.spec.integrator)
                m = {}
                if estimate:   # with the conditions the bench measures (seeded by the case)
                    cond = mean_conditions(measure_conditions(p, point.seed,
                                                              CONDITION_READINGS))
                    e = load_faults().estimate(rec, cond)
                    m.update({f'est_{n}': v for n, v in e.values.items()})
                    m.update({f'std_{n}': v for n, v in e.stds.items()})
                    m.update(ood_score=e.ood_score, mismatch=bool(e.mismatch))
                if c.model == 'hf':
                    ref = rec
                elif wanted & {'p12_rel_error', 'spool_rel_error'}:
                    if ref is None:
                        ref = run_preflight(p, seed=point.seed, dt_s=c.dt_s)
                    m['p12_rel_error'] = relative_error(rec['p12_pa'], ref['p12_pa'])
                    m['spool_rel_error'] = relative_error(rec['spool_position_m'],
                                                          ref['spool_position_m'])
                row.update(status='ok', error=None, **m, **self._signals(rec))
            except Exception as exc:
                row.update(zip(('status', 'error'), status_of(exc)))
            row['wall_s'] = time.perf_counter() - t
            rows.append(row)
        wall = time.perf_counter() - t0
        by_id = {r['case_id']: r for r in rows}
        for r in rows:
            r['wall_point_s'] = wall
        return [by_id[c.case_id] for c in point.cases]


class ValveTestProcedure(Procedure):
    """The valve test's curves and their estimate (module docstring): the reference's
    transient read by the diagnostic network, or the settled test read by the valve fit at
    the measured conditions (``valve_test_procedure``).  The seed draws the bench's sensor
    errors on the conditions and the relative noise ``pressure_noise`` on every pressure."""

    SIGNALS = ('p12_pa',)
    RECORD_DT_S = 1.0
    TICKED = False
    INTEGRATES = False   # the map transient is a kernel of its own (physics.maps)

    @classmethod
    def metrics(cls, compare=None) -> tuple:
        return tuple((n, 'bool' if n == 'mismatch' else 'float') for n in (
            'est_radial_clearance_m', 'est_radial_clearance_std_m', 'est_overlap_m',
            'est_overlap_std_m', 'pressure_residual_pa', 'est_valve_degradation',
            'est_valve_degradation_std', 'est_leakage_coeff_m3_s_pa',
            'est_leakage_coeff_m3_s_pa_std', 'chi', 'mismatch', 'measured_supply_pressure_pa',
            'measured_return_pressure_pa', 'measured_fluid_temperature_k'))

    def check(self, where: str) -> None:
        spec = self.spec
        if spec.signals and spec.signal_dt_s != 1e-3:
            raise ValueError(f'{where}: valve_test keeps its P12 curves whole (no '
                             'signal_dt_s)')
        spec.signal_dt_s = 1e-3
        super().check(where)
        try:
            if spec.valve_test_procedure == 'settled':
                load_calibration()
            else:
                load_diagnostic()
        except ValueError as exc:
            raise ValueError(f'{where}: {exc}') from None

    def warm_up(self) -> None:
        p = self.spec.point_params({})
        transient_map([0.0], self.schedule()['flows_m3_s'][0], params=p)
        steady_map([0.0], 0.0, params=p)

    def schedule(self) -> dict:
        return valve_test_schedule(self.spec.valve_test_procedure, self.spec.flows_m3_s)

    def run_point(self, point) -> list:
        (c,) = point.cases
        t0 = time.perf_counter()
        row = {'case_id': c.case_id, 'model': c.model, 'dt_s': c.dt_s}
        try:
            p = point.params(self.spec)
            sch = self.schedule()
            grid = spool_grid(sch['n_points'], p.spool_stroke_m)
            rng = np.random.default_rng([int(point.seed), 0x9E55])
            curves = []
            settled = self.spec.valve_test_procedure == 'settled'

            def noisy(p12):   # the relative pressure noise, drawn for every pressure
                if not self.spec.pressure_noise:
                    return p12
                return p12 * (1.0 + self.spec.pressure_noise * rng.standard_normal(p12.shape))
            for q in sch['flows_m3_s']:
                if not settled:   # the reference's: P12 at the end of the hold
                    curves.append((q, grid, noisy(np.asarray(transient_map(
                        grid, q, params=p, t_end_s=sch['hold_s'], dt_s=c.dt_s)['p12_pa'],
                        dtype=float))))
                    continue
                # settled: the plant's 1 ms samples of the hold's last two READING_S windows;
                # the reading is the last window's mean, the settle check the one before
                n_hold = int(round(sch['hold_s'] / 1e-3))
                n_win = int(round(READING_S / 1e-3))
                p1, p2 = stepped_trace(grid, q, n_hold, int(round(1e-3 / c.dt_s)), p,
                                       c.dt_s, first=n_hold - 2 * n_win)
                p12 = noisy(p1 - p2)
                curves.append((q, grid, np.array([window_mean(v) for v in p12[n_win:].T]),
                               np.array([window_mean(v) for v in p12[:n_win].T])))
            nominal = replace(default_params(), noise_std_a=0.0)
            # as the plant reports them at 1 kHz: one reading at start, one per test tick
            n_ticks = int(round(sch['hold_s'] * 1e3)) * sch['n_points'] * len(curves)
            cond = mean_conditions(measure_conditions(p, point.seed, n_ticks + 1,
                                                      load_bench())[1:])
            if settled:
                est = ValveFitEstimator(nominal).estimate(curves, cond)
                k, k_std = est.extra['valve_degradation']
                leak, leak_std = est.extra['leakage_coeff_m3_s_pa']
                chi = est.extra['chi']
            else:
                est = ValveTestEstimator(nominal).estimate(curves)
                k = k_std = leak = leak_std = chi = float('nan')
            row.update(status='ok', error=None,
                       est_radial_clearance_m=est.radial_clearance_m,
                       est_radial_clearance_std_m=est.radial_clearance_std_m,
                       est_overlap_m=est.overlap_m, est_overlap_std_m=est.overlap_std_m,
                       pressure_residual_pa=est.pressure_residual_pa,
                       est_valve_degradation=k, est_valve_degradation_std=k_std,
                       est_leakage_coeff_m3_s_pa=leak, est_leakage_coeff_m3_s_pa_std=leak_std,
                       chi=chi,
                       mismatch=bool(est.mismatch),
                       measured_supply_pressure_pa=cond.supply_pressure_pa,
                       measured_return_pressure_pa=cond.return_pressure_pa,
                       measured_fluid_temperature_k=cond.fluid_temperature_k)
            if self.spec.signals:
                row['signal_p12_pa'] = np.concatenate([cv[2] for cv in curves])
        except Exception as exc:
            row.update(zip(('status', 'error'), status_of(exc)))
        row['wall_s'] = row['wall_point_s'] = time.perf_counter() - t0
        return [row]
