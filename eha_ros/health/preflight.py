"""Multi-fault diagnosis from the pre-flight check (:mod:`eha_ros.physics.maintenance`).

The pre-flight check drives the coil open loop (steps and sines, jack free) and records coil
current, spool, flapper, load pressure and jack at every 1 ms tick.  A network reads from
these records the degradations the check excites, under the plant's own parameter names
(:data:`FAULTS`): torque-motor demagnetisation (KGM), first-stage filter clogging (K_intas),
spool and jack breakaway friction and the torque-motor current offset - and, as nuisances it
must see through, the valve's clearance and overlap (the valve test reads those better).

Features (:func:`preflight_features`)
    10 ms means of the coil current less the command, spool, flapper, P12, jack position and
    velocity (120 x 6), and the spool and flapper in the 5 ticks after each current step
    (5 x 10): 770 numbers, standardised on the training set.

Network and uncertainty
    An ensemble of multilayer perceptrons (tanh), each
    with two outputs per parameter - mean and log-variance of the parameter normalised to its
    range - trained by Adam on the Gaussian negative log-likelihood (after a mean-squared
    warm-up).  The estimate is the ensemble mean; its variance is the members' mean variance
    plus the variance of their means.  Then per parameter a calibration factor (at least 1)
    scales the standard deviation so that 95 % of the validation cases, and 95 % of 200 further
    2-3-fault combinations (a separate stream), lie within 2 sigma: the stated deviation is
    never tighter than what held-out data showed.

Data, training and calibration: :mod:`eha_ros.training.preflight`
(``nice python -m eha_ros.training.preflight`` writes ``models/faults.npz``).  Inference is
numpy only.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np

from eha_ros.artefacts import ArtefactError, load_artefact, models_dir
from eha_ros.mlp import flatten_weights, mlp_forward, split_weights
from eha_ros.physics import default_params

__all__ = ['Fault', 'FAULTS', 'FAULT_NAMES', 'FaultModel', 'FaultEstimate', 'load_faults',
           'preflight_features', 'FAULTS_FILE']

FAULTS_FILE = 'faults.npz'
#: ``python -m`` argument that rebuilds it
REBUILD = 'eha_ros.training.preflight'


@dataclasses.dataclass(frozen=True)
class Fault:
    """One estimated parameter: plant name, unit and the range the network was trained over
    (errors are quoted in % of it)."""

    name: str
    unit: str
    lo: float
    hi: float
    meaning: str

    @property
    def span(self) -> float:
        return self.hi - self.lo

    @property
    def nominal(self) -> float:
        """The parameter's nominal value (``config/eha_params.yaml``)."""
        return float(getattr(default_params(), self.name))


#: The parameters the pre-flight network estimates (plant parameter names, SI units).
FAULTS = (
    Fault('demagnetisation', '1', 0.0, 0.5, 'torque-motor demagnetisation KGM'),
    Fault('filter_clogging', '1', 0.0, 0.8, 'first-stage filter clogging K_intas'),
    Fault('spool_static_friction_n', 'N', 0.5, 6.0, 'spool breakaway friction'),
    Fault('jack_static_friction_n', 'N', 100.0, 2000.0, 'jack seal breakaway friction'),
    Fault('offset_a', 'A', -1e-3, 1e-3, 'torque-motor current offset'),
    Fault('radial_clearance_m', 'm', 1e-6, 6e-6, 'spool radial clearance'),
    Fault('overlap_supply_m', 'm', -2e-6, 6e-6, 'spool overlap (supply = return)'),
)
FAULT_NAMES = tuple(f.name for f in FAULTS)
_BY_NAME = {f.name: f for f in FAULTS}

_EDGES = (50, 100, 150, 200, 250)
_BIN = 10


def preflight_features(a: dict) -> np.ndarray:
    """Feature vector of one pre-flight record ``a`` (``command_a`` and the
    :data:`eha_ros.physics.maintenance.PREFLIGHT_SIGNALS` arrays, one value per 1 ms tick)."""
    n = a['command_a'].size
    nb = n // _BIN
    sig = [a['coil_current_a'] - a['command_a'], a['spool_position_m'],
           a['flapper_position_m'], a['p12_pa'], a['jack_position_m'], a['jack_velocity_m_s']]
    parts = [np.asarray(s[:nb * _BIN], dtype=float).reshape(nb, _BIN).mean(axis=1)
             for s in sig]
    for k in _EDGES:
        parts.append(np.asarray(a['spool_position_m'][k:k + 5], dtype=float))
        parts.append(np.asarray(a['flapper_position_m'][k:k + 5], dtype=float))
    return np.concatenate(parts)


@dataclasses.dataclass
class FaultEstimate:
    """Estimates and standard deviations (SI, plant names) of one pre-flight check."""

    values: dict
    stds: dict


@dataclasses.dataclass
class FaultModel:
    """A loaded ensemble: input standardisation, members' weights, calibration."""

    in_mean: np.ndarray
    in_std: np.ndarray
    members: list           # each [(W, b), ...]
    calibration: np.ndarray  # per output, >= 1
    meta: dict

    def predict_normalised(self, x):
        """Ensemble mean and standard deviation (calibrated) of the outputs in units of each
        range, for feature rows ``x`` ``(n, d)``."""
        z = (np.atleast_2d(x) - self.in_mean) / self.in_std
        mus, vars_ = [], []
        k = len(FAULTS)
        for weights in self.members:
            o = mlp_forward(weights, z)
            mus.append(o[:, :k])
            vars_.append(np.exp(np.clip(o[:, k:], -30, 10)))
        mus = np.array(mus)
        var = np.mean(vars_, axis=0) + np.var(mus, axis=0)
        return mus.mean(axis=0), np.sqrt(var) * self.calibration

    def estimate(self, record: dict) -> FaultEstimate:
        """Estimate from one pre-flight record (see :func:`preflight_features`)."""
        mu, sd = self.predict_normalised(preflight_features(record)[None, :])
        vals, stds = {}, {}
        for j, f in enumerate(FAULTS):
            vals[f.name] = float(f.lo + mu[0, j] * f.span)
            stds[f.name] = float(sd[0, j] * f.span)
        return FaultEstimate(vals, stds)

    def data(self) -> tuple:
        flat = [flatten_weights(m) for m in self.members]
        return (self.in_mean, self.in_std, np.array(flat), self.calibration)


def load_faults(path: Path | None = None) -> FaultModel:
    """The shipped pre-flight network (:data:`FAULTS_FILE`)."""
    path = Path(path) if path is not None else models_dir('health') / FAULTS_FILE
    if not path.is_file():
        raise ArtefactError(f'{path}: no pre-flight fault network: build it with python -m '
                            f'{REBUILD}')
    return _load_cached(str(path), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=4)
def _load_cached(path: str, mtime_ns: int) -> FaultModel:
    (in_mean, in_std, flat, cal), meta = load_artefact(Path(path), REBUILD)
    if tuple(meta.get('outputs', ())) != FAULT_NAMES:
        raise ArtefactError(f'{path}: outputs {meta.get("outputs")} are not {FAULT_NAMES}')
    sizes = [in_mean.size] + list(meta['hidden']) + [2 * len(FAULTS)]
    members = [split_weights(theta, sizes) for theta in flat]
    return FaultModel(in_mean, in_std, members, cal, meta)
