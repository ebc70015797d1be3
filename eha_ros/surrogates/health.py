"""Servovalve wear (radial clearance, overlap) from in-service samples, and health levels.

In service the jack moves as commanded and the plant reports spool position XS, load flow Q
and load pressure P12.  For a worn valve the relation P12(XS, Q) changes - the overlap shifts
and the clearance flattens the pressure gain near null - so the wear is the (overlap,
clearance) whose valve model best explains the samples::

    (overlap, clearance) = argmin  sum_k (P12_model(XS_k, Q_k; overlap, clearance) - P12_k)^2

The model is the valve's steady state (:func:`eha_ros.physics.maps.steady_map`, method
``steady-fit``) or any 4-input surrogate (method ``surrogate-fit``).  In service the valve is
quasi-static at the controller's pace, which the steady state describes; the reference's maps
(a 10 ms transient from zero pressure) do not settle near null and bias the estimate.

Estimate and uncertainty (the steady model, method ``steady-fit``): a posterior over the
wear grid of the precomputed steady-state table (:mod:`.steady_table`: overlap every 0.5 um,
clearance every 0.25 um over the swept ranges, uniform prior), with the likelihood of each
node ``exp(-n_eff mse / (2 sigma^2))``:

* ``sigma`` is the best node's RMS residual floored at ``model_bias_pa`` (the steady model's
  own misfit on a healthy valve in service): a fit closer than the model can be proves
  nothing, so it buys no precision;
* ``n_eff`` is the number of samples divided by the integrated autocorrelation time of the
  best node's residuals: consecutive samples of a smooth motion are not independent.

The estimate is the posterior mean, the deviation the posterior standard deviation (with the
grid's own resolution added), so a motion that leaves clearance and overlap trading off along
the valley gives a wide, correlated posterior - the message says so - instead of the sharp
curvature of one minimum.  This replaces a Levenberg-Marquardt fit with a Laplace deviation
(``sigma^2 (J^T J)^-1``), which stated 0.06-0.3 um on estimates 3 um off, and took seconds per
estimate (the steady state solved per sample); on the table an estimate takes milliseconds.
With a surrogate model (method ``surrogate-fit``) the former fit is kept.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from eha_ros.graph import LEVEL_ERROR as ERROR, LEVEL_OK as OK, LEVEL_WARN as WARN
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import WEAR_RANGES, steady_map
from eha_ros.physics.params import ParameterError, read_yaml

__all__ = ['HealthEstimate', 'InServiceEstimator', 'ValveTestEstimator', 'HealthThresholds',
           'FaultLimit', 'classify', 'classify_fault', 'OK', 'WARN', 'ERROR']


@dataclasses.dataclass
class HealthEstimate:
    radial_clearance_m: float
    radial_clearance_std_m: float
    overlap_m: float
    overlap_std_m: float
    pressure_residual_pa: float
    samples_used: int
    method: str
    #: RMS residual [Pa] of the nominal valve (the parameters' wear) on the same samples; NaN
    #: where not computed.  Its ratio to ``pressure_residual_pa`` tells whether the data reject
    #: the nominal valve at all (:func:`classify`).
    nominal_residual_pa: float = float('nan')
    #: Correlation of the clearance and overlap estimates (NaN where not computed).
    correlation: float = float('nan')
    #: Posterior probabilities (in-service grid posterior) that the wear is beyond the warn and
    #: error limits of ``config/health.yaml``: ``{'clearance_warn': p, ...}``; empty otherwise.
    beyond: dict = dataclasses.field(default_factory=dict)


class InServiceEstimator:
    """Least-squares wear estimate from (XS, Q, P12) samples.

    Parameters
    ----------
    params : PlantParams
        Physics of the valve (the wear values in it are ignored).
    model : callable, optional
        ``model(xs, q, overlap, clearance) -> p12`` broadcasting over arrays (a surrogate's
        ``p12``); default the steady-state valve solution.
    coarse : int
        Points per axis of the coarse grid that picks the starting point.
    iterations : int
        Most Levenberg-Marquardt iterations from there.
    max_samples : int
        Samples used (evenly decimated from the most recent).
    """

    def __init__(self, params: PlantParams | None = None, model: Callable | None = None,
                 coarse: int = 7, iterations: int = 30, max_samples: int = 200,
                 limits: 'HealthThresholds | None' = None, table=None):
        self.params = params if params is not None else default_params()
        self.model = model
        self.method = 'steady-fit' if model is None else 'surrogate-fit'
        self.coarse = coarse
        self.iterations = iterations
        self.max_samples = max_samples
        self.limits = limits if limits is not None else HealthThresholds.load()
        self.table = None
        if model is None:
            from .steady_table import load_steady_table
            self.table = table if table is not None else load_steady_table(self.params)

    def _grid_estimate(self, xs, q, p12) -> HealthEstimate:
        """Posterior over the steady table's wear grid (see the module docstring)."""
        t = self.table
        ok = t.inside(xs, q)
        xs, q, p12 = xs[ok], q[ok], p12[ok]
        if xs.size < 10:
            raise ParameterError(f'{xs.size} samples inside the steady table (spool within '
                                 f'+-{t.xs_m[-1] * 1e6:g} um, flow within '
                                 f'+-{t.q_m3_s[-1] * 1e6:g} cm^3/s): at least 10 are needed')
        if xs.size > self.max_samples:
            keep = np.linspace(0, xs.size - 1, self.max_samples).round().astype(int)
            xs, q, p12 = xs[keep], q[keep], p12[keep]
        n = xs.size
        res = t.p12_at_nodes(xs, q) - p12
        mse = np.mean(res ** 2, axis=2)
        i, j = np.unravel_index(np.argmin(mse), mse.shape)
        r = res[i, j] - res[i, j].mean()
        acf = np.correlate(r, r, mode='full')[n - 1:] / max(float(r @ r), 1e-300)
        neg = np.flatnonzero(acf <= 0)
        tau = float(min(max(1.0 + 2.0 * acf[1:neg[0] if neg.size else n].sum(), 1.0), n))
        n_eff = n / tau
        sigma2 = max(float(mse[i, j]), self.limits.model_bias_pa ** 2) * (
            self.limits.likelihood_temperature)
        logw = -0.5 * n_eff * (mse - mse[i, j]) / sigma2
        w = np.exp(logw)
        w /= w.sum()
        lg, cg = np.meshgrid(t.overlap_m, t.clearance_m, indexing='ij')
        m_l, m_c = float(np.sum(w * lg)), float(np.sum(w * cg))
        v_l = float(np.sum(w * (lg - m_l) ** 2))
        v_c = float(np.sum(w * (cg - m_c) ** 2))
        cov = float(np.sum(w * (lg - m_l) * (cg - m_c)))
        rho = cov / np.sqrt(max(v_l * v_c, 1e-300))
        # the grid's resolution: a node stands for a cell of its step
        s_l = np.sqrt(v_l + np.diff(t.overlap_m[:2])[0] ** 2 / 12)
        s_c = np.sqrt(v_c + np.diff(t.clearance_m[:2])[0] ** 2 / 12)
        lim = self.limits
        beyond = {'clearance_warn': float(np.sum(w[cg >= lim.clearance_warn_m])),
                  'clearance_error': float(np.sum(w[cg >= lim.clearance_error_m])),
                  'overlap_warn': float(np.sum(w[lg <= lim.overlap_warn_m])),
                  'overlap_error': float(np.sum(w[lg <= lim.overlap_error_m]))}
        a = int(np.argmin(np.abs(t.overlap_m - self.params.overlap_supply_m)))
        b = int(np.argmin(np.abs(t.clearance_m - self.params.radial_clearance_m)))
        return HealthEstimate(radial_clearance_m=m_c, radial_clearance_std_m=float(s_c),
                              overlap_m=m_l, overlap_std_m=float(s_l),
                              pressure_residual_pa=float(np.sqrt(mse[i, j])), samples_used=n,
                              method=self.method,
                              nominal_residual_pa=float(np.sqrt(mse[a, b])),
                              correlation=float(rho), beyond=beyond)

    def _predict(self, xs, q, lap, clr):
        if self.model is None:
            return steady_map(xs, q, lap, clr, params=self.params)['p12_pa']
        return self.model(xs, q, lap, clr)

    def _residuals(self, xs, q, p12, laps, clrs):
        lap_g, clr_g = np.meshgrid(laps, clrs, indexing='ij')
        pred = self._predict(xs[None, None, :], q[None, None, :], lap_g[..., None],
                             clr_g[..., None])
        return np.mean((pred - p12[None, None, :]) ** 2, axis=2), lap_g, clr_g

    def estimate(self, xs_m, q_m3_s, p12_pa) -> HealthEstimate:
        xs, q, p12 = (np.asarray(a, dtype=float).ravel() for a in (xs_m, q_m3_s, p12_pa))
        ok = np.isfinite(xs) & np.isfinite(q) & np.isfinite(p12)
        xs, q, p12 = xs[ok], q[ok], p12[ok]
        if xs.size < 10:
            raise ParameterError(f'{xs.size} usable samples: at least 10 are needed')
        if self.table is not None:
            return self._grid_estimate(xs, q, p12)
        if xs.size > self.max_samples:
            keep = np.linspace(0, xs.size - 1, self.max_samples).round().astype(int)
            xs, q, p12 = xs[keep], q[keep], p12[keep]
        (l0, l1), (c0, c1) = WEAR_RANGES['overlap_m'], WEAR_RANGES['radial_clearance_m']
        # 1. coarse grid: the basin of the global minimum
        laps = np.linspace(l0, l1, self.coarse)
        clrs = np.linspace(c0, c1, self.coarse)
        mse, lg, cg = self._residuals(xs, q, p12, laps, clrs)
        i, j = np.unravel_index(np.argmin(mse), mse.shape)
        # 2. Levenberg-Marquardt from there, in micrometres, inside the swept ranges
        lo, hi = np.array([l0, c0]) * 1e6, np.array([l1, c1]) * 1e6
        x = np.array([laps[i], clrs[j]]) * 1e6
        scale = max(float(np.sqrt(np.mean(p12 ** 2))), 1e3)

        def resid(v):
            return (self._predict(xs, q, v[0] * 1e-6, v[1] * 1e-6) - p12) / scale

        r = resid(x)
        cost = float(r @ r)
        lam = 1e-2
        jac = None
        for _ in range(self.iterations):
            h = 1e-3
            jac = np.stack([(resid(x + h * e) - r) / h for e in np.eye(2)], axis=1)
            g = jac.T @ r
            a = jac.T @ jac
            step = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-12), -g)
            x_new = np.clip(x + step, lo, hi)
            r_new = resid(x_new)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                converged = abs(cost - cost_new) <= 1e-10 * cost or np.all(
                    np.abs(x_new - x) < 1e-5)
                x, r, cost, lam = x_new, r_new, cost_new, max(lam / 10, 1e-9)
                if converged:
                    break
            else:
                lam *= 10
                if lam > 1e8:
                    break
        # 3. uncertainty: sigma^2 (J^T J)^-1 with sigma^2 from the residual
        dof = max(xs.size - 2, 1)
        sigma2 = cost / dof
        try:
            cov = np.linalg.inv(jac.T @ jac) * sigma2 if jac is not None else np.full((2, 2),
                                                                                        np.nan)
        except np.linalg.LinAlgError:
            cov = np.full((2, 2), np.inf)
        std = np.sqrt(np.abs(np.diag(cov))) * 1e-6
        nominal = self._predict(xs, q, self.params.overlap_supply_m,
                                self.params.radial_clearance_m) - p12
        return HealthEstimate(radial_clearance_m=float(x[1] * 1e-6),
                              radial_clearance_std_m=float(std[1]),
                              overlap_m=float(x[0] * 1e-6), overlap_std_m=float(std[0]),
                              pressure_residual_pa=float(np.sqrt(cost / xs.size) * scale),
                              samples_used=int(xs.size), method=self.method,
                              nominal_residual_pa=float(np.sqrt(np.mean(nominal ** 2))))


class ValveTestEstimator:
    """Wear from the P12 curves of a diagnostic valve test (:mod:`eha_ros.physics.valve_test`)
    by the diagnostic network (:mod:`.diagnostics`), method ``diagnostic-network``.

    One estimate per curve; the wear is their median and the uncertainty their standard
    deviation, floored at the network's RMS error on held-out clean maps (recorded in its
    artefact).  The residual is the RMS difference between the measured
    curves and the map model at the estimated wear: it tells whether the network's answer
    explains the data (a curve outside what the network was trained on does not).

    Parameters
    ----------
    params : PlantParams
        Physics of the valve: the network must have been built for its fluid parameters.
    model : DiagnosticModel, optional
        Default: the shipped network, checked against ``params``.
    """

    method = 'diagnostic-network'

    def __init__(self, params: PlantParams | None = None, model=None):
        from .diagnostics import load_diagnostic
        self.params = params if params is not None else default_params()
        self.model = model if model is not None else load_diagnostic(self.params)

    def estimate(self, curves) -> HealthEstimate:
        """``curves``: ``(q_m3_s, xs_m, p12_pa)`` per flow, the spool positions [m] in
        increasing order (resampled onto the network's grid if they are not it)."""
        from eha_ros.physics.maps import transient_map
        from eha_ros.physics.params import replace

        from .diagnostics import estimate_wear
        curves = [(float(q), np.asarray(xs, dtype=float), np.asarray(p, dtype=float))
                  for q, xs, p in curves]
        if not curves:
            raise ParameterError('no complete valve-test curve')
        grid = self.model.xs_m
        est = [estimate_wear(p, q, model=self.model, xs_m=None if np.array_equal(xs, grid)
                             else xs) for q, xs, p in curves]
        c = np.array([e[0] for e in est])
        o = np.array([e[1] for e in est])
        clr, lap = float(np.median(c)), float(np.median(o))
        lo, hi = WEAR_RANGES['radial_clearance_m']
        model_params = replace(self.params, radial_clearance_m=float(np.clip(clr, lo * 0.5,
                                                                              hi * 2)),
                               overlap_supply_m=lap, overlap_return_m=lap)
        r2, n = 0.0, 0
        for q, xs, p in curves:
            pred = transient_map(xs, q, params=model_params)['p12_pa']
            r2 += float(np.sum((pred - p) ** 2))
            n += p.size
        # the curves' spread, floored at the network's own held-out error: on clean curves (per
        # map, or per curve over the root of the curves used, whichever is larger), plus
        # the per-curve error at 1 % noise scaled by the noise the data show (measurement
        # noise biases the estimate, the same way on every curve, so their spread misses it;
        # the map model's relative residual at the estimate is 0.8x the noise level)
        (l0, l1), (c0, c1) = WEAR_RANGES['overlap_m'], WEAR_RANGES['radial_clearance_m']
        errs = self.model.meta.get('errors', {})
        clean, noisy = errs.get('clean', {}), errs.get('noise_1pct', {})
        p_rms = float(np.sqrt(np.mean(np.concatenate([p for _, _, p in curves]) ** 2)))
        noise = np.sqrt(r2 / n) / max(p_rms, 1e-9) / 0.01     # in units of 1 %
        k = np.sqrt(len(curves))   # the per-map error of the held-out maps used 15 curves

        def floor(name, span):
            clean_err = max(clean.get(f'{name}_map', {}).get('rms', 0.0),
                            clean.get(f'{name}_curve', {}).get('rms', 0.0) / k)
            return np.hypot(clean_err, noise * noisy.get(f'{name}_curve', {}).get('rms', 0.0)
                            ) / 100 * span
        floor_c = floor('clearance', c1 - c0)
        floor_o = floor('overlap', l1 - l0)
        return HealthEstimate(radial_clearance_m=clr,
                              radial_clearance_std_m=float(np.hypot(np.std(c), floor_c)),
                              overlap_m=lap, overlap_std_m=float(np.hypot(np.std(o), floor_o)),
                              pressure_residual_pa=float(np.sqrt(r2 / n)), samples_used=n,
                              method=self.method)


@dataclasses.dataclass(frozen=True)
class FaultLimit:
    """Warn and error limits of one fault of the pre-flight check (``faults:`` in
    ``config/health.yaml``); ``absolute``: the limits apply to the magnitude (an offset of
    either sign)."""

    name: str
    warn: float
    error: float
    absolute: bool
    reason: str


@dataclasses.dataclass(frozen=True)
class HealthThresholds:
    """Limits of the health levels (``config/health.yaml``)."""

    clearance_warn_m: float
    clearance_error_m: float
    overlap_warn_m: float
    overlap_error_m: float
    residual_error_pa: float
    anomaly_ratio: float
    model_bias_pa: float
    evidence_probability: float
    separable_correlation: float
    stale_after_s: float
    likelihood_temperature: float = 1.0
    faults: tuple = ()

    @classmethod
    def load(cls, path=None) -> 'HealthThresholds':
        from eha_ros.physics.params import config_dir
        path = path or config_dir() / 'health.yaml'
        doc = read_yaml(path, 'health threshold')
        fields = [f.name for f in dataclasses.fields(cls) if f.name != 'faults']
        if not isinstance(doc, dict):
            raise ParameterError(f'malformed health threshold file {path}: expected a mapping')
        missing = [f for f in fields if f not in doc]
        unknown = sorted(set(doc) - set(fields) - {'faults'})
        if missing or unknown:
            what = f'missing {missing[0]}' if missing else f'unknown {unknown[0]}'
            raise ParameterError(f'{path}: {what}')
        try:
            values = {f: float(doc[f]['value'] if isinstance(doc[f], dict) else doc[f])
                      for f in fields}
        except (TypeError, ValueError, KeyError):
            raise ParameterError(f'{path}: every threshold must be a number') from None
        faults = []
        for name, spec in (doc.get('faults') or {}).items():
            try:
                lim = FaultLimit(str(name), float(spec['warn']), float(spec['error']),
                                 bool(spec.get('absolute', False)), str(spec.get('reason', '')))
            except (TypeError, ValueError, KeyError):
                raise ParameterError(f'{path}: faults: {name} needs numeric warn and error'
                                     ) from None
            if not lim.warn < lim.error:
                raise ParameterError(f'{path}: faults: {name}: need warn < error')
            faults.append(lim)
        t = cls(**values, faults=tuple(faults))
        if not (t.clearance_warn_m < t.clearance_error_m and t.overlap_error_m
                < t.overlap_warn_m and t.residual_error_pa > 0 and t.anomaly_ratio >= 1
                and t.model_bias_pa > 0):
            raise ParameterError(f'{path}: need clearance_warn < clearance_error, overlap_error '
                                 '< overlap_warn, positive residual limit and model bias and an '
                                 'anomaly ratio of at least 1')
        if not (t.likelihood_temperature >= 1):
            raise ParameterError(f'{path}: likelihood_temperature must be at least 1')
        if not (0.5 <= t.evidence_probability < 1 and 0 < t.separable_correlation <= 1
                and t.stale_after_s > 0):
            raise ParameterError(f'{path}: need evidence_probability in [0.5, 1), '
                                 'separable_correlation in (0, 1] and a positive stale_after_s')
        return t

    def fault(self, name: str) -> 'FaultLimit | None':
        return next((f for f in self.faults if f.name == name), None)


def _z(probability: float) -> float:
    """One-sided Gaussian quantile of ``probability`` (0.5 .. 0.999)."""
    from statistics import NormalDist
    return NormalDist().inv_cdf(probability)


def classify_fault(name: str, value: float, std: float, limits: HealthThresholds
                   ) -> tuple[int, str]:
    """Level and reason of one pre-flight estimate: a limit counts as passed only when the
    estimate is beyond it by ``z`` standard deviations (``z`` from ``evidence_probability``,
    1.64 for 0.95): levels are raised on evidence."""
    lim = limits.fault(name)
    if lim is None:
        return OK, f'{name} = {value:.4g} +- {std:.2g} (no limits configured)'
    z = _z(limits.evidence_probability)
    v = abs(value) if lim.absolute else value
    low = v - z * std
    what = f'|{name}|' if lim.absolute else name
    text = f'{what} = {v:.4g} +- {std:.2g}'
    if low >= lim.error:
        return ERROR, f'{text}: beyond the error limit {lim.error:g} ({lim.reason})'
    if low >= lim.warn:
        return WARN, f'{text}: beyond the warn limit {lim.warn:g} ({lim.reason})'
    if v >= lim.warn:
        return OK, (f'{text}: above the warn limit {lim.warn:g} but not by '
                    f'{z:.2f} sigma: not proven')
    return OK, f'{text}: within limits (warn {lim.warn:g})'


def classify(est: HealthEstimate, limits: HealthThresholds) -> tuple[int, str]:
    """Level (OK/WARN/ERROR) and a one-line reason.

    An in-service estimate (``nominal_residual_pa`` known) raises a level only when the data
    reject the nominal valve: its residual at least ``anomaly_ratio`` times the best fit's, or
    times ``model_bias_pa`` if that is larger (a fit better than the model's own bias on a
    healthy valve proves nothing).
    Below that the motion did not excite the valve enough to tell its wear apart from nominal
    (small or slow commands keep the spool inside the overlap, where clearance and overlap
    trade off), and the estimate is reported as such, level OK.  Above it a wear limit counts
    only when the posterior puts at least ``evidence_probability`` beyond it; with the wear
    not pinned down the valve deviates in a way the data do not resolve: WARN, run a valve
    test.  When clearance and overlap trade off (their correlation beyond
    ``separable_correlation``) the message says so.
    """
    if est.pressure_residual_pa > limits.residual_error_pa:
        return ERROR, (f'valve model does not explain the data (residual '
                       f'{est.pressure_residual_pa / 1e6:.2f} MPa)')
    c_um, o_um = est.radial_clearance_m * 1e6, est.overlap_m * 1e6
    sc, so = est.radial_clearance_std_m * 1e6, est.overlap_std_m * 1e6
    fit = f'clearance {c_um:.2f} +- {sc:.2f} um, overlap {o_um:.2f} +- {so:.2f} um'
    if np.isfinite(est.correlation):
        (l0, l1), (c0, c1) = WEAR_RANGES['overlap_m'], WEAR_RANGES['radial_clearance_m']
        vague = (est.radial_clearance_std_m > 0.5 * (c1 - c0) / np.sqrt(12)
                 or est.overlap_std_m > 0.5 * (l1 - l0) / np.sqrt(12))
        if abs(est.correlation) >= limits.separable_correlation:
            fit += (f' (not separable from this motion: correlation {est.correlation:+.2f}, '
                    'they trade off)')
        elif vague:
            fit += (' (not separable from this motion: deviations over half the prior\'s, the '
                    'data barely constrain the wear)')
    ratio = est.nominal_residual_pa / max(est.pressure_residual_pa, limits.model_bias_pa)
    if np.isfinite(ratio) and ratio < limits.anomaly_ratio:
        return OK, (f'consistent with the nominal valve (its residual {ratio:.1f}x the best '
                    f'fit\'s, limit {limits.anomaly_ratio:g}x); {fit}')
    if est.beyond:
        pe = limits.evidence_probability
        b = est.beyond
        if b['clearance_error'] >= pe:
            return ERROR, (f'radial clearance beyond {limits.clearance_error_m * 1e6:g} um '
                           f'(probability {b["clearance_error"]:.2f}): replace the valve; {fit}')
        if b['overlap_error'] >= pe:
            return ERROR, (f'overlap below {limits.overlap_error_m * 1e6:g} um (probability '
                           f'{b["overlap_error"]:.2f}): metering edges worn, replace the valve; '
                           f'{fit}')
        if b['clearance_warn'] >= pe:
            return WARN, (f'radial clearance beyond {limits.clearance_warn_m * 1e6:g} um '
                          f'(probability {b["clearance_warn"]:.2f}): plan maintenance; {fit}')
        if b['overlap_warn'] >= pe:
            return WARN, (f'overlap below {limits.overlap_warn_m * 1e6:g} um (probability '
                          f'{b["overlap_warn"]:.2f}): plan maintenance; {fit}')
        return WARN, (f'valve deviates from nominal (its residual {ratio:.1f}x the best fit\'s) '
                      f'but the data do not pin the wear beyond a limit: run a valve test; {fit}')
    if est.radial_clearance_m >= limits.clearance_error_m:
        return ERROR, f'radial clearance {c_um:.2f} um beyond its limit: replace the valve'
    if est.overlap_m <= limits.overlap_error_m:
        return ERROR, f'overlap {o_um:.2f} um: metering edges worn, replace the valve'
    if est.radial_clearance_m >= limits.clearance_warn_m:
        return WARN, f'radial clearance {c_um:.2f} um rising: plan maintenance'
    if est.overlap_m <= limits.overlap_warn_m:
        return WARN, f'overlap {o_um:.2f} um falling: plan maintenance'
    if np.isfinite(ratio):
        return WARN, (f'valve deviates from nominal (its residual {ratio:.1f}x the best fit\'s) '
                      f'but the fit ({fit}) is within limits: run a valve test')
    return OK, f'{fit}: within limits'
