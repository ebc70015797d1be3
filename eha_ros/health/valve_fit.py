"""Wear from the settled valve test (:mod:`eha_ros.physics.maintenance`, procedure
``settled``): the valve model fitted to the measured curves at the measured test conditions.

What is measured and what is not
    The bench measures supply and return pressure and the fluid temperature
    (:mod:`eha_ros.physics.bench`); the fit takes them as inputs (the fluid's viscosity and
    density from its temperature by the datasheet law).  The settled pressures are the steady
    map (:func:`eha_ros.physics.maps.steady_map`), which the bulk modulus does not enter.
    What a real unit does not share with the model enters the maps through few groups, and
    the fit has one variable for each:

    * the metering edges' flow coefficient ``kappa = Cd (1 - Khsv) w / (Cd w)_nominal``:
      silting (Khsv), the unit's discharge coefficient and port width act alike, so Khsv is
      read as ``1 - kappa / E[Cd w / (Cd w)_nominal]``, its deviation widened by that
      ratio's unit-to-unit spread (``config/tolerances.yaml``);
    * the Cd law's critical flow number (a model uncertainty, 30-1000), fitted on a log
      scale;
    * the laminar factor, the covered edges' leakage gain over the model's: the fluid's
      condition over the port width's and the eccentricity's gain ``(1 + 1.5 e^2)``.  The
      test cannot tell it from the clearance (the leakage goes as ``c^3`` times it), so it is
      fitted with its prior from the tolerances (:func:`unit_priors`), and the clearance's
      deviation carries it;
    * the jack's piston leakage (the test circuit's ports are the jack's), near null;
    * the supply pressure's calibration error, with its sensor's prior.

Fit
    Weighted least squares (:func:`scipy.optimize.least_squares`) of the steady P12 on the
    points whose measured |P12| lies below 95 % of the measured supply-return difference (a
    blocked chamber at a flow is beyond what a bench's relief lets through), weights
    ``1 / (0.01 |P12| + 20 kPa)``: in units of a 1 % measurement noise.  Starts: a grid of
    clearance, overlap and critical flow number (4 x 4 x 2), the best three refined.  A
    point's reading is the mean of its P12 samples over the last tenth of its hold; points
    that had not settled (that mean differs from the previous tenth's) are left out.

Uncertainty
    The fit's covariance (scaled by its own residual where that exceeds the weights' noise),
    plus the conditions' sensor errors (calibration error uniform within the sensor's bias,
    ``config/test_bench.yaml``) propagated through the fit's linearisation, times a
    calibration factor per parameter (at least 1) that put 95 % of a held-out drawn fleet
    (every nuisance of ``config/tolerances.yaml``) within 2 sigma (``valve_fit.npz``,
    :mod:`eha_ros.training.valve_fit`).

Model-mismatch test
    ``chi``, the weighted RMS residual per degree of freedom, against the limit found on the
    held-out fleet; measured conditions outside the service range; Khsv beyond its envelope
    (either side).  Beyond any of them the estimate says the valve model does not explain the
    test, and why, and the deviations widen to the range's (:attr:`HealthEstimate.mismatch`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np

from eha_ros.artefacts import ArtefactError, CachedReader, load_artefact, models_dir
from eha_ros.health.thresholds import HealthEstimate
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.bench import (CONDITIONS, Conditions, load_bench, true_conditions,
                                   with_conditions)
from eha_ros.physics.maps import WEAR_RANGES, steady_map
from eha_ros.physics.params import ParameterError, replace

__all__ = ['read_calibration', 'ValveFitEstimator', 'FitCalibration', 'load_calibration',
           'FIT_NAMES', 'FIT_FILE', 'fit_curves']

FIT_FILE = 'valve_fit.npz'
REBUILD = 'eha_ros.training.valve_fit'
#: The fitted parameters (plant names).
FIT_NAMES = ('radial_clearance_m', 'overlap_supply_m', 'valve_degradation',
             'leakage_coeff_m3_s_pa')
_NOISE_REL = 0.01
_NOISE_FLOOR_PA = 2e4
_BAND = 1.05
#: A point's reading is the mean of its P12 samples over the last ``READING_S`` of its hold
#: (:func:`window_mean`); it counts as settled when that reading differs from the mean over
#: the ``READING_S`` before by at most ``SETTLED_REL`` of itself plus ``SETTLED_ABS_PA``
#: (plus the measurement noise the pairs show).
READING_S = 0.01
SETTLED_REL = 0.002
SETTLED_ABS_PA = 2e3


def window_mean(samples) -> float:
    """The mean of a window's samples, exactly rounded (``math.fsum``): the same number
    whatever their order, live or from a sweep."""
    samples = [float(x) for x in samples]
    return math.fsum(samples) / len(samples) if samples else math.nan


_SUPPLY_UNIT_PA = 1e4
#: The fit's maps to this relative tolerance (:func:`~eha_ros.physics.maps.steady_map`'s
#: Illinois solver, a tenth of the bisections' cost): far below the finite-difference steps.
_MAP_RTOL = 1e-10
# fit variables: clearance [um], overlap [um], kappa (the metering edges' flow coefficient
# Cd (1 - Khsv) w over the nominal Cd w), log10 of the Cd law's critical flow number, jack
# leakage [1e-13 m^3/(s Pa)], supply pressure less its reading [10 kPa], log10 of the
# laminar factor (module docstring)
_LO = np.array([0.3, -5.0, 0.3, np.log10(15.0), 0.0, -50.0, -0.5])
_HI = np.array([10.0, 10.0, 1.3, np.log10(3000.0), 100.0, 50.0, 0.5])
_SCALE = np.array([1.0, 1.0, 0.05, 0.2, 1.0, 1.0, 0.02])
_UNITS = np.array([1e-6, 1e-6, 1.0, 1e-13])
_START_C = (1.2, 2.5, 4.0, 5.5)
_START_O = (-1.5, 1.0, 3.5, 6.0)
_START_LC = (60.0, 400.0)
#: Starts refined by least squares (the best of the grid by cost).
_REFINED = 3
#: Draws of the unit-to-unit priors (:func:`unit_priors`), from a stream of their own.
_PRIOR_DRAWS = 20000
_PRIOR_STREAM = 0x7A1F


@functools.lru_cache(maxsize=4)
def _priors(tol_path: str, p: PlantParams) -> dict:
    from eha_ros.physics.tolerances import load_tolerances
    tol = load_tolerances(tol_path)
    rng = np.random.default_rng(_PRIOR_STREAM)

    def factor(name):   # the parameter's drawn value over its nominal
        t = tol[name]
        if t.klass not in ('nuisance', 'negligible'):
            return np.ones(_PRIOR_DRAWS)
        lo, hi = t.bounds(p)
        v = rng.uniform(lo, hi, _PRIOR_DRAWS)
        nominal = getattr(p, name)
        return v / nominal if nominal else v

    width = factor('port_width_m')
    cd = factor('discharge_coefficient')
    ecc = tol['eccentricity_ratio']
    e = (rng.uniform(*ecc.bounds(p), _PRIOR_DRAWS) if ecc.klass in ('nuisance', 'negligible')
         else np.full(_PRIOR_DRAWS, p.eccentricity_ratio))
    cond = factor('fluid_condition_factor') * p.fluid_condition_factor
    e0 = 1.0 + 1.5 * p.eccentricity_ratio ** 2
    laminar = np.log10(cond / (width * (1.0 + 1.5 * e * e) / e0))
    edge = cd * width
    return {'laminar': (float(laminar.mean()), float(laminar.std())),
            'edge': (float(edge.mean()), float(edge.std()))}


def unit_priors(params: PlantParams | None = None, tolerances=None) -> dict:
    """The unit-to-unit spread the valve test cannot see, from ``config/tolerances.yaml``
    (module docstring): ``laminar`` (mean, std) of log10 of the laminar factor, the fluid's
    condition over the port width's and the eccentricity's leakage gain; ``edge`` (mean, std)
    of the metering edges' Cd w over nominal, which sets Khsv's reading."""
    from eha_ros.physics.params import config_dir
    return _priors(str(tolerances or config_dir() / 'tolerances.yaml'),
                   params or default_params())


@dataclasses.dataclass(frozen=True)
class FitCalibration:
    """Calibration of :class:`ValveFitEstimator` from drifted held-out tests."""

    factors: np.ndarray      # per FIT_NAMES, >= 1
    chi_limit: float         # mismatch beyond this chi
    meta: dict


def load_calibration(path: Path | None = None) -> FitCalibration:
    """The shipped calibration (:data:`FIT_FILE`)."""
    path = Path(path) if path is not None else models_dir('health') / FIT_FILE
    return read_calibration(path)


def _read_calibration(path: Path) -> FitCalibration:
    (factors, chi), meta = load_artefact(path, REBUILD)
    if meta.get('kind') != 'valve_fit' or factors.shape != (len(FIT_NAMES),):
        raise ArtefactError(f'{path}: not a valve-fit calibration')
    return FitCalibration(np.asarray(factors, dtype=float), float(np.ravel(chi)[0]), meta)


#: :func:`load_calibration`'s reader, once per state of the file
#: (:class:`.artefacts.CachedReader`).
read_calibration = CachedReader(_read_calibration)


def _params(base: PlantParams, theta) -> PlantParams:
    """The plant parameters of fit variables ``theta`` (all but the supply offset) about
    ``base`` at the test's conditions: Khsv 0, the edges' coefficient in Cd, the laminar
    factor in the fluid's condition."""
    c, o, kappa, log_lc, leak, log_lam = (float(v) for v in theta)
    return replace(base, radial_clearance_m=c * 1e-6, overlap_supply_m=o * 1e-6,
                   overlap_return_m=o * 1e-6, valve_degradation=0.0,
                   discharge_coefficient=min(base.discharge_coefficient * kappa, 1.0),
                   critical_flow_number=10.0 ** log_lc, leakage_coeff_m3_s_pa=leak * 1e-13,
                   fluid_condition_factor=base.fluid_condition_factor * 10.0 ** log_lam)


def _points(curves, cond: Conditions):
    """The fitted points: inside the bench's pressure range and, where the curves carry the
    pressure a tenth of the hold before its end, settled: moved by at most ``SETTLED_REL``
    of itself plus ``SETTLED_ABS_PA``, plus three times the measurement noise the pairs
    show (their median relative difference over 0.674 x sqrt 2)."""
    checked = [(np.asarray(c[2], dtype=float), np.asarray(c[3], dtype=float))
               for c in curves if len(c) > 3 and c[3] is not None]
    noise_rel = 0.0
    if checked:
        end, before = (np.concatenate(a) for a in zip(*checked))
        ok = np.isfinite(before) & (np.abs(end) > 10 * SETTLED_ABS_PA)
        if ok.any():
            rel = np.abs(end[ok] - before[ok]) / np.abs(end[ok])
            noise_rel = float(np.median(rel)) / (0.674 * np.sqrt(2.0))
    xs, q, p12, unsettled = [], [], [], 0
    for c in curves:
        x, p = np.asarray(c[1], dtype=float), np.asarray(c[2], dtype=float)
        keep = np.ones(p.size, dtype=bool)
        if len(c) > 3 and c[3] is not None:
            before = np.asarray(c[3], dtype=float)
            tol = (SETTLED_REL + 3.0 * np.sqrt(2.0) * noise_rel) * np.abs(p) + SETTLED_ABS_PA
            keep = np.isnan(before) | (np.abs(p - before) <= tol)
            unsettled += int(np.sum(~keep))
        xs.append(x[keep])
        p12.append(p[keep])
        q.append(np.full(int(keep.sum()), float(c[0])))
    xs, q, p12 = (np.concatenate(a) for a in (xs, q, p12))
    if not (np.all(np.isfinite(p12)) and np.all(np.isfinite(xs))):
        raise ParameterError('valve test: the curves must be finite')
    n_all = sum(np.size(c[2]) for c in curves)
    keep = np.abs(p12) <= _BAND * (cond.supply_pressure_pa - cond.return_pressure_pa)
    return xs[keep], q[keep], p12[keep], n_all, unsettled


def fit_curves(curves, cond: Conditions, base: PlantParams, bench=None,
               supply_std_pa: float | None = None, laminar_prior=None) -> dict:
    """The weighted least-squares fit (module docstring): ``theta`` (clearance [um],
    overlap [um], the edges' flow coefficient kappa, log10 critical flow number, jack leakage
    [1e-13 m^3/(s Pa)], supply pressure less its reading [10 kPa], log10 laminar factor), its
    covariance, ``chi``, the RMS residual [Pa], the points used and the
    sensitivities of ``theta`` to the other measured conditions.  ``supply_std_pa``: the
    prior deviation of the supply pressure about ``cond``'s (default: its sensor's);
    ``laminar_prior``: (mean, std) of log10 of the laminar factor (default: the fleet's,
    :func:`unit_priors`)."""
    from scipy.optimize import least_squares
    b = bench or load_bench()
    xs, q, p12, n_all, unsettled = _points(curves, cond)
    if xs.size < 10:
        raise ParameterError(f'valve test: {xs.size} of {n_all} points settled inside the '
                             'measured supply-return range: too few to fit')
    w = 1.0 / (_NOISE_REL * np.abs(p12) + _NOISE_FLOOR_PA)
    if supply_std_pa is None:   # the transducer's calibration error, uniform
        supply_std_pa = b.sensors['supply_pressure_pa'].bias / np.sqrt(3.0)
    s_ps = supply_std_pa / _SUPPLY_UNIT_PA
    lam_mean, lam_std = (unit_priors(base)['laminar'] if laminar_prior is None
                         else (float(laminar_prior[0]), float(laminar_prior[1])))
    lam_std = max(lam_std, 1e-6)

    def resid(theta, c=cond):
        at = with_conditions(base, dataclasses.replace(
            c, supply_pressure_pa=c.supply_pressure_pa + theta[5] * _SUPPLY_UNIT_PA), b)
        m = steady_map(xs, q, params=_params(at, np.delete(theta, 5)), rtol=_MAP_RTOL)
        r = (m['p12_pa'] - p12) * w
        return np.append(r, [theta[5] / s_ps, (theta[6] - lam_mean) / lam_std])

    starts = [np.array([c, o, 0.95, np.log10(lc), 2.0, 0.0, lam_mean])
              for lc in _START_LC for c in _START_C for o in _START_O]
    costs = [float(np.sum(resid(s) ** 2)) for s in starts]
    best = min((least_squares(resid, starts[i], bounds=(_LO, _HI), x_scale=_SCALE,
                              diff_step=1e-4, xtol=1e-10, ftol=1e-10)
                for i in np.argsort(costs)[:_REFINED]), key=lambda r: r.cost)
    theta = best.x
    dof = max(xs.size + 2 - theta.size, 1)
    chi = float(np.sqrt(2.0 * best.cost / dof))
    jac = best.jac
    jtj_inv = np.linalg.pinv(jac.T @ jac)
    cov = jtj_inv * max(chi, 1.0) ** 2
    # d theta / d condition, by the fit's linearisation: -(J'J)^-1 J' dr/dc (the supply's
    # error is a parameter of the fit, with its sensor's prior)
    sens = {}
    r0 = resid(theta)
    for name, h in (('return_pressure_pa', 2e3), ('fluid_temperature_k', 0.2)):
        c2 = dataclasses.replace(cond, **{name: getattr(cond, name) + h})
        dr = (resid(theta, c2) - r0) / h
        sens[name] = -(jtj_inv @ (jac.T @ dr))
    # no leakage is a physical bound, not a failure of the fit
    at_bound = bool(np.any(np.isclose(theta[:4], _LO[:4], rtol=0, atol=1e-6))
                    or np.any(np.isclose(theta[:5], _HI[:5], rtol=0, atol=1e-6)))
    return {'theta': theta, 'cov': cov, 'chi': chi, 'at_bound': at_bound,
            'residual_pa': float(np.sqrt(np.mean((r0[:-2] / w) ** 2))),
            'n_used': int(xs.size), 'n_points': n_all, 'unsettled': unsettled,
            'supply_offset_pa': float(theta[5] * _SUPPLY_UNIT_PA), 'sensitivity': sens}


class ValveFitEstimator:
    """Clearance, overlap and Khsv from a settled valve test at measured conditions (module
    docstring), method ``settled-valve-fit``.

    Parameters
    ----------
    params : PlantParams
        Physics of the valve less what the fit estimates and the bench measures.
    calibration : FitCalibration or None
        Default: the shipped one; ``None`` with ``uncalibrated=True``: factors 1 and no chi
        limit (used to build the calibration).
    laminar_prior : (float, float) or None
        Mean and standard deviation of log10 of the laminar factor (module docstring).
        Default: the fleet's, from the tolerances (:func:`unit_priors`).  The shipped
        calibration holds for the default; another prior is a control (what the fit reads
        when the unit's leakage gain is known), not a calibrated estimate.
    """

    method = 'settled-valve-fit'

    def __init__(self, params: PlantParams | None = None, calibration='default',
                 bench=None, laminar_prior=None):
        self.params = params if params is not None else default_params()
        self.bench = bench or load_bench()
        self.calibration = load_calibration() if calibration == 'default' else calibration
        self.laminar_prior = laminar_prior

    def estimate(self, curves, conditions: Conditions | None) -> HealthEstimate:
        """``curves``: ``(q_m3_s, xs_m, p12_pa[, p12_before_pa])`` per flow: each point's
        reading (for the settled test the mean over the last ``READING_S`` of the hold) and,
        where known, the mean over the ``READING_S`` before (unsettled points are left
        out); ``conditions``: the measured test conditions (``None``: nominal
        assumed, said so, deviations widened)."""
        curves = [(float(c[0]), np.asarray(c[1], dtype=float), np.asarray(c[2], dtype=float),
                   None if len(c) < 4 or c[3] is None else np.asarray(c[3], dtype=float))
                  for c in curves]
        if not curves:
            raise ParameterError('no complete valve-test curve')
        notes = []
        if conditions is None:
            conditions = dataclasses.replace(true_conditions(self.params, self.bench),
                                             assumed=True)
        if conditions.assumed:
            notes.append('test conditions not measured: nominal assumed, deviations widened')
        cal = self.calibration
        if cal is not None and cal.meta.get('stage') != 'calibrated':
            notes.append(f'the valve fit is not calibrated (python -m {REBUILD}): deviations '
                         'unscaled, no residual limit')
        lo, hi = self.bench.service['supply_pressure_pa']
        f = fit_curves(curves, conditions, self.params, self.bench,
                       (hi - lo) / np.sqrt(12.0) if conditions.assumed else None,
                       self.laminar_prior)
        # reported: clearance, overlap, Khsv = 1 - kappa / (Cd w over nominal), leakage
        pick = [0, 1, 2, 4]
        edge_mean, edge_std = unit_priors(self.params)['edge']
        to_item = np.diag([1.0, 1.0, -1.0 / edge_mean, 1.0])
        theta = f['theta'][pick]
        cov = to_item @ f['cov'][np.ix_(pick, pick)] @ to_item
        theta = np.array([theta[0], theta[1], 1.0 - theta[2] / edge_mean, theta[3]])
        f['sensitivity'] = {k: to_item @ v[pick] for k, v in f['sensitivity'].items()}
        var = np.abs(np.diag(cov))
        var[2] += ((1.0 - theta[2]) * edge_std / edge_mean) ** 2   # Cd w unit to unit
        if conditions.assumed:   # the whole service range is possible
            cstd = np.array([(hi - lo) / np.sqrt(12.0)
                             for lo, hi in (self.bench.service[k] for k in CONDITIONS)])
        else:   # each measured condition's error: its sensor's bias, uniform
            cstd = np.array([self.bench.sensors[k].bias / np.sqrt(3.0) for k in CONDITIONS])
        for j, name in enumerate(CONDITIONS):
            if name in f['sensitivity']:
                var += (f['sensitivity'][name] * cstd[j]) ** 2
        factors = cal.factors if cal is not None else np.ones(len(FIT_NAMES))
        std = np.sqrt(var) * factors * _UNITS
        value = theta * _UNITS
        mismatch = list(self.bench.outside_service(conditions))
        k_lo, k_hi = self.bench.nuisance_range('valve_degradation', self.params)
        if cal is not None and f['chi'] > cal.chi_limit:
            mismatch.append(f'the valve model does not explain this test: residual '
                            f'{f["residual_pa"] / 1e3:.1f} kPa RMS, chi {f["chi"]:.2f}, limit '
                            f'{cal.chi_limit:.2f}')
        if value[2] > k_hi + 2 * std[2] or value[2] < k_lo - 2 * std[2]:
            mismatch.append(f'Khsv {value[2]:.3f} beyond the calibrated envelope '
                            f'[{k_lo:g}, {k_hi:g}]')
        if f['at_bound']:
            mismatch.append('the fit ran into a bound of its parameters')
        if mismatch or conditions.assumed:
            l_lo, l_hi = self.bench.nuisance_range('leakage_coeff_m3_s_pa', self.params)
            spans = np.array([np.diff(WEAR_RANGES['radial_clearance_m'])[0],
                              np.diff(WEAR_RANGES['overlap_m'])[0], k_hi - k_lo, l_hi - l_lo])
            std = np.maximum(std, spans / np.sqrt(12.0))
        return HealthEstimate(
            radial_clearance_m=float(value[0]), radial_clearance_std_m=float(std[0]),
            overlap_m=float(value[1]), overlap_std_m=float(std[1]),
            pressure_residual_pa=f['residual_pa'], samples_used=f['n_used'],
            method=self.method, mismatch='; '.join(mismatch),
            extra={'valve_degradation': (float(value[2]), float(std[2])),
                   'leakage_coeff_m3_s_pa': (float(value[3]), float(std[3])), 'chi': f['chi'],
                   'critical_flow_number': float(10.0 ** f['theta'][3]),
                   'laminar_factor': float(10.0 ** f['theta'][6]),
                   'points_in_band': f['n_used'], 'points': f['n_points']},
            conditions=conditions.as_dict(), note='; '.join(notes))
