"""Fit the reference's 8-coefficient function (:mod:`eha_ros.surrogates.ga`) by a real-coded
genetic algorithm, refit it by gradient, and write ``ga.npz``.

Build: ``python -m eha_ros.training.ga``.

Admissible coefficients (:mod:`eha_ros.surrogates.ga`): an individual whose denominators
fall below ``MIN_DENOMINATOR`` over the spool stroke gets an infinite fitness.

Genetic algorithm
-----------------
Genes are the coefficients in a signed-log coordinate ``z = asinh(c)`` (the bounds span 14
decades through zero; a Gaussian step in ``z`` is a relative step for large coefficients).
Tournament selection, blend crossover (BLX-alpha) in ``z``, Gaussian mutation in ``z`` with a
geometrically shrinking step, elitism, offspring clipped to the bounds, pinned genes
(``lb == ub``) left alone.  The initial population is the reference's initial coefficients
plus individuals drawn around them and across the bounds.  All randomness comes from one
seeded ``np.random.Generator``.  Fitness: the relative Euclidean-norm error
``||P_fit - P_map||_2 / ||P_map||_2`` over the training map.

:func:`gradient_fit` refits the same function with ``scipy.optimize.least_squares``
(training only; scipy is imported there) to tell the function's limit from the genetic
algorithm's.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit, prange

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.physics import PlantParams, default_params, params_hash
from eha_ros.physics.maps import FLOW_MAX_M3_S
from eha_ros.surrogates.base import SurrogateError
from eha_ros.surrogates.ga import Q_REF_M3_S, XS_REF_M, formula, ga_p12, make_ga
from eha_ros.training.database import get_database, heldout_maps

__all__ = ['THESIS_INITIAL', 'THESIS_LB', 'THESIS_UB', 'MIN_DENOMINATOR', 'GASettings',
           'GAResult', 'coefficient_errors', 'min_denominators', 'genetic_fit', 'evolve',
           'gradient_fit', 'nominal_offgrid_map', 'build_artefact']

#: The reference's initial coefficients and bounds (``c1`` pinned at 2e7 Pa).
THESIS_INITIAL = np.array([2e7, 2e2, -1.5e7, 800.0, 1e4, -8e5, 5e3, 1e4])
THESIS_LB = np.array([2e7, 1e2, -1e9, -1e7, -1e7, -1e7, -1e7, -1e7])
THESIS_UB = np.array([2e7, 1e3, 1e9, 1e7, 1e7, 1e7, 1e7, 1e7])
for _a in (THESIS_INITIAL, THESIS_LB, THESIS_UB):
    _a.setflags(write=False)


#: Smallest admissible value of either denominator over the spool stroke.
MIN_DENOMINATOR = 0.1


@njit(cache=True, parallel=True)
def _sq_errors(c, wx, wq, p, out):
    """Sum of squared residuals of each coefficient row of ``c`` (``inf`` if not finite)."""
    for k in prange(c.shape[0]):
        ck = c[k]
        acc = 0.0
        for i in range(p.size):
            r = ga_p12(ck, wx[i], wq[i]) - p[i]
            acc += r * r
        out[k] = acc if math.isfinite(acc) else np.inf


def coefficient_errors(c, xs_m, q_m3_s, p12_pa) -> np.ndarray:
    """``||P_fit - P||_2 / ||P||_2`` over all points, one per row of ``c`` (shape ``(8,)``
    or ``(n, 8)``); ``inf`` where the function is not finite."""
    c = np.ascontiguousarray(np.atleast_2d(np.asarray(c, dtype=float)))
    wx = np.ascontiguousarray(np.ravel(xs_m), dtype=float) / XS_REF_M
    wq = np.ascontiguousarray(np.ravel(q_m3_s), dtype=float) / Q_REF_M3_S
    p = np.ascontiguousarray(np.ravel(p12_pa), dtype=float)
    out = np.empty(c.shape[0])
    _sq_errors(c, wx, wq, p, out)
    return np.sqrt(out) / np.linalg.norm(p)


def min_denominators(c, xs_max_m: float) -> np.ndarray:
    """Smallest value of each denominator over ``|XS| <= xs_max_m``: shape ``(n, 2)``."""
    c = np.atleast_2d(np.asarray(c, dtype=float))
    s_max = (xs_max_m / XS_REF_M) ** 2
    out = np.empty((c.shape[0], 2))
    for col, (a, b) in enumerate(((c[:, 3], c[:, 4]), (c[:, 6], c[:, 7]))):
        # 1 + a s + b s^2 over s = wxs^2 in [0, s_max]: the ends, and the vertex if inside
        m = np.minimum(1.0, 1.0 + a * s_max + b * s_max * s_max)
        with np.errstate(divide='ignore', invalid='ignore'):
            sv = np.where(b > 0, -a / (2.0 * b), -1.0)
        inside = (sv > 0) & (sv < s_max)
        m = np.where(inside, np.minimum(m, 1.0 - a * a / (4.0 * np.where(b > 0, b, 1.0))), m)
        out[:, col] = m
    return out


@dataclasses.dataclass(frozen=True)
class GASettings:
    """Settings of :func:`genetic_fit` (steps in the gene coordinate ``z = asinh(c)``)."""

    population: int = 120
    generations: int = 300
    stall_generations: int = 60
    tournament: int = 3
    crossover_rate: float = 0.9
    blend_alpha: float = 0.3
    mutation_rate: float = 0.3
    mutation_sigma_start: float = 1.0
    mutation_sigma_end: float = 0.003
    elite: int = 4
    init_sigma: float = 2.0
    init_uniform_fraction: float = 0.25
    seed: int = 20240611

    def check(self) -> None:
        if self.population < 4 or self.generations < 1 or self.stall_generations < 1:
            raise SurrogateError('GA needs population >= 4, generations >= 1 and '
                                 'stall_generations >= 1')
        if not 1 <= self.tournament <= self.population:
            raise SurrogateError('GA tournament size must lie in [1, population]')
        if not 0 <= self.elite < self.population:
            raise SurrogateError('GA elite count must lie in [0, population)')
        for name in ('crossover_rate', 'mutation_rate', 'init_uniform_fraction'):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise SurrogateError(f'GA {name} must lie in [0, 1]')
        if not (self.mutation_sigma_start > 0 and self.mutation_sigma_end > 0):
            raise SurrogateError('GA mutation steps must be positive')


@dataclasses.dataclass
class GAResult:
    """Best coefficients, their fitness (relative error), the best fitness per generation
    (``history[0]``: the first population), fitness evaluations and wall time [s]."""

    coefficients: np.ndarray
    error: float
    history: np.ndarray
    evaluations: int
    wall_s: float

    @property
    def generations(self) -> int:
        return self.history.size - 1


def genetic_fit(xs_m, q_m3_s, p12_pa, xs_max_m: float, settings: GASettings | None = None,
                x0=THESIS_INITIAL, lb=THESIS_LB, ub=THESIS_UB) -> GAResult:
    """Fit the function to P12 [Pa] at points ``(xs_m, q_m3_s)`` with the genetic algorithm.

    Parameters
    ----------
    xs_m, q_m3_s, p12_pa : array_like
        Training points [m, m^3/s] and values [Pa], same size.
    xs_max_m : float
        Spool stroke [m] over which the denominators must stay admissible.
    settings : GASettings
        Population, operators and seed.
    x0, lb, ub : array_like of 8
        Initial coefficients (an individual of the first population) and bounds.
    """
    s = settings if settings is not None else GASettings()
    s.check()
    lb, ub, x0 = (np.asarray(a, dtype=float) for a in (lb, ub, x0))
    if lb.shape != (8,) or ub.shape != (8,) or x0.shape != (8,) or np.any(lb > ub):
        raise SurrogateError('GA needs 8 initial coefficients and bounds with lb <= ub')
    if np.any(x0 < lb) or np.any(x0 > ub):
        raise SurrogateError('GA initial coefficients lie outside the bounds')
    xs, q, p = (np.ravel(np.asarray(a, dtype=float)) for a in (xs_m, q_m3_s, p12_pa))
    if not (xs.size == q.size == p.size) or xs.size == 0:
        raise SurrogateError('GA training points and values must have the same, non-zero size')
    t0 = time.perf_counter()
    zlb, zub, z0 = np.arcsinh(lb), np.arcsinh(ub), np.arcsinh(x0)
    free = zub > zlb

    def coefficients(z):  # genes -> coefficients, exactly inside the bounds
        c = np.clip(np.sinh(z), lb, ub)
        c[..., ~free] = lb[~free]
        return c

    def fitness(z):
        c = coefficients(z)
        f = coefficient_errors(c, xs, q, p)
        f[np.any(min_denominators(c, xs_max_m) < MIN_DENOMINATOR, axis=1)] = np.inf
        return f

    z, err, history, evals = evolve(fitness, z0, zlb, zub, s)
    return GAResult(coefficients=coefficients(z), error=err, history=history,
                    evaluations=evals, wall_s=time.perf_counter() - t0)


def evolve(fitness, z0, zlb, zub, s: GASettings):
    """The real-coded genetic algorithm on genes ``z`` within ``[zlb, zub]`` (genes with
    ``zlb == zub`` stay pinned): ``fitness(pop)`` gives one value per row (lower is better,
    ``inf`` for an inadmissible individual).  First population: ``z0``, a Gaussian cloud around
    it and a uniform share across the bounds; then per generation tournament selection, blend
    crossover (BLX-alpha), Gaussian mutation with a geometrically shrinking step, ``elite``
    survivors; stops after ``generations`` or ``stall_generations`` without a relative
    improvement of 1e-6.  Randomness from ``numpy.random.default_rng(s.seed)``.

    Returns ``(best genes, best fitness, best fitness per generation, evaluations)``.
    """
    rng = np.random.default_rng(s.seed)
    z0, zlb, zub = (np.asarray(a, dtype=float) for a in (z0, zlb, zub))
    dim = z0.size
    free = zub > zlb

    def inside(z):   # clipped to the bounds, pinned genes at their value
        z = np.clip(z, zlb, zub)
        z[:, ~free] = zlb[~free]
        return z
    # first population: x0, Gaussian cloud around it, uniform across the bounds
    n = s.population
    n_uni = int(round(s.init_uniform_fraction * (n - 1)))
    pop = np.empty((n, dim))
    pop[0] = z0
    pop[1:n - n_uni] = z0 + s.init_sigma * rng.standard_normal((n - 1 - n_uni, dim))
    pop[n - n_uni:] = zlb + (zub - zlb) * rng.random((n_uni, dim))
    pop = inside(pop)
    fit = fitness(pop)
    evals = n
    history = [fit.min()]
    g_den = max(1, s.generations - 1)
    for g in range(s.generations):
        sigma = s.mutation_sigma_start * (s.mutation_sigma_end / s.mutation_sigma_start) ** (
            g / g_den)
        order = np.argsort(fit, kind='stable')
        elite = pop[order[:s.elite]]
        n_child = n - s.elite
        # tournament selection: the fittest of `tournament` random individuals
        cand = rng.integers(0, n, size=(2 * n_child, s.tournament))
        winners = cand[np.arange(2 * n_child), np.argmin(fit[cand], axis=1)]
        pa, pb = pop[winners[:n_child]], pop[winners[n_child:]]
        # blend crossover (BLX-alpha), gene by gene
        lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
        span = hi - lo
        u = rng.random((n_child, dim))
        child = lo - s.blend_alpha * span + u * (1.0 + 2.0 * s.blend_alpha) * span
        keep = rng.random(n_child) >= s.crossover_rate
        child[keep] = pa[keep]
        # Gaussian mutation, each free gene with probability mutation_rate
        mut = (rng.random((n_child, dim)) < s.mutation_rate) & free
        child = inside(child + mut * (sigma * rng.standard_normal((n_child, dim))))
        child_fit = fitness(child)
        evals += n_child
        pop = np.concatenate([elite, child])
        fit = np.concatenate([fit[order[:s.elite]], child_fit])
        history.append(fit.min())
        # stop when the best has not improved by 1e-6 (relative) for stall_generations
        if g + 1 >= s.stall_generations and (
                history[-1] >= history[-1 - s.stall_generations] * (1.0 - 1e-6)):
            break
    best = int(np.argmin(fit))
    return pop[best].copy(), float(fit[best]), np.array(history), evals


def gradient_fit(xs_m, q_m3_s, p12_pa, xs_max_m: float, x0=THESIS_INITIAL, lb=THESIS_LB,
                 ub=THESIS_UB, max_nfev: int = 2000) -> tuple[np.ndarray, float, dict]:
    """Fit the same function with ``scipy.optimize.least_squares`` (trust-region reflective,
    analytic Jacobian) from ``x0`` within ``[lb, ub]``; pinned coefficients stay fixed.

    Admissibility is kept by hinge residuals ``10 max(0, MIN_DENOMINATOR - D(XS))`` on 65
    spool positions over the stroke.  Training only: imports scipy.

    Returns
    -------
    coefficients : ndarray
    error : float
        Relative Euclidean-norm error on the training points.
    info : dict
        ``nfev``, ``status``, ``message``, ``wall_s``, ``admissible``.
    """
    from scipy.optimize import least_squares

    lb, ub = np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)
    x0 = np.clip(np.asarray(x0, dtype=float), lb, ub)
    free = ub > lb
    wx = np.ravel(np.asarray(xs_m, dtype=float)) / XS_REF_M
    wq = np.ravel(np.asarray(q_m3_s, dtype=float)) / Q_REF_M3_S
    p = np.ravel(np.asarray(p12_pa, dtype=float))
    norm = np.linalg.norm(p)
    w2, w4, wq3 = wx * wx, wx ** 4, wq ** 3
    sg = np.linspace(0.0, (xs_max_m / XS_REF_M) ** 2, 65)  # wxs^2 over the stroke
    weight = 10.0

    def full(v):
        c = lb.copy()
        c[free] = v
        return c

    def residuals(v):
        c = full(v)
        with np.errstate(all='ignore'):
            r = (formula(c, wx, wq) - p) / norm
        dens = np.concatenate([1.0 + c[a] * sg + c[b] * sg * sg for a, b in ((3, 4), (6, 7))])
        pen = weight * np.maximum(0.0, MIN_DENOMINATOR - dens)
        return np.nan_to_num(np.concatenate([r, pen]), nan=1e6, posinf=1e6, neginf=-1e6)

    def jacobian(v):
        c = full(v)
        th = np.tanh(c[1] * wx)
        d1 = 1.0 + c[3] * w2 + c[4] * w4
        d2 = 1.0 + c[6] * w2 + c[7] * w4
        j = np.empty((p.size, 8))
        j[:, 0] = th
        j[:, 1] = c[0] * wx * (1.0 - th * th)
        j[:, 2] = wq / d1
        j[:, 3] = -c[2] * wq * w2 / d1 ** 2
        j[:, 4] = -c[2] * wq * w4 / d1 ** 2
        j[:, 5] = wq3 / d2
        j[:, 6] = -c[5] * wq3 * w2 / d2 ** 2
        j[:, 7] = -c[5] * wq3 * w4 / d2 ** 2
        jp = np.zeros((2 * sg.size, 8))
        for k, (a, b) in enumerate(((3, 4), (6, 7))):   # each denominator's hinges
            rows = slice(k * sg.size, (k + 1) * sg.size)
            g = (1.0 + c[a] * sg + c[b] * sg * sg) < MIN_DENOMINATOR
            jp[rows, a] = -weight * sg * g
            jp[rows, b] = -weight * sg * sg * g
        jac = np.concatenate([j / norm, jp])[:, free]
        return np.nan_to_num(jac, nan=0.0, posinf=0.0, neginf=0.0)

    t0 = time.perf_counter()
    v0 = x0[free]
    # least_squares wants x0 strictly inside the bounds
    v0 = np.clip(v0, lb[free] + 1e-9 * (ub[free] - lb[free]),
                 ub[free] - 1e-9 * (ub[free] - lb[free]))
    res = least_squares(residuals, v0, jac=jacobian, bounds=(lb[free], ub[free]),
                        x_scale='jac', max_nfev=max_nfev, method='trf')
    c = full(res.x)
    err = float(coefficient_errors(c, xs_m, q_m3_s, p12_pa)[0])
    admissible = bool(np.all(min_denominators(c, xs_max_m) >= MIN_DENOMINATOR * (1 - 1e-6)))
    return c, err, {'nfev': int(res.nfev), 'status': int(res.status),
                    'message': str(res.message), 'wall_s': time.perf_counter() - t0,
                    'admissible': admissible}


def nominal_offgrid_map(params: PlantParams | None = None, xs_grid_m=None, q_grid_m3_s=None):
    """The nominal-wear map at the midpoints of a training grid (default: DB5's), from the
    databases' map transient: ``(xs_m, q_m3_s, p12_pa)``, each of shape ``(n_xs-1, n_q-1)``."""
    p = params if params is not None else default_params()
    if xs_grid_m is None or q_grid_m3_s is None:
        db = get_database('DB5', p)
        xs_grid_m, q_grid_m3_s = db.xs_m, db.q_m3_s
    xs = 0.5 * (xs_grid_m[1:] + xs_grid_m[:-1])
    q = 0.5 * (q_grid_m3_s[1:] + q_grid_m3_s[:-1])
    x, qq = np.meshgrid(xs, q, indexing='ij')
    (_, _, _, _, p12), = heldout_maps(wear=[(p.overlap_supply_m, p.radial_clearance_m)],
                                      params=p, xs_m=xs, q_m3_s=q)
    return x, qq, p12


def build_artefact(params: PlantParams | None = None, path: Path | None = None,
                   settings: GASettings | None = None, gradient: bool = True) -> Path:
    """Fit the function on the nominal-wear map (DB5) and write ``models/ga.npz``.

    Parameters
    ----------
    params : PlantParams, optional
        Physics parameters (default: the nominal ones).
    path : Path, optional
        Output file (default ``models/ga.npz``).
    settings : GASettings, optional
        Genetic-algorithm settings and seed (default :class:`GASettings()`).
    gradient : bool
        Also refit with the gradient optimiser from the GA's best and from the reference's
        initial coefficients and record both in the meta.

    Returns
    -------
    Path
        The artefact written; it carries the GA's coefficients.
    """
    p = params if params is not None else default_params()
    s = settings if settings is not None else GASettings()
    path = Path(path) if path is not None else models_dir('surrogates') / 'ga.npz'
    t0 = time.perf_counter()
    db = get_database('DB5', p)
    x, q = np.meshgrid(db.xs_m, db.q_m3_s, indexing='ij')
    p12 = db.p12_pa[:, :, 0, 0]
    stroke = float(p.spool_stroke_m)
    res = genetic_fit(x, q, p12, stroke, s)
    xh, qh, ph = nominal_offgrid_map(p, db.xs_m, db.q_m3_s)
    held = float(coefficient_errors(res.coefficients, xh, qh, ph)[0])
    grad = {}
    if gradient:
        for label, start in (('from_ga', res.coefficients), ('from_initial', THESIS_INITIAL)):
            c, err, info = gradient_fit(x, q, p12, stroke, x0=start)
            grad[label] = {'coefficients': c.tolist(), 'train_error': err,
                           'heldout_error': float(coefficient_errors(c, xh, qh, ph)[0]),
                           'nfev': info['nfev'], 'admissible': info['admissible'],
                           'wall_s': round(info['wall_s'], 2)}
    meta = {
        'kind': 'ga', 'format': 1,
        'function': 'c1 tanh(c2 wxs) + c3 wq/(1 + c4 wxs^2 + c5 wxs^4) '
                    '+ c6 wq^3/(1 + c7 wxs^2 + c8 wxs^4)',
        'inputs': [{'name': 'xs_m', 'unit': 'm'}, {'name': 'q_m3_s', 'unit': 'm^3/s'},
                   {'name': 'overlap_m', 'unit': 'm', 'used': False},
                   {'name': 'clearance_m', 'unit': 'm', 'used': False}],
        'output': {'name': 'p12_pa', 'unit': 'Pa'},
        'normalisation': {'wxs': 'xs_m / xs_ref_m', 'wq': 'q_m3_s / q_ref_m3_s',
                          'xs_ref_m': XS_REF_M, 'q_ref_m3_s': Q_REF_M3_S,
                          'p12': 'Pa, not scaled (c1 = 2e7 Pa)'},
        'clamp': {'xs_max_m': stroke, 'q_max_m3_s': FLOW_MAX_M3_S},
        'coefficients': res.coefficients.tolist(),
        'bounds': {'initial': THESIS_INITIAL.tolist(), 'lb': THESIS_LB.tolist(),
                   'ub': THESIS_UB.tolist(), 'min_denominator': MIN_DENOMINATOR},
        'ga': {'settings': dataclasses.asdict(s), 'generations_run': res.generations,
               'evaluations': res.evaluations, 'wall_s': round(res.wall_s, 2),
               'train_error': res.error, 'heldout_error': held,
               'initial_error': float(coefficient_errors(THESIS_INITIAL, x, q, p12)[0])},
        'gradient': grad,
        'training': {'database': 'DB5', 'wear': {'overlap_m': float(db.overlap_m[0]),
                                                 'clearance_m': float(db.clearance_m[0])},
                     'points': int(p12.size),
                     'heldout': 'nominal map at the midpoints of the DB5 grid'},
        'limits': 'no wear inputs (fitted at nominal wear; overlap and clearance ignored); '
                  'inputs clamped to the training ranges',
        'fluid_hash': db.meta['fluid_hash'], 'params_hash': params_hash(p),
    }
    meta['build_wall_s'] = round(time.perf_counter() - t0, 2)
    sur = make_ga(res.coefficients, stroke, FLOW_MAX_M3_S, meta)
    save_artefact(path, sur.data, meta)
    return path


if __name__ == '__main__':
    sys.exit(print(build_artefact()))
