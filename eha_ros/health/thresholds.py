"""Health levels: the limits of ``config/health.yaml`` and the grading of an estimate against
them (OK, WARN, ERROR), with the evidence the estimate carries.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from eha_ros.graph import LEVEL_ERROR as ERROR, LEVEL_OK as OK, LEVEL_WARN as WARN
from eha_ros.physics.maps import WEAR_RANGES
from eha_ros.physics.params import ParameterError, config_dir, read_yaml

__all__ = ['HealthEstimate', 'HealthThresholds', 'FaultLimit', 'classify', 'classify_fault',
           'OK', 'WARN', 'ERROR']


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
    #: Why the model does not explain the data ('' when it does): the estimate cannot be
    #: assessed, its deviations are widened (:data:`CANNOT_ASSESS`).
    mismatch: str = ''
    #: Further estimates ``{name: (value, std)}`` and figures of the method.
    extra: dict = dataclasses.field(default_factory=dict)
    #: The test conditions the estimate used (measured, or ``assumed``), ``{}`` in service.
    conditions: dict = dataclasses.field(default_factory=dict)
    #: A caveat that does not refuse the estimate (e.g. nominal conditions assumed).
    note: str = ''


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
        path = path or config_dir() / 'health.yaml'
        doc = read_yaml(path, 'health threshold', 'name -> limit')
        fields = [f.name for f in dataclasses.fields(cls) if f.name != 'faults']
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


def classify_fault(name: str, value: float, std: float, limits: HealthThresholds
                   ) -> tuple[int, str]:
    """Level and reason of one pre-flight estimate: a limit counts as passed only when the
    estimate is beyond it by ``z`` standard deviations (``z`` from ``evidence_probability``,
    1.64 for 0.95): levels are raised on evidence."""
    lim = limits.fault(name)
    if lim is None:
        return OK, f'{name} = {value:.4g} +- {std:.2g} (no limits configured)'
    from statistics import NormalDist
    z = NormalDist().inv_cdf(limits.evidence_probability)   # one-sided Gaussian quantile
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
        for key, level, what, limit, action in (
                ('clearance_error', ERROR, 'radial clearance beyond', limits.clearance_error_m,
                 'replace the valve'),
                ('overlap_error', ERROR, 'overlap below', limits.overlap_error_m,
                 'metering edges worn, replace the valve'),
                ('clearance_warn', WARN, 'radial clearance beyond', limits.clearance_warn_m,
                 'plan maintenance'),
                ('overlap_warn', WARN, 'overlap below', limits.overlap_warn_m,
                 'plan maintenance')):
            p = est.beyond[key]
            if p >= limits.evidence_probability:
                return level, (f'{what} {limit * 1e6:g} um (probability {p:.2f}): {action}; '
                               f'{fit}')
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
