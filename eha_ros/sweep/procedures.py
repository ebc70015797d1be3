"""The closed-loop scenario procedure, and the one table of the sweep's procedures.

:class:`ScenarioProcedure` (``scenario``): the closed loop on a scenario of
``config/scenarios.yaml``, controller at 1 kHz, every tick recorded (as the in-loop
comparison, :func:`eha_ros.evaluation.run`).  Metrics: the comparison's features
(:func:`eha_ros.evaluation.features`, one implementation) and, for a surrogate, the relative
errors of jack position and P12 against hf run at the same point.  With ``compare:
yardstick`` and noise off the point is :func:`eha_ros.evaluation.noise_free` (hf's yardstick,
the bounds, the features' spread); with noise on, hf is also run at seed + 1 (hf's
seed-to-seed spread) and with the discharge coefficient + 0.1 % (as
:func:`eha_ros.evaluation.with_noise`).

:data:`PROCEDURES` maps each name a spec's ``procedure`` may take to its class: this one, and
the pre-flight check and the valve test of :mod:`eha_ros.health.procedures`.  The base,
:class:`eha_ros.procedure.Procedure`, says what a procedure declares.  Timing columns are
named ``wall_*``.
"""

from __future__ import annotations

import time

import numpy as np

from eha_ros.evaluation import CONTROLLER_PERIOD_S, features, noise_free, run
from eha_ros.graph import DYNAMIC_MODELS
from eha_ros.health.procedures import PreflightProcedure, ValveTestProcedure
from eha_ros.physics import ParameterError, get_scenario, simulate
from eha_ros.physics.params import replace
from eha_ros.procedure import Procedure, status_of
from eha_ros.surrogates.base import relative_error

__all__ = ['PROCEDURES', 'ScenarioProcedure', 'FEATURES']

#: The in-loop comparison's features (:func:`eha_ros.evaluation.features`) and their types.
FEATURES = (('rms_tracking_error_m', 'float'), ('final_position_m', 'float'),
            ('stick_slip_steps', 'int'), ('mean_step_m', 'float'), ('p12_rms_pa', 'float'),
            ('p12_peak_pa', 'float'))


def _errors(r, ref) -> dict:
    return {'jack_rel_error': relative_error(r['jack_position_m'], ref['jack_position_m']),
            'p12_rel_error': relative_error(r['p12_pa'], ref['p12_pa'])}


def _converged_columns(c) -> dict:
    """A run's columns against the converged hf (``c`` from :func:`noise_free`; none
    without)."""
    return {} if c is None else {'converged_jack': c['jack'], 'converged_p12': c['p12'],
                                 'meets_bounds_converged': c['meets']}


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
            # against the converged hf (spec converged_dt; empty without); the check (hf at
            # twice its step against it) and whether it settled, on hf's row
            out += (('converged_jack', 'float'), ('converged_p12', 'float'),
                    ('meets_bounds_converged', 'bool'), ('converged_check_jack', 'float'),
                    ('converged_check_p12', 'float'), ('converged_settled', 'bool'))
        return out

    def columns(self) -> tuple:
        out = super().columns()
        if self.spec.compare == 'yardstick' and not self.spec.noise:  # hf's yardstick envelope
            out += tuple((f'signal_{s}_yardstick_{e}', 'floats')
                         for s in self.spec.signals for e in ('lo', 'hi'))
        return out

    def check(self, where: str) -> None:
        spec = self.spec
        if spec.compare == 'yardstick' and spec.noise and (spec.large_dts or spec.split_dts):
            raise ValueError(f'{where}: large_dts and split_dts are compared noise-free only')
        super().check(where)

    def run_point(self, point) -> list:
        if self.spec.compare == 'yardstick':
            return self._yardstick_noise(point) if self.spec.noise else self._yardstick(point)
        sc = point.scenario
        t0 = time.perf_counter()
        rows = {}
        ref = None
        try:
            p = point.params(self.spec)
        except ParameterError as exc:
            return [self._row(c, {}, *status_of(exc)) for c in point.cases]
        need_ref = any(c.model != 'hf' for c in point.cases)
        for c in sorted(point.cases, key=lambda c: c.model != 'hf'):  # hf first: the reference
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
                row = self._row(c, {}, *status_of(exc))
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
        p = self.spec.point_params({})
        runs = [(m, self.spec.dt_s, self.spec.integrator) for m in self.spec.models]
        if self.spec.split_dts:  # the split kernel compiles apart
            runs += [(m, self.spec.split_dts[0], 'split') for m in ('hf',) + self.spec.models
                     if m == 'hf' or m in DYNAMIC_MODELS]
        for m, dt, integrator in runs:
            simulate(p, self.spec.scenarios[0], duration_s=0.01, dt_s=dt,
                     controller_period_s=CONTROLLER_PERIOD_S, record_dt_s=None,
                     fluid=self.model(m), integrator=integrator)

    def _row(self, case, metrics, status, error=None, signals=None) -> dict:
        return {'case_id': case.case_id, 'model': case.model, 'dt_s': case.dt_s,
                'status': status, 'error': error, **metrics, **(signals or {})}

    def _yardstick(self, point) -> list:
        t0 = time.perf_counter()
        try:
            p = point.params(self.spec)
            sur = {m: self.model(m) for m in self.spec.models if m != 'hf'}
            out = noise_free(p, point.scenario, sur, self.spec.large_dts,
                             keep_runs=bool(self.spec.signals), split_dts=self.spec.split_dts,
                             converged_dt=self.spec.converged_dt)
        except Exception as exc:
            return [self._row(c, {}, *status_of(exc)) for c in point.cases]
        wall = time.perf_counter() - t0
        common = {'yardstick_jack': out['yardstick']['jack'],
                  'yardstick_p12': out['yardstick']['p12'],
                  'bound_jack': out['bound']['jack'], 'bound_p12': out['bound']['p12'],
                  **{f'spread_{f}': v for f, v in out['feature_spread'].items()}}
        conv = out.get('converged')
        hf_conv = {} if conv is None else {
            **_converged_columns(conv['hf']), 'converged_check_jack': conv['check']['jack'],
            'converged_check_p12': conv['check']['p12'], 'converged_settled': conv['settled']}
        duration = float(get_scenario(point.scenario).duration_s)
        runs = out.get('runs', {})
        rows = []
        for c in point.cases:
            if c.model == 'hf' and c.dt_s == self.spec.dt_s:
                row = self._row(c, {**out['hf_features'], **common, **hf_conv}, 'ok', None,
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
                                        'meets_bounds': r['meets'],
                                        **_converged_columns(r.get('converged'))}, 'ok',
                                    None,
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
            return [self._row(c, {}, *status_of(exc)) for c in point.cases]
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
                    row = self._row(c, {}, *status_of(exc))
                    row['wall_s'] = time.perf_counter() - t
            rows.append(row)
        wall = time.perf_counter() - t0
        duration = float(get_scenario(sc).duration_s)
        for row in rows:
            row['wall_point_s'] = wall
            row['wall_cost_s_per_s'] = row['wall_s'] / duration
        return rows


#: The procedures, by the name a spec's ``procedure`` gives.
PROCEDURES = {'scenario': ScenarioProcedure, 'preflight_check': PreflightProcedure,
              'valve_test': ValveTestProcedure}
