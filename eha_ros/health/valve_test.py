"""Wear diagnosis from pressure curves (the reference's section 5.4.3): a network that reads
one characteristic curve - the 133 values of P12 along the spool grid at one imposed flow - and
that flow, and returns the radial clearance and the overlap of the valve.

Network
    134 inputs (133 pressures [Pa] and the flow [m^3/s]), each min-max normalised to [-1, 1]
    on the training split; tanh hidden layers; 2 linear outputs, the clearance and the overlap,
    min-max normalised over the training split (the wear ranges of DB4).  The shipped default
    (``diag.npz``, :data:`eha_ros.training.valve_test.DIAG_SETTINGS`) has two hidden layers
    of 64 trained by Adam then L-BFGS; the reference's network (one hidden layer of 10,
    Levenberg-Marquardt, :data:`eha_ros.training.valve_test.DIAG_THESIS_SETTINGS`) is trained
    alongside and its held-out errors are recorded in the artefact's metadata
    (``alternatives``) beside the default's (``errors``).

Symmetry
    With equal supply and return overlaps the valve is antisymmetric,
    ``P12(-XS, -Q) = -P12(XS, Q)``, so a curve at a negative flow is mapped onto the positive
    flow (:func:`canonical_curves`) before it reaches the network, which is trained on the
    non-negative flows only.  This halves what the network has to learn.

Per-map estimate
    A map (the curves at several flows of one valve) gives one estimate per curve; they are
    combined by their median, and their standard deviation is the spread reported as the
    uncertainty.

Errors are reported in % of each parameter's range (:data:`WEAR_RANGES`).  Inference is numpy
only (:func:`estimate_wear`, :func:`estimate_wear_batch`, :func:`estimate_wear_map`).

Training, its data and noise model: :mod:`eha_ros.training.valve_test`
(``python -m eha_ros.training.valve_test``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from eha_ros.artefacts import ArtefactError, CachedReader, check_hash, load_artefact, models_dir
from eha_ros.mlp import flatten_weights, mlp_forward, split_weights
from eha_ros.health.thresholds import HealthEstimate
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import WEAR_RANGES, fluid_hash
from eha_ros.physics.params import ParameterError

__all__ = ['read_diagnostic', 'ValveTestEstimator', 'WearEstimate', 'DiagnosticModel',
           'load_diagnostic', 'estimate_wear', 'estimate_wear_batch', 'estimate_wear_map',
           'canonical_curves', 'OUTPUT_NAMES', 'OUTPUT_UNITS']

#: The network's outputs, in order (the reference's order: clearance, then overlap).
OUTPUT_NAMES = ('radial_clearance_m', 'overlap_m')
OUTPUT_UNITS = ('m', 'm')
#: ``python -m`` argument that rebuilds ``diag.npz``
REBUILD = 'eha_ros.training.valve_test'


@dataclasses.dataclass
class WearEstimate:
    """Wear of one valve from a map: combined estimate and spread over its curves."""

    radial_clearance_m: float
    overlap_m: float
    radial_clearance_std_m: float
    overlap_std_m: float
    curves_used: int
    per_curve_clearance_m: np.ndarray
    per_curve_overlap_m: np.ndarray


@dataclasses.dataclass
class DiagnosticModel:
    """A loaded diagnostic network: spool grid, normalisations, weights and metadata."""

    xs_m: np.ndarray
    in_norm: np.ndarray     # (2, 134): mid, half
    out_norm: np.ndarray    # (2, 2): mid, half of (clearance, overlap)
    weights: list           # [(W (d_in, d_out), b (d_out,)), ...]
    meta: dict

    def forward(self, p12_curves_pa, q_m3_s):
        """``(n, 2)`` (clearance, overlap) [m] for curves ``(n, 133)`` [Pa] and flows ``(n,)``."""
        if self.meta.get('symmetric', False):  # trained on the canonical curves
            p12_curves_pa, q_m3_s = canonical_curves(p12_curves_pa, q_m3_s)
        x = np.concatenate([p12_curves_pa, q_m3_s[:, None]], axis=1)
        h = mlp_forward(self.weights, (x - self.in_norm[0]) / self.in_norm[1])
        return self.out_norm[0] + self.out_norm[1] * h

    def data(self) -> tuple:
        """The arrays as saved: ``(layout, xs_m, in_norm, out_norm, theta)``."""
        sizes = [self.in_norm.shape[1]] + [b.size for _, b in self.weights]
        theta = flatten_weights(self.weights)
        return (np.array(sizes, dtype=float), self.xs_m, self.in_norm, self.out_norm, theta)

    @classmethod
    def from_data(cls, data, meta) -> 'DiagnosticModel':
        layout, xs, in_norm, out_norm, theta = (np.asarray(a, dtype=float) for a in data)
        sizes = [int(s) for s in layout]
        try:
            weights = split_weights(theta, sizes)
        except ArtefactError as exc:
            raise ArtefactError(f'diagnostic artefact: {exc}') from None
        if in_norm.shape != (2, sizes[0]) or xs.size + 1 != sizes[0]:
            raise ArtefactError('diagnostic artefact: normalisation or spool grid do not '
                                'match the layer widths')
        return cls(xs, in_norm, out_norm, weights, meta)


def load_diagnostic(params: PlantParams | None = None, path: Path | None = None,
                    ) -> DiagnosticModel:
    """Load the shipped diagnostic network (``models/diag.npz``) and check it was built for
    ``params`` (default: the nominal parameters); ``ArtefactError`` otherwise."""
    p = params if params is not None else default_params()
    path = Path(path) if path is not None else models_dir('health') / 'diag.npz'
    model = read_diagnostic(path)
    check_hash(model.meta, 'fluid_hash', fluid_hash(p), f'valve-test network {path.name}',
               REBUILD)
    return model


def _read_diagnostic(path: Path) -> DiagnosticModel:
    data, meta = load_artefact(path, REBUILD)
    if meta.get('kind') != 'diag':
        raise ArtefactError(f'{path}: not a diagnostic network (kind {meta.get("kind")!r})')
    return DiagnosticModel.from_data(data, meta)


#: :func:`load_diagnostic`'s reader, once per state of the file
#: (:class:`.artefacts.CachedReader`).
read_diagnostic = CachedReader(_read_diagnostic)


def estimate_wear_batch(p12_curves_pa, q_m3_s, xs_m=None, model: DiagnosticModel | None = None,
                        ):
    """Clearance [m] and overlap [m] arrays, one per curve.

    Parameters
    ----------
    p12_curves_pa : array (n, 133)
        P12 [Pa] along the model's spool grid (:func:`eha_ros.physics.maps.spool_grid`), or
        along ``xs_m`` (then linearly resampled).
    q_m3_s : array (n,) or float
        Imposed flow [m^3/s] of each curve.
    """
    m = model if model is not None else load_diagnostic()
    p12 = np.atleast_2d(np.asarray(p12_curves_pa, dtype=float))
    if xs_m is not None:
        p12 = np.stack([np.interp(m.xs_m, np.asarray(xs_m, dtype=float), c) for c in p12])
    if p12.shape[1] != m.xs_m.size:
        raise ValueError(f'a curve holds {m.xs_m.size} pressures on the spool grid '
                         f'(got {p12.shape[1]}); pass xs_m to resample another grid')
    if not np.all(np.isfinite(p12)):
        raise ValueError('pressures must be finite')
    q = np.broadcast_to(np.asarray(q_m3_s, dtype=float), (p12.shape[0],))
    out = m.forward(p12, np.ascontiguousarray(q))
    return out[:, 0], out[:, 1]


def estimate_wear(p12_curve_pa, q_m3_s: float, xs_m=None,
                  model: DiagnosticModel | None = None) -> tuple[float, float]:
    """``(radial_clearance_m, overlap_m)`` from one curve (133 P12 values [Pa] along the spool
    grid) at flow ``q_m3_s`` [m^3/s]; ``model`` defaults to the shipped network (loaded and
    checked against the nominal parameters on first use)."""
    c, o = estimate_wear_batch(np.asarray(p12_curve_pa, dtype=float)[None, :], [q_m3_s],
                               xs_m=xs_m, model=model)
    return float(c[0]), float(o[0])


def estimate_wear_map(p12_map_pa, q_m3_s, xs_m=None, model: DiagnosticModel | None = None,
                      combine: str = 'median') -> WearEstimate:
    """Wear from a map ``(133, n_q)`` [Pa] at flows ``(n_q,)`` [m^3/s]: the per-curve
    estimates combined by ``combine`` (``'median'`` or ``'mean'``), with their standard
    deviation as the spread."""
    p12 = np.asarray(p12_map_pa, dtype=float)
    q = np.asarray(q_m3_s, dtype=float).ravel()
    if p12.ndim != 2 or p12.shape[1] != q.size:
        raise ValueError('p12_map_pa must be (n_xs, n_q) with one flow per column')
    c, o = estimate_wear_batch(p12.T, q, xs_m=xs_m, model=model)
    agg = {'median': np.median, 'mean': np.mean}[combine]
    return WearEstimate(float(agg(c)), float(agg(o)), float(np.std(c)), float(np.std(o)),
                        int(q.size), c, o)


def canonical_curves(p12_curves_pa, q_m3_s):
    """Curves at negative flow mapped onto positive flow by the valve's symmetry.

    With equal supply and return overlaps the valve is antisymmetric,
    ``P12(-XS, -Q) = -P12(XS, Q)``; on the antisymmetric spool grid the curve at ``-Q`` is
    ``-curve[::-1]`` of the curve at ``Q``.  Curves ``(n, n_xs)``, flows ``(n,)``.
    """
    p12 = np.asarray(p12_curves_pa, dtype=float)
    q = np.asarray(q_m3_s, dtype=float)
    neg = q < 0.0
    out = p12.copy()
    out[neg] = -p12[neg, ::-1]
    return out, np.abs(q)


class ValveTestEstimator:
    """Wear from the P12 curves of a diagnostic valve test (:mod:`eha_ros.physics.maintenance`)
    by the diagnostic network (:mod:`eha_ros.training.valve_test` builds it), method
    ``diagnostic-network``.

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
        self.params = params if params is not None else default_params()
        self.model = model if model is not None else load_diagnostic(self.params)

    def estimate(self, curves) -> HealthEstimate:
        """``curves``: ``(q_m3_s, xs_m, p12_pa)`` per flow, the spool positions [m] in
        increasing order (resampled onto the network's grid if they are not it)."""
        from eha_ros.physics.maps import transient_map
        from eha_ros.physics.params import replace
        curves = [(float(q), np.asarray(xs, dtype=float), np.asarray(p, dtype=float))
                  for q, xs, p in curves]
        if not curves:
            raise ParameterError('no complete valve-test curve')
        grid = self.model.xs_m
        est = [estimate_wear(p, q, model=self.model, xs_m=None if np.array_equal(xs, grid)
                             else xs) for q, xs, p in curves]
        c, o = (np.array(v) for v in zip(*est))
        clr, lap = float(np.median(c)), float(np.median(o))
        (l0, l1), (c0, c1) = WEAR_RANGES['overlap_m'], WEAR_RANGES['radial_clearance_m']
        model_params = replace(self.params, overlap_supply_m=lap, overlap_return_m=lap,
                               radial_clearance_m=float(np.clip(clr, c0 * 0.5, c1 * 2)))
        r2 = sum(float(np.sum((transient_map(xs, q, params=model_params)['p12_pa'] - p) ** 2))
                 for q, xs, p in curves)
        n = sum(p.size for _, _, p in curves)
        # the curves' spread, floored at the network's own held-out error: on clean curves (per
        # map, or per curve over the root of the curves used, whichever is larger), plus
        # the per-curve error at 1 % noise scaled by the noise the data show (measurement
        # noise biases the estimate, the same way on every curve, so their spread misses it;
        # the map model's relative residual at the estimate is 0.8x the noise level)
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
