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
curvature of one minimum.  A Laplace deviation (``sigma^2 (J^T J)^-1``) of one least-squares
minimum states far less than the estimate's real error along that valley
(``bench/health.py`` measures both).  With a surrogate model (method ``surrogate-fit``) the
estimate is that least-squares fit.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from eha_ros.health.thresholds import HealthEstimate, HealthThresholds
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import WEAR_RANGES
from eha_ros.physics.params import ParameterError

__all__ = ['InServiceEstimator']


class InServiceEstimator:
    """Wear estimate from (XS, Q, P12) samples.

    By default (no ``model``: method ``steady-fit``) the estimate is the grid posterior of the
    module docstring, on the steady table (:mod:`eha_ros.health.steady_table`).  With a
    ``model`` (method ``surrogate-fit``) it is a least-squares fit instead: the best node of a
    coarse grid, then Levenberg-Marquardt, with a Laplace deviation.

    Parameters
    ----------
    params : PlantParams
        Physics of the valve (the wear values in it are ignored).
    model : callable, optional
        ``model(xs, q, overlap, clearance) -> p12`` broadcasting over arrays (a surrogate's
        ``p12``); default the steady table.
    coarse : int
        ``surrogate-fit``: points per axis of the coarse grid that picks the starting point.
    iterations : int
        ``surrogate-fit``: most Levenberg-Marquardt iterations from there.
    max_samples : int
        Samples used (evenly decimated from the most recent).
    limits : HealthThresholds, optional
        Limits whose posterior probabilities are reported, and the model bias that floors the
        likelihood's sigma (default ``config/health.yaml``).
    table : SteadyTable, optional
        Default: the shipped table, checked against ``params``.
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
            from eha_ros.health.steady_table import load_steady_table
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
        lap_g, clr_g = np.meshgrid(laps, clrs, indexing='ij')
        pred = self.model(xs[None, None, :], q[None, None, :], lap_g[..., None], clr_g[..., None])
        mse = np.mean((pred - p12[None, None, :]) ** 2, axis=2)
        i, j = np.unravel_index(np.argmin(mse), mse.shape)
        # 2. Levenberg-Marquardt from there, in micrometres, inside the swept ranges
        lo, hi = np.array([l0, c0]) * 1e6, np.array([l1, c1]) * 1e6
        x = np.array([laps[i], clrs[j]]) * 1e6
        scale = max(float(np.sqrt(np.mean(p12 ** 2))), 1e3)

        def resid(v):
            return (self.model(xs, q, v[0] * 1e-6, v[1] * 1e-6) - p12) / scale

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
        nominal = self.model(xs, q, self.params.overlap_supply_m,
                             self.params.radial_clearance_m) - p12
        return HealthEstimate(radial_clearance_m=float(x[1] * 1e-6),
                              radial_clearance_std_m=float(std[1]),
                              overlap_m=float(x[0] * 1e-6), overlap_std_m=float(std[0]),
                              pressure_residual_pa=float(np.sqrt(cost / xs.size) * scale),
                              samples_used=int(xs.size), method=self.method,
                              nominal_residual_pa=float(np.sqrt(np.mean(nominal ** 2))))
