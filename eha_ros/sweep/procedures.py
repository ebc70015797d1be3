"""What runs at a point, and the dataset row of each of its cases.

Three procedures, physics only:

* :class:`ScenarioProcedure` (``scenario``): the closed loop on a scenario of
  ``config/scenarios.yaml``, controller at 1 kHz, every tick recorded (as the in-loop
  comparison, :func:`eha_ros.evaluation.run`).  Metrics: the comparison's features
  (:func:`eha_ros.evaluation.features`, one implementation) and, for a surrogate, the relative
  errors of jack position and P12 against hf run at the same point.  With ``compare:
  yardstick`` and noise off the point is :func:`eha_ros.evaluation.noise_free` (hf's yardstick,
  the bounds, the features' spread); with noise on, hf is also run at seed + 1 (hf's
  seed-to-seed spread) and with the discharge coefficient + 0.1 % (as
  :func:`eha_ros.evaluation.with_noise`).
* :class:`PreflightProcedure` (``preflight_check``): the pre-flight check
  (:func:`eha_ros.physics.maintenance.run_preflight`); the pre-flight network's estimates and
  deviations, the check's features (signal ``preflight_features``) on request.
* :class:`ValveTestProcedure` (``valve_test``): the valve test's P12 curves (the map transients
  the plant reports at the end of each hold) and the diagnostic network's wear estimate.

A case that diverges is a row with status ``diverged``, one that raises a row with status
``error``; both carry the message in ``error``.  Timing columns are named ``wall_*``.
"""

from __future__ import annotations

import time

import numpy as np

from eha_ros.evaluation import CONTROLLER_PERIOD_S, features, model_integrator, run
from eha_ros.physics import ParameterError, SimulationDiverged
from eha_ros.physics.params import replace
from eha_ros.surrogates.base import relative_error

from .errors import SpecError, label

__all__ = ['PROCEDURE_CLASSES', 'Procedure', 'ScenarioProcedure', 'PreflightProcedure',
           'ValveTestProcedure', 'FEATURES']

#: The in-loop comparison's features (:func:`eha_ros.evaluation.features`) and their types.
FEATURES = (('rms_tracking_error_m', 'float'), ('final_position_m', 'float'),
            ('stick_slip_steps', 'int'), ('mean_step_m', 'float'), ('p12_rms_pa', 'float'),
            ('p12_peak_pa', 'float'))


def _status(exc: BaseException) -> tuple:
    status = 'diverged' if isinstance(exc, SimulationDiverged) else 'error'
    return status, f'{type(exc).__name__}: {exc}'


class Procedure:
    """A procedure: its metrics (name, type), signals, checks and the run of one point."""

    SIGNALS: tuple = ()
    #: Interval [s] the signals are recorded at (``signal_dt_s`` a whole multiple of it).
    RECORD_DT_S = CONTROLLER_PERIOD_S
    #: Whether the procedure runs in ticks of ``RECORD_DT_S`` (a whole number of steps).
    TICKED = True
    #: Whether it runs the plant's loop, and so takes the spec's ``integrator``.
    INTEGRATES = True

    def __init__(self, spec):
        self.spec = spec
        self._models = {}

    @classmethod
    def metrics(cls, compare=None) -> tuple:
        return ()

    @classmethod
    def metric_names(cls, compare=None) -> tuple:
        return tuple(n for n, _ in cls.metrics(compare))

    def wanted(self) -> tuple:
        """``(name, type)`` of the metric columns of this spec."""
        allm = self.metrics(self.spec.compare)
        if self.spec.metrics is None:
            return allm
        return tuple(m for m in allm if m[0] in self.spec.metrics)

    @classmethod
    def check(cls, spec, where: str) -> None:
        """Every point's parameters within the plant's ranges and every model's validity."""
        from eha_ros.physics.stability import EXPLICIT, check_dt, integrator_substeps
        for _, dt in spec.case_models():
            n = cls.RECORD_DT_S / dt
            if cls.TICKED and abs(n - round(n)) > 1e-9 * n:
                raise _spec_error(f'{where}: dt_s = {dt:g} s: the tick of {cls.RECORD_DT_S:g} s '
                                  'must be a whole multiple of the step')
        every = spec.signal_dt_s / cls.RECORD_DT_S
        if spec.signals and abs(every - round(every)) > 1e-9 * every:
            raise _spec_error(f'{where}: signal_dt_s = {spec.signal_dt_s:g} s must be a whole '
                              f'multiple of {cls.RECORD_DT_S:g} s')
        proc = cls(spec)
        models = {}
        for m in spec.models:
            try:
                models[m] = proc.model(m)
            except (ValueError, OSError) as exc:
                raise _spec_error(f'{where}: model {m}: {exc}') from None
        seen = set()
        for pt in spec.points():
            key = tuple(sorted(pt.inputs.items()))
            if key in seen:   # the same parameters at another seed or scenario: checked
                continue
            seen.add(key)
            try:
                p = pt.params(spec)
                for c in pt.cases:
                    name, integ = model_integrator(c.model)
                    s = models.get(name)
                    if s is not None:
                        s.check_params(p)
                    if cls.INTEGRATES:
                        integ = spec.integrator if integ == EXPLICIT else integ
                        integrator_substeps(integ, c.dt_s)
                        check_dt(p, c.dt_s, s, integ)
            except ValueError as exc:
                raise _spec_error(f'{where}: case {label(pt.inputs)}: {exc}') from None

    def model(self, name):
        """The fluid block of model ``name`` (``None`` for hf; ``<name>@split`` is ``name``'s),
        loaded once."""
        name = model_integrator(name)[0]
        if name == 'hf':
            return None
        if name not in self._models:
            from eha_ros.physics import default_params
            from eha_ros.surrogates.registry import load_surrogate
            self._models[name] = load_surrogate(name, default_params())
        return self._models[name]

    def _signals(self, arrays: dict) -> dict:
        every = int(round(self.spec.signal_dt_s / self.RECORD_DT_S))
        return {f'signal_{s}': np.array(arrays[s], dtype=float)[every - 1::every]
                for s in self.spec.signals}

    def run_point(self, point) -> list:
        raise NotImplementedError

    def warm_up(self) -> None:
        """Load every model and compile its kernels (a short run each)."""
        from eha_ros.physics import Plant
        p = self.spec.point_params({})
        for m in self.spec.models:
            Plant(p, dt_s=self.spec.dt_s, fluid=self.model(m),
                  integrator=self.spec.integrator).advance(0.0, 100)


def _spec_error(text):
    return SpecError(text)


def _errors(r, ref) -> dict:
    return {'jack_rel_error': relative_error(r['jack_position_m'], ref['jack_position_m']),
            'p12_rel_error': relative_error(r['p12_pa'], ref['p12_pa'])}


class ScenarioProcedure(Procedure):
    """The closed loop on the spec's scenario (see the module's docstring)."""

    SIGNALS = ('time_s', 'command_m', 'current_command_a', 'coil_current_a',
               'flapper_position_m', 'spool_position_m', 'p1_pa', 'p2_pa', 'p12_pa',
               'load_flow_m3_s', 'jack_position_m', 'jack_velocity_m_s')

    @classmethod
    def metrics(cls, compare=None) -> tuple:
        out = FEATURES + (('jack_rel_error', 'float'), ('p12_rel_error', 'float'))
        if compare == 'yardstick':
            out += (('yardstick_jack', 'float'), ('yardstick_p12', 'float'),
                    ('bound_jack', 'float'), ('bound_p12', 'float'),
                    ('meets_bounds', 'bool'))
            out += tuple((f'spread_{f}', 'float') for f, _ in FEATURES)
            out += (('seed_spread_jack', 'float'), ('seed_spread_p12', 'float'),
                    ('cd_plus_0p1pct_jack', 'float'), ('cd_plus_0p1pct_p12', 'float'))
        return out

    @classmethod
    def check(cls, spec, where: str) -> None:
        if spec.compare == 'yardstick' and spec.noise and (spec.large_dts or spec.split_dts):
            raise _spec_error(f'{where}: large_dts and split_dts are compared noise-free only')
        super().check(spec, where)

    def run_point(self, point) -> list:
        if self.spec.compare == 'yardstick':
            if self.spec.noise:
                return self._yardstick_noise(point)
            return self._yardstick(point)
        sc = point.scenario
        t0 = time.perf_counter()
        rows = {}
        ref = None
        try:
            p = point.params(self.spec)
        except ParameterError as exc:
            return [self._row(c, {}, *_status(exc)) for c in point.cases]
        need_ref = any(c.model != 'hf' for c in point.cases)
        order = sorted(point.cases, key=lambda c: c.model != 'hf')
        for c in order:
            t = time.perf_counter()
            try:
                if c.model == 'hf' and c.dt_s == self.spec.dt_s and ref is not None:
                    r = ref
                else:
                    r = run(p, sc, self.model(c.model), dt=c.dt_s, seed=point.seed,
                            integrator=self.spec.integrator)
                if c.model == 'hf' and c.dt_s == self.spec.dt_s:
                    ref = r
                m = features(r)
                if c.model != 'hf':
                    if ref is None and need_ref:
                        ref = run(p, sc, dt=self.spec.dt_s, seed=point.seed,
                                  integrator=self.spec.integrator)
                    m.update(_errors(r, ref))
                row = self._row(c, m, 'ok', None, self._signals(r.data))
            except Exception as exc:  # a diverging or refused run is a result too
                row = self._row(c, {}, *_status(exc))
                if c.model == 'hf':
                    ref = None
                    need_ref = False  # no reference: the surrogates' errors stay empty
            row['wall_s'] = time.perf_counter() - t
            rows[c.case_id] = row
        wall = time.perf_counter() - t0
        for row in rows.values():
            row['wall_point_s'] = wall
        return [rows[c.case_id] for c in point.cases]

    def warm_up(self) -> None:
        from eha_ros.graph import DYNAMIC_MODELS
        from eha_ros.physics import simulate
        p = self.spec.point_params({})
        for m in self.spec.models:
            simulate(p, self.spec.scenarios[0], duration_s=0.01, dt_s=self.spec.dt_s,
                     controller_period_s=CONTROLLER_PERIOD_S, record_dt_s=None,
                     fluid=self.model(m), integrator=self.spec.integrator)
        if self.spec.split_dts:  # the split kernel compiles apart
            dt = self.spec.split_dts[0]
            for m in ('hf',) + self.spec.models:
                if m == 'hf' or m in DYNAMIC_MODELS:
                    simulate(p, self.spec.scenarios[0], duration_s=0.01, dt_s=dt,
                             controller_period_s=CONTROLLER_PERIOD_S, record_dt_s=None,
                             fluid=self.model(m), integrator='split')

    def _row(self, case, metrics, status, error=None, signals=None) -> dict:
        return {'case_id': case.case_id, 'model': case.model, 'dt_s': case.dt_s,
                'status': status, 'error': error, **metrics, **(signals or {})}

    def _yardstick(self, point) -> list:
        from eha_ros.evaluation import noise_free
        t0 = time.perf_counter()
        try:
            p = point.params(self.spec)
            sur = {m: self.model(m) for m in self.spec.models if m != 'hf'}
            out = noise_free(p, point.scenario, sur, self.spec.large_dts,
                             keep_runs=bool(self.spec.signals), split_dts=self.spec.split_dts)
        except Exception as exc:
            return [self._row(c, {}, *_status(exc)) for c in point.cases]
        wall = time.perf_counter() - t0
        common = {'yardstick_jack': out['yardstick']['jack'],
                  'yardstick_p12': out['yardstick']['p12'],
                  'bound_jack': out['bound']['jack'], 'bound_p12': out['bound']['p12'],
                  **{f'spread_{f}': v for f, v in out['feature_spread'].items()}}
        duration = self._duration(point.scenario)
        runs = out.get('runs', {})
        rows = []
        for c in point.cases:
            if c.model == 'hf' and c.dt_s == self.spec.dt_s:
                row = self._row(c, {**out['hf_features'], **common}, 'ok', None,
                                self._signals(runs['hf'].data) if runs else None)
                row['wall_cost_s_per_s'] = out['hf_cost_s_per_s']
                if runs:
                    row.update(self._envelope([runs[k] for k in out['yardstick']['runs']]))
            else:
                key = c.model if c.dt_s == self.spec.dt_s and '@' not in c.model \
                    else f'{c.model}@dt={c.dt_s:g}'
                r = out['models'][key]
                if 'error' in r:
                    status = 'diverged' if r['error'].startswith('SimulationDiverged') \
                        else 'error'
                    row = self._row(c, {}, status, r['error'])
                else:
                    row = self._row(c, {**r['features'], 'jack_rel_error': r['jack'],
                                        'p12_rel_error': r['p12'], **common,
                                        'meets_bounds': r['meets']}, 'ok', None,
                                    self._signals(runs[key].data) if runs else None)
                    row['wall_cost_s_per_s'] = r['cost_s_per_s']
            if row.get('wall_cost_s_per_s') is not None:
                row['wall_s'] = row['wall_cost_s_per_s'] * duration
            row['wall_point_s'] = wall
            rows.append(row)
        return rows

    def _envelope(self, runs) -> dict:
        """Per kept signal, the smallest and largest value of hf's yardstick runs."""
        out = {}
        for name in self.spec.signals:
            sig = [self._signals(r.data)[f'signal_{name}'] for r in runs]
            out[f'signal_{name}_yardstick_lo'] = np.min(sig, axis=0)
            out[f'signal_{name}_yardstick_hi'] = np.max(sig, axis=0)
        return out

    @staticmethod
    def _duration(scenario) -> float:
        from eha_ros.physics import get_scenario
        return float(get_scenario(scenario).duration_s)

    def _yardstick_noise(self, point) -> list:
        """hf at seed k, k + 1 and with Cd + 0.1 %; each model at seed k against hf at k."""
        sc, k = point.scenario, point.seed
        t0 = time.perf_counter()
        try:
            p = point.params(self.spec)
            hf = run(p, sc, seed=k)
            hf1 = run(p, sc, seed=k + 1)
            cd = run(replace(p, discharge_coefficient=p.discharge_coefficient * 1.001), sc,
                     seed=k)
        except Exception as exc:
            return [self._row(c, {}, *_status(exc)) for c in point.cases]
        spread, same = _errors(hf1, hf), _errors(cd, hf)
        rows = []
        for c in point.cases:
            t = time.perf_counter()
            if c.model == 'hf':
                row = self._row(c, {**features(hf),
                                    'seed_spread_jack': spread['jack_rel_error'],
                                    'seed_spread_p12': spread['p12_rel_error'],
                                    'cd_plus_0p1pct_jack': same['jack_rel_error'],
                                    'cd_plus_0p1pct_p12': same['p12_rel_error']}, 'ok',
                                None, self._signals(hf.data))
                row['wall_s'] = hf.wall_time_s
            else:
                try:
                    r = run(p, sc, self.model(c.model), seed=k)
                    row = self._row(c, {**features(r), **_errors(r, hf)}, 'ok', None,
                                    self._signals(r.data))
                    row['wall_s'] = r.wall_time_s
                except Exception as exc:
                    row = self._row(c, {}, *_status(exc))
                    row['wall_s'] = time.perf_counter() - t
            rows.append(row)
        wall = time.perf_counter() - t0
        for row in rows:
            row['wall_point_s'] = wall
            row['wall_cost_s_per_s'] = row['wall_s'] / self._duration(sc)
        return rows


class PreflightProcedure(Procedure):
    """The pre-flight check (see the module's docstring).  The network reads each case with
    the conditions the bench measures for it (:data:`eha_ros.health.preflight.
    CONDITION_READINGS` readings seeded by the case's seed, averaged); ``ood_score`` and
    ``mismatch`` (the estimate's refusal is set) come with its estimates."""

    from eha_ros.physics.maintenance import PREFLIGHT_SIGNALS, PREFLIGHT_TICK_S
    SIGNALS = ('command_a',) + PREFLIGHT_SIGNALS + ('preflight_features',)
    RECORD_DT_S = PREFLIGHT_TICK_S
    #: Metrics of the network besides ``est_*`` and ``std_*``.
    ESTIMATE_METRICS = ('ood_score', 'mismatch')

    @classmethod
    def metrics(cls, compare=None) -> tuple:
        from eha_ros.health.preflight import FAULT_NAMES
        out = tuple((f'est_{n}', 'float') for n in FAULT_NAMES)
        out += tuple((f'std_{n}', 'float') for n in FAULT_NAMES)
        out += (('ood_score', 'float'), ('mismatch', 'bool'))
        return out + (('p12_rel_error', 'float'), ('spool_rel_error', 'float'))

    def _estimates(self) -> bool:
        """Whether the spec wants the network's metrics."""
        return any(m in self.ESTIMATE_METRICS or m.startswith(('est_', 'std_'))
                   for m, _ in self.wanted())

    @classmethod
    def check(cls, spec, where: str) -> None:
        super().check(spec, where)
        if cls(spec)._estimates():
            from eha_ros.health.preflight import load_faults
            try:
                load_faults()
            except ValueError as exc:
                raise _spec_error(f'{where}: {exc}') from None

    def warm_up(self) -> None:
        super().warm_up()
        if self._estimates():
            from eha_ros.health.preflight import load_faults
            load_faults()

    def _signals(self, arrays: dict) -> dict:
        out = {}
        if 'preflight_features' in self.spec.signals:
            from eha_ros.health.preflight import preflight_features
            out['signal_preflight_features'] = np.asarray(preflight_features(arrays),
                                                          dtype=float)
        rest = [s for s in self.spec.signals if s != 'preflight_features']
        every = int(round(self.spec.signal_dt_s / self.RECORD_DT_S))
        out.update({f'signal_{s}': np.array(arrays[s], dtype=float)[every - 1::every]
                    for s in rest})
        return out

    def run_point(self, point) -> list:
        from eha_ros.physics.maintenance import run_preflight
        wanted = {m for m, _ in self.wanted()}
        estimate = self._estimates()
        t0 = time.perf_counter()
        rows, ref = [], None
        try:
            p = point.params(self.spec)
        except ParameterError as exc:
            return [{'case_id': c.case_id, 'model': c.model, 'dt_s': c.dt_s,
                     **dict(zip(('status', 'error'), _status(exc)))} for c in point.cases]
        for c in sorted(point.cases, key=lambda c: c.model != 'hf'):
            t = time.perf_counter()
            row = {'case_id': c.case_id, 'model': c.model, 'dt_s': c.dt_s}
            try:
                rec = run_preflight(p, seed=point.seed, dt_s=c.dt_s, fluid=self.model(c.model),
                                    integrator=self.spec.integrator)
                m = {}
                if estimate:   # with the conditions the bench measures (seeded by the case)
                    from eha_ros.health.preflight import CONDITION_READINGS, load_faults
                    from eha_ros.physics.bench import mean_conditions, measure_conditions
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
                row.update(zip(('status', 'error'), _status(exc)))
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
        return (('est_radial_clearance_m', 'float'), ('est_radial_clearance_std_m', 'float'),
                ('est_overlap_m', 'float'), ('est_overlap_std_m', 'float'),
                ('pressure_residual_pa', 'float'), ('est_valve_degradation', 'float'),
                ('est_valve_degradation_std', 'float'), ('est_leakage_coeff_m3_s_pa', 'float'),
                ('est_leakage_coeff_m3_s_pa_std', 'float'), ('chi', 'float'),
                ('mismatch', 'bool'), ('measured_supply_pressure_pa', 'float'),
                ('measured_return_pressure_pa', 'float'),
                ('measured_fluid_temperature_k', 'float'))

    @classmethod
    def check(cls, spec, where: str) -> None:
        if spec.signals and spec.signal_dt_s != 1e-3:
            raise _spec_error(f'{where}: valve_test keeps its P12 curves whole (no '
                              'signal_dt_s)')
        spec.signal_dt_s = 1e-3
        super().check(spec, where)
        try:
            if spec.valve_test_procedure == 'settled':
                from eha_ros.health.valve_fit import load_calibration
                load_calibration()
            else:
                from eha_ros.health.valve_test import load_diagnostic
                load_diagnostic()
        except ValueError as exc:
            raise _spec_error(f'{where}: {exc}') from None

    def warm_up(self) -> None:
        from eha_ros.physics.maps import steady_map, transient_map
        p = self.spec.point_params({})
        transient_map([0.0], self.flows()[0], params=p)
        steady_map([0.0], 0.0, params=p)

    def schedule(self) -> dict:
        from eha_ros.physics.maintenance import valve_test_schedule
        return valve_test_schedule(self.spec.valve_test_procedure, self.spec.flows_m3_s)

    def flows(self) -> tuple:
        return self.schedule()['flows_m3_s']

    def run_point(self, point) -> list:
        from eha_ros.health.valve_fit import READING_S, ValveFitEstimator, window_mean
        from eha_ros.health.valve_test import ValveTestEstimator
        from eha_ros.physics import default_params
        from eha_ros.physics.bench import load_bench, mean_conditions, measure_conditions
        from eha_ros.physics.maps import spool_grid, stepped_trace, transient_map
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
            for q in sch['flows_m3_s']:
                if not settled:   # the reference's: P12 at the end of the hold
                    p12 = np.asarray(transient_map(grid, q, params=p, t_end_s=sch['hold_s'],
                                                   dt_s=c.dt_s)['p12_pa'], dtype=float)
                    if self.spec.pressure_noise:
                        p12 = p12 * (1.0 + self.spec.pressure_noise
                                     * rng.standard_normal(p12.shape))
                    curves.append((q, grid, p12))
                    continue
                # settled: the plant's 1 ms samples of the hold's last two READING_S windows;
                # the reading is the last window's mean, the settle check the one before
                n_hold = int(round(sch['hold_s'] / 1e-3))
                n_win = int(round(READING_S / 1e-3))
                p1, p2 = stepped_trace(grid, q, n_hold, int(round(1e-3 / c.dt_s)), p,
                                       c.dt_s, first=n_hold - 2 * n_win)
                p12 = p1 - p2
                if self.spec.pressure_noise:
                    p12 = p12 * (1.0 + self.spec.pressure_noise * rng.standard_normal(
                        p12.shape))
                curves.append((q, grid, np.array([window_mean(v) for v in p12[n_win:].T]),
                               np.array([window_mean(v) for v in p12[:n_win].T])))
            nominal = replace(default_params(), noise_std_a=0.0)
            # as the plant reports them at 1 kHz: one reading at start, one per test tick
            n_ticks = int(round(sch['hold_s'] * 1e3)) * sch['n_points'] * len(curves)
            cond = mean_conditions(measure_conditions(p, point.seed, n_ticks + 1,
                                                      load_bench())[1:])
            if self.spec.valve_test_procedure == 'settled':
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
            row.update(zip(('status', 'error'), _status(exc)))
        row['wall_s'] = row['wall_point_s'] = time.perf_counter() - t0
        return [row]


PROCEDURE_CLASSES = {'scenario': ScenarioProcedure, 'preflight_check': PreflightProcedure,
                     'valve_test': ValveTestProcedure}
