"""Fault diagnosis from the pre-flight check (:mod:`eha_ros.physics.maintenance`), robust to
the drift no bench measures.

The pre-flight check drives the coil open loop (steps and sines, jack free) and records coil
current, spool, flapper, load pressure and jack at every 1 ms tick.  A network reads from
these records, and from the test conditions the bench measured, the degradations the check
excites, under the plant's own parameter names (:data:`FAULTS`): torque-motor demagnetisation
(KGM), first-stage filter clogging (K_intas), spool and jack breakaway friction and the
torque-motor current offset.  It was trained with everything else drifting over the test
bench's envelope (``config/test_bench.yaml``, :mod:`eha_ros.physics.bench`): bulk modulus,
metering-edge silting, hysteresis, feedback backlash, jack leakage, a load on the jack, coil
noise, the spool's clearance and overlap (the valve test reads those), supply and return
pressure and the fluid temperature.

Inputs (:func:`model_inputs`)
    10 ms means of the coil current less the command, spool, flapper, P12, jack position and
    velocity (120 x 6), the spool and flapper in the 5 ticks after each current step (5 x 10),
    P12 and jack velocity in the 10 ticks after each step (5 x 20: the ringing of the jack on
    its oil columns, whose frequency follows the bulk modulus, which 10 ms means average out)
    (:func:`preflight_features`), then the measured supply pressure, return pressure and fluid
    temperature (the mean of the bench's readings, :func:`eha_ros.physics.bench.
    mean_conditions`): 873 numbers, standardised on the training set.

Network and uncertainty
    An ensemble of multilayer perceptrons (tanh), each with two outputs per fault - mean and
    log-variance of the fault normalised to its range - trained by Adam on the Gaussian
    negative log-likelihood (after a mean-squared warm-up).  The estimate is the ensemble
    mean; its variance is the members' mean variance plus the variance of their means.  Per
    fault a calibration factor (at least 1) scales the deviation so that 95 % of drifted
    held-out cases lie within 2 sigma (the figures are in the artefact's ``meta``).

Mismatch (:attr:`FaultEstimate.mismatch`)
    A check the network was not built for is reported, not estimated: a measured condition
    outside the service envelope the network was trained over, or an out-of-distribution score
    (:class:`OodModel`: a parameter's estimate, linear or by a network, beyond the range
    the data was drawn over, or inputs off the training data's principal subspaces) above
    the limit set on drifted held-out data.  Then every deviation is widened to at least
    the range's uniform-prior deviation (span / sqrt(12)).

Unmeasured conditions (:attr:`FaultEstimate.note`)
    With ``conditions.assumed`` the network is evaluated over a 3 x 3 x 3 grid of the service
    envelope and the estimate is the grid's mean; its variance adds the grid's spread of
    estimates (never below the deviation at the conditions given); the OOD score is the
    grid's smallest; ``note`` says so.

Measured (``bench/health_preflight.py``, streams no build step used; figures in
``docs/fleet/health_preflight.json``): on 400 checks of a drawn fleet the mean error is
0.14-4.7 % of each range, 96-99.5 % lie within 2 sigma and 1.5 % are refused; no false
alarm on 24 drifted nominal valves; of 48 cases beyond the envelope 46 are refused (all with
the supply pressure 15 % off, the fluid at 0 or 90 degC, Khsv = 0.4; 6 of 8 with the bulk
modulus halved, whose unrefused estimates all held the truth within 2 sigma).

Data, training and calibration: :mod:`eha_ros.training.preflight`
(``nice python -m eha_ros.training.preflight`` writes ``models/faults.npz``).  Inference is
numpy only.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import numpy as np

from eha_ros.artefacts import ArtefactError, CachedReader, load_artefact, models_dir
from eha_ros.mlp import flatten_weights, mlp_forward, split_weights
from eha_ros.physics import default_params
from eha_ros.physics.bench import CONDITIONS, Conditions, outside_ranges

__all__ = ['read_faults', 'Fault', 'FAULTS', 'FAULT_NAMES', 'FaultModel', 'FaultEstimate',
           'OodModel', 'load_faults', 'preflight_features', 'model_inputs', 'FAULTS_FILE',
           'CONDITION_READINGS', 'N_INPUTS', 'RING_COLUMNS', 'Subspace', 'NetEnvelope']

FAULTS_FILE = 'faults.npz'
#: ``python -m`` argument that rebuilds it
REBUILD = 'eha_ros.training.preflight'
#: Bench readings of the test conditions averaged per check (training and the procedures).
CONDITION_READINGS = 1200


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
)
FAULT_NAMES = tuple(f.name for f in FAULTS)

_EDGES = (50, 100, 150, 200, 250)
_BIN = 10
_RING = 10
#: Columns of the inputs holding P12 and jack velocity after the steps (the last features).
RING_COLUMNS = (120 * 6 + 2 * 5 * len(_EDGES), 120 * 6 + 2 * (5 + _RING) * len(_EDGES))
#: Features of a check (:func:`preflight_features`) and inputs of the network.
N_FEATURES = 870
N_INPUTS = N_FEATURES + len(CONDITIONS)
_TICKS = 1200


def preflight_features(a: dict) -> np.ndarray:
    """Feature vector of one pre-flight record ``a`` (``command_a`` and the
    :data:`eha_ros.physics.maintenance.PREFLIGHT_SIGNALS` arrays, one value per 1 ms tick)."""
    n = a['command_a'].size
    nb = n // _BIN
    sig = [a['coil_current_a'] - a['command_a'], a['spool_position_m'],
           a['flapper_position_m'], a['p12_pa'], a['jack_position_m'], a['jack_velocity_m_s']]
    parts = [np.asarray(s[:nb * _BIN], dtype=float).reshape(nb, _BIN).mean(axis=1)
             for s in sig]
    parts += [np.asarray(a[name][k:k + n], dtype=float)
              for n, names in ((5, ('spool_position_m', 'flapper_position_m')),
                               (_RING, ('p12_pa', 'jack_velocity_m_s')))
              for k in _EDGES for name in names]
    return np.concatenate(parts)


def model_inputs(record: dict, conditions: Conditions) -> np.ndarray:
    """The network's input vector: :func:`preflight_features` of ``record`` and the measured
    ``conditions`` (:data:`eha_ros.physics.bench.CONDITIONS`)."""
    from eha_ros.physics.maintenance import PREFLIGHT_SIGNALS
    if not isinstance(conditions, Conditions):
        raise TypeError(f'pre-flight estimate: conditions must be a bench Conditions, not '
                        f'{type(conditions).__name__}')
    for name in ('command_a',) + PREFLIGHT_SIGNALS:
        if name not in record:
            raise ValueError(f'pre-flight estimate: the record has no {name}')
        if np.size(record[name]) != _TICKS:
            raise ValueError(f'pre-flight estimate: {name} has {np.size(record[name])} '
                             f'samples, the check {_TICKS}')
    x = np.concatenate([preflight_features({k: np.asarray(v, dtype=float)
                                            for k, v in record.items()}),
                        conditions.array()])
    if not np.all(np.isfinite(x)):
        raise ValueError('pre-flight estimate: the record or the conditions are not finite')
    return x


@dataclasses.dataclass
class FaultEstimate:
    """Estimates and standard deviations (SI, plant names) of one pre-flight check.

    ``ood_score`` and ``ood_limit``: the check's out-of-distribution score and the limit
    (:class:`OodModel`).  ``mismatch``: ``''`` when the check lies within what the network
    was built for, otherwise one line saying why not (the deviations are then widened: the
    estimate cannot assess the valve).  ``note``: ``''``, or one line on a widening that is
    not a mismatch (conditions assumed, not measured)."""

    values: dict
    stds: dict
    ood_score: float = 0.0
    ood_limit: float = math.inf
    mismatch: str = ''
    note: str = ''


@dataclasses.dataclass
class Subspace:
    """Subspace test on the standardised inputs ``z[:, start:stop]``: their principal
    subspace in the training data (``basis``, rows orthonormal, training ``variances`` along
    them); score: the root of the mean of the squared Mahalanobis distance per dimension and
    the squared residual outside the subspace over its training mean (``residual_ms``), times
    ``scale``."""

    start: int
    stop: int
    basis: np.ndarray       # (k, stop - start)
    variances: np.ndarray   # (k,)
    residual_ms: float
    scale: float = 1.0

    def score(self, z) -> np.ndarray:
        z = np.atleast_2d(z)[:, self.start:self.stop]
        t = z @ self.basis.T
        d2 = np.mean(t ** 2 / self.variances, axis=1)
        r2 = np.maximum(np.sum(z ** 2, axis=1) - np.sum(t ** 2, axis=1), 0.0)
        return self.scale * np.sqrt(0.5 * (d2 + r2 / self.residual_ms))


def _beyond(u, scales) -> np.ndarray:
    """Per row, the largest distance of an estimate ``u`` outside ``[0, 1]`` in ``scales``."""
    return np.max(np.maximum(0.0, np.maximum(-u, u - 1.0)) / scales, axis=1)


@dataclasses.dataclass
class NetEnvelope:
    """The envelope test by a network: a multilayer perceptron (``silu``, which extrapolates
    about linearly) estimates the same parameters as the ridge regression from the
    standardised inputs, normalised to their ranges; score: as :class:`OodModel`'s envelope
    (with the network's ``scales``), times ``scale``.  Where a parameter shows only
    through a non-linear feature of the check (the bulk modulus through the frequency of
    the ringing after the steps) the network reads it four to ten times closer than the
    linear estimate."""

    weights: list           # [(W, b), ...]
    scales: np.ndarray      # (m,)
    scale: float = 1.0

    def score(self, z) -> np.ndarray:
        return self.scale * _beyond(mlp_forward(self.weights, np.atleast_2d(z), 'silu'),
                                    self.scales)


@dataclasses.dataclass
class OodModel:
    """Out-of-distribution score of standardised network inputs ``z`` (rows): the largest of

    envelope
        Every parameter the data was drawn over (the faults, the bench's nuisances, the
        clearance and overlap, the true conditions; ``meta['ood']['parameters']``) estimated
        by a ridge regression, linear in ``z`` (``weights``, last row the intercept) so that
        it extrapolates beyond the training ranges; each estimate is normalised to its range.
        Score: the largest distance of an estimate outside ``[0, 1]`` in units of its
        ``scales`` (the 99 % quantile of its absolute error on held-out data: estimators
        with heavy-tailed errors weigh no more than the others).
    subspaces
        :class:`Subspace` tests: all inputs, and the P12 and jack-velocity ticks after the
        steps (:data:`RING_COLUMNS`), where the bulk modulus shows and which the test on all
        873 inputs dilutes.
    net
        :class:`NetEnvelope`: the envelope test with a network's estimates (where present).

    Each test's scale puts its limit on drifted held-out data at ``limit``."""

    weights: np.ndarray     # (d + 1, m)
    scales: np.ndarray      # (m,)
    subspaces: list
    limit: float
    net: NetEnvelope | None = None

    def envelope(self, z) -> np.ndarray:
        return _beyond(np.atleast_2d(z) @ self.weights[:-1] + self.weights[-1], self.scales)

    def score(self, z) -> np.ndarray:
        tests = [self.envelope(z)] + [t.score(z) for t in self.subspaces]
        if self.net is not None:
            tests.append(self.net.score(z))
        return np.max(tests, axis=0)


@dataclasses.dataclass
class FaultModel:
    """A loaded ensemble: input standardisation, members' weights, calibration, the OOD
    model and the service envelope it was trained over (``meta['service']``)."""

    in_mean: np.ndarray
    in_std: np.ndarray
    members: list           # each [(W, b), ...]
    calibration: np.ndarray  # per output, >= 1
    meta: dict
    ood: OodModel | None = None

    def standardise(self, x) -> np.ndarray:
        return (np.atleast_2d(x) - self.in_mean) / self.in_std

    def predict_normalised(self, x):
        """Ensemble mean and standard deviation (calibrated) of the outputs in units of each
        range, for input rows ``x`` ``(n, d)`` (:func:`model_inputs`)."""
        z = self.standardise(x)
        k = len(FAULTS)
        o = np.array([mlp_forward(weights, z) for weights in self.members])
        mus = o[:, :, :k]
        var = np.mean(np.exp(np.clip(o[:, :, k:], -30, 10)), axis=0) + np.var(mus, axis=0)
        return mus.mean(axis=0), np.sqrt(var) * self.calibration

    def ood_score(self, x) -> np.ndarray:
        """Out-of-distribution score of input rows ``x``."""
        return self.ood.score(self.standardise(x))

    def estimate(self, record: dict, conditions: Conditions) -> FaultEstimate:
        """Estimate from one pre-flight record (see :func:`preflight_features`) and the test
        conditions the bench measured (see the module on ``mismatch`` and ``note``)."""
        x = model_inputs(record, conditions)
        note = ''
        if conditions.assumed:
            grid = np.array(list(itertools.product(*[
                [lo + (hi - lo) * q for q in (1 / 6, 0.5, 5 / 6)]
                for lo, hi in (self.meta['service'][n] for n in CONDITIONS)])))
            xs = np.hstack([np.repeat(x[None, :N_FEATURES], len(grid), axis=0), grid])
            mus, sds = self.predict_normalised(xs)
            mu = mus.mean(axis=0)
            sd = np.maximum(np.sqrt(np.mean(sds ** 2, axis=0) + np.var(mus, axis=0)),
                            self.predict_normalised(x[None, :])[1][0])
            score = float(np.min(self.ood_score(xs)))
            note = ('test conditions not measured (nominal assumed): estimates averaged over '
                    'the service envelope, deviations include their spread')
            reasons = []
        else:
            mu, sd = (a[0] for a in self.predict_normalised(x[None, :]))
            score = float(self.ood_score(x[None, :])[0])
            # one phrase per measured condition outside the envelope trained over
            reasons = outside_ranges(self.meta['service'], conditions)
        limit = float(self.ood.limit)
        if score > limit:
            reasons.insert(0, f'the pre-flight check lies outside what the network was trained '
                              f'on: OOD score {score:.3g}, limit {limit:.3g}')
        mismatch = '; '.join(reasons)
        if mismatch:
            sd = np.maximum(sd, 1.0 / math.sqrt(12.0))
        vals = {f.name: float(f.lo + mu[j] * f.span) for j, f in enumerate(FAULTS)}
        stds = {f.name: float(sd[j] * f.span) for j, f in enumerate(FAULTS)}
        return FaultEstimate(vals, stds, score, limit, mismatch, note)

    def data(self) -> tuple:
        out = (self.in_mean, self.in_std, np.array([flatten_weights(m) for m in self.members]),
               self.calibration, self.ood.weights, self.ood.scales)
        for t in self.ood.subspaces:
            out += (t.basis, t.variances)
        if self.ood.net is not None:
            out += (flatten_weights(self.ood.net.weights), self.ood.net.scales)
        return out


def load_faults(path: Path | None = None) -> FaultModel:
    """The shipped pre-flight network (:data:`FAULTS_FILE`)."""
    path = Path(path) if path is not None else models_dir('health') / FAULTS_FILE
    return read_faults(path)


def _read_faults(path: Path) -> FaultModel:
    data, meta = load_artefact(path, REBUILD)
    if tuple(meta.get('outputs', ())) != FAULT_NAMES:
        raise ArtefactError(f'{path}: outputs {meta.get("outputs")} are not {FAULT_NAMES}: '
                            f'rebuild it with python -m {REBUILD}')
    subs = meta.get('ood', {}).get('subspaces', [])
    net = meta.get('ood', {}).get('net')
    if 'ood' not in meta or len(data) != 6 + 2 * len(subs) + 2 * bool(net) or \
            data[0].size != N_INPUTS:
        raise ArtefactError(f'{path}: not the {N_INPUTS}-input network with an OOD model: '
                            f'rebuild it with python -m {REBUILD}')
    in_mean, in_std, flat, cal, weights, scales = data[:6]
    sizes = [in_mean.size] + list(meta['hidden']) + [2 * len(FAULTS)]
    members = [split_weights(theta, sizes) for theta in flat]
    tests = [Subspace(int(t['columns'][0]), int(t['columns'][1]), data[6 + 2 * j],
                      data[7 + 2 * j], float(t['residual_ms']), float(t['scale']))
             for j, t in enumerate(subs)]
    ood = OodModel(weights, scales, tests, float(meta['ood']['limit']))
    if net:
        k = 6 + 2 * len(subs)
        ood.net = NetEnvelope(split_weights(data[k], [in_mean.size] + list(net['hidden'])
                                            + [data[k + 1].size]),
                              data[k + 1], float(net['scale']))
    return FaultModel(in_mean, in_std, members, cal, meta, ood)


#: :func:`load_faults`'s reader, once per state of the file
#: (:class:`.artefacts.CachedReader`).
read_faults = CachedReader(_read_faults)
