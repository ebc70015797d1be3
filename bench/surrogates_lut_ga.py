"""Accuracy and speed of the lookup-table (``lut``) and genetic-algorithm (``ga``) surrogates,
from the shipped artefacts, side by side with the alternatives a user would pick: scipy's
``RegularGridInterpolator`` on the same table, and scipy's ``differential_evolution`` on the
same 8-coefficient function and bounds.

Accuracy: the reference's metric, relative error in Euclidean norm of each map,
``||P_pred - P_true||_2 / ||P_true||_2`` (map = all XS x Q of one overlap/clearance pair),
mean and max over the maps.
    lut   12 fresh maps at random wear (seed 2024), on the midpoints of the spool grid x 30
          random flows (off every table axis); also the 12 maps of the network benchmark
          (seed 4242, database spool grid x 15 flows); tables from DB1 (the reference's) and
          DB2 for comparison; where the error sits (share of squared error by |XS| band).
    ga    the nominal map at the midpoints of the DB5 grid (132 x 132, off the training grid)
          for the GA's, the gradient refits' and the reference's initial coefficients; the
          nominal fit on the random-wear maps above (the function has no wear input); the
          function's limit per wear pair: refitted (gradient, from the shipped coefficients)
          on each DB1 map and evaluated on that map and on a fresh off-grid map at its wear.
    both  "small signal": the region the closed loop of the shipped scenarios visits
          (|XS| < 25 um, |Q| < 1e-5 or 1e-6 m^3/s), 80 x 20 random points at 5 wear pairs;
          the map-wide metric above is dominated by the large peaks at large flows.
Speed: the kernel called as the plant calls it (an njit loop over 1e6 random inputs, and over
a smooth 1e6-step trajectory), a Python-level scalar call, batch throughput of
``FluidSurrogate.p12`` on 1e6 points.  Build: ``build_artefact`` timed into a temporary folder
(``--no-build``: the times recorded in the artefacts).

    python bench/surrogates_lut_ga.py [--no-build] [--de-maxiter 300] [--smoke]

``--smoke`` runs the same code on tiny sets (a few maps, 2,000 calls, a small table and GA
build, one differential-evolution generation): a check that the bench runs, no figure.
"""

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from numba import njit

from eha_ros.physics import default_params
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, transient_map
from eha_ros.surrogates import ga, lut
from eha_ros.training import ga as ga_fit
from eha_ros.training import lut as lut_build
from eha_ros.artefacts import load_artefact, models_dir
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.physics.maps import FLOW_MAX_M3_S
from eha_ros.training.database import get_database, map_errors

N_CALLS = 1_000_000

#: Sizes of a ``--smoke`` run (see the module docstring); ``None``: the full bench.
SMOKE = {'calls': 2000, 'maps': 2, 'db1_pairs': 2, 'de_maxiter': 1,
         'lut_grid': {'n_xs': 9, 'n_q': 5, 'n_overlap': 2, 'n_clearance': 2},
         'ga': {'population': 8, 'generations': 2, 'stall_generations': 2, 'elite': 1}}


@njit(cache=True)
def _kernel_loop(kernel, data, xs, q, lap, clr):
    acc = 0.0
    for i in range(xs.size):
        acc += kernel(data, xs[i], q[i], lap[i], clr[i])
    return acc


def _summary(errs):
    errs = np.asarray(errs)
    return {'mean_pct': round(float(errs.mean()) * 100, 4),
            'max_pct': round(float(errs.max()) * 100, 4), 'n_maps': int(errs.size)}


def _inputs(n=N_CALLS, seed=0):
    """Random inputs over the tables' ranges, and a smooth trajectory (1e6 steps of 1 us of
    a 50 Hz spool and flow oscillation at nominal wear)."""
    p = default_params()
    rng = np.random.default_rng(seed)
    rand = (rng.uniform(-p.spool_stroke_m, p.spool_stroke_m, n),
            rng.uniform(-FLOW_MAX_M3_S, FLOW_MAX_M3_S, n),
            rng.uniform(*WEAR_RANGES['overlap_m'], n),
            rng.uniform(*WEAR_RANGES['radial_clearance_m'], n))
    t = np.arange(n) * 1e-6
    smooth = (0.3 * p.spool_stroke_m * np.sin(2 * np.pi * 50 * t),
              0.5 * FLOW_MAX_M3_S * np.cos(2 * np.pi * 50 * t),
              np.full(n, p.overlap_supply_m), np.full(n, p.radial_clearance_m))
    return rand, smooth


def _best(fn, repeat):
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _timing(s, rand, smooth):
    """Per-call [us] from an njit loop (random / smooth inputs), Python scalar call [us],
    batch points/s of ``p12``."""
    n = rand[0].size
    _kernel_loop(s.kernel, s.data, *(a[:10] for a in rand))  # compile
    t_rand = _best(lambda: _kernel_loop(s.kernel, s.data, *rand), 7)
    t_smooth = _best(lambda: _kernel_loop(s.kernel, s.data, *smooth), 7)
    m = min(20000, n)
    s.p12(0.0, 0.0, 0.0, 3e-6)
    args = [tuple(float(a[i]) for a in rand) for i in range(m)]
    t0 = time.perf_counter()
    for a in args:
        s.p12(*a)
    py = (time.perf_counter() - t0) / m
    s.p12(*(a[:10] for a in rand))
    bt = _best(lambda: s.p12(*rand), 3)
    return {'kernel_njit_loop_random_us': round(t_rand / n * 1e6, 4),
            'kernel_njit_loop_smooth_us': round(t_smooth / n * 1e6, 4),
            'python_scalar_call_us': round(py * 1e6, 2),
            'batch_points_per_s': round(n / bt)}


def _error_by_band(model, maps):
    """Share of the squared error of ``maps`` by |XS| band."""
    bands = [(0.0, 5e-6), (5e-6, 2e-5), (2e-5, 1e-4), (1e-4, math.inf)]
    tot = np.zeros(len(bands))
    for xs, q, lap, clr, p12 in maps:
        r2 = (model(xs[:, None], q[None, :], lap, clr) - p12) ** 2
        for k, (lo, hi) in enumerate(bands):
            tot[k] += r2[(np.abs(xs) >= lo) & (np.abs(xs) < hi)].sum()
    return {f'|xs| {lo * 1e6:g}-{hi * 1e6:g} um': round(float(v / tot.sum()), 3)
            for (lo, hi), v in zip(bands, tot)}


def _db_grid_maps(n_maps, seed, n_q=15):
    """Maps at random wear on the database spool grid x ``n_q`` flows (as the network
    benchmark draws them)."""
    rng = np.random.default_rng(seed)
    lap = rng.uniform(*WEAR_RANGES['overlap_m'], n_maps)
    clr = rng.uniform(*WEAR_RANGES['radial_clearance_m'], n_maps)
    xs = spool_grid(133)
    q = np.linspace(-FLOW_MAX_M3_S, FLOW_MAX_M3_S, n_q)
    r = transient_map(xs[:, None, None], q[None, :, None], lap[None, None, :],
                      clr[None, None, :])['p12_pa']
    return [(xs, q, float(lap[m]), float(clr[m]), r[:, :, m]) for m in range(n_maps)]


#: Wear pairs of the small-signal maps: nominal and four spread over WEAR_RANGES.
SMALL_SIGNAL_WEAR = ((1e-6, 2.5e-6), (-1e-6, 5e-6), (4e-6, 1.5e-6), (6e-6, 1e-6),
                     (-2e-6, 6e-6))


def _small_signal_maps(q_max_m3_s, seed=5):
    """Maps in the region the closed loop of the shipped scenarios visits: 80 random spool
    positions in +-25 um x 20 random flows in +-q_max, at :data:`SMALL_SIGNAL_WEAR`."""
    rng = np.random.default_rng(seed)
    xs = np.sort(rng.uniform(-25e-6, 25e-6, 80))
    q = np.sort(rng.uniform(-q_max_m3_s, q_max_m3_s, 20))
    x, qq = np.meshgrid(xs, q, indexing='ij')
    return [(xs, q, lap, clr, transient_map(x, qq, lap, clr)['p12_pa'])
            for lap, clr in SMALL_SIGNAL_WEAR]


def _small_signal(model, small):
    return {k: _summary(map_errors(model, m)) for k, m in small.items()}


def _bench_lut(rand, smooth, maps, db_maps, small, build, smoke=False):
    from scipy.interpolate import RegularGridInterpolator

    s = load_surrogate('lut')
    axes, table = s.data[:4], s.data[4]
    out = {'grid': {k: s.meta['data'][k] for k in ('source', 'n_xs', 'n_q', 'q_density',
                                                   'n_overlap', 'n_clearance')},
           'artefact_bytes': (models_dir('surrogates') / 'lut.npz').stat().st_size,
           'table_dtype': str(table.dtype)}
    acc = {'random_wear_offgrid': _summary(map_errors(s.p12, maps)),
           'random_wear_db_grid_15_flows': _summary(map_errors(s.p12, db_maps)),
           'error_share_by_xs_band': _error_by_band(s.p12, maps),
           'small_signal': _small_signal(s.p12, small)}
    for name in ('DB1', 'DB2'):
        db = get_database(name)
        t = lut.make_lut(db.xs_m, db.q_m3_s, db.overlap_m, db.clearance_m, db.p12_pa)
        acc[f'table_{name}'] = {
            'shape': list(db.p12_pa.shape),
            'random_wear_offgrid': _summary(map_errors(t.p12, maps)),
            'random_wear_db_grid_15_flows': _summary(map_errors(t.p12, db_maps)),
            'small_signal': _small_signal(t.p12, small)}
    out['accuracy'] = acc
    out['speed'] = _timing(s, rand, smooth)
    # scipy's interpolator on the same table
    rgi = RegularGridInterpolator(axes, table.astype(np.float64), method='linear',
                                  bounds_error=False, fill_value=None)

    def rgi_model(x, q, a, c):
        b = np.broadcast_arrays(x, q, a, c)
        pts = np.stack([np.clip(v.ravel(), ax[0], ax[-1]) for v, ax in zip(b, axes)], axis=1)
        return rgi(pts).reshape(b[0].shape)

    pts = np.stack(rand, axis=1)
    pts_c = np.stack([np.clip(pts[:, d], axes[d][0], axes[d][-1]) for d in range(4)], axis=1)
    m = 2000
    rgi(pts_c[:1])
    t0 = time.perf_counter()
    for i in range(m):
        rgi(pts_c[i:i + 1])
    py = (time.perf_counter() - t0) / m
    bt = _best(lambda: rgi(pts_c), 3)
    out['scipy_regular_grid_interpolator'] = {
        'same_table': True,
        'random_wear_offgrid': _summary(map_errors(rgi_model, maps)),
        'max_abs_difference_to_lut_pa': float(np.abs(rgi(pts_c) - s.p12(*rand)).max()),
        'python_scalar_call_us': round(py * 1e6, 2),
        'batch_points_per_s': round(pts.shape[0] / bt)}
    if build:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            lut_build.build_artefact(path=Path(d) / 'lut.npz',
                                     grid=SMOKE['lut_grid'] if smoke else None,
                                     n_validation_maps=1 if smoke else 5)
            out['build_s'] = round(time.perf_counter() - t0, 1)
    else:
        out['build_s_recorded'] = s.meta.get('build_wall_s')
    return out


def _bench_ga(rand, smooth, maps, small, build, de_maxiter, smoke=False):
    from scipy.optimize import differential_evolution

    p = default_params()
    s = load_surrogate('ga')
    meta = s.meta
    db = get_database('DB5')
    x, q = np.meshgrid(db.xs_m, db.q_m3_s, indexing='ij')
    p12 = db.p12_pa[:, :, 0, 0]
    xh, qh, ph = ga_fit.nominal_offgrid_map(p, db.xs_m, db.q_m3_s)
    stroke = p.spool_stroke_m

    def errs(c):
        err = ga_fit.coefficient_errors
        return {'train_pct': round(float(err(c, x, q, p12)[0]) * 100, 3),
                'heldout_pct': round(float(err(c, xh, qh, ph)[0]) * 100, 3)}

    out = {'coefficients': meta['coefficients'], 'normalisation': meta['normalisation'],
           'ga_settings': meta['ga']['settings'],
           'ga_recorded': {k: meta['ga'][k] for k in ('generations_run', 'evaluations',
                                                      'wall_s')}}
    acc = {'nominal_offgrid': {'ga': errs(s.data[0]),
                               'reference_initial': errs(ga_fit.THESIS_INITIAL)}}
    for label, rec in meta.get('gradient', {}).items():
        if isinstance(rec, dict):
            acc['nominal_offgrid'][f'gradient_{label}'] = errs(np.array(rec['coefficients']))
    # the same function without the reference's bounds (the function's own limit)
    wide = np.r_[2e7, np.full(7, 1e12)]
    c_wide, _, _ = ga_fit.gradient_fit(x, q, p12, stroke, x0=s.data[0],
                                       lb=np.r_[2e7, -wide[1:]], ub=wide)
    acc['nominal_offgrid']['gradient_from_ga_unbounded'] = errs(c_wide)
    acc['error_share_by_xs_band_nominal'] = _error_by_band(
        lambda a, b, c_, d: ga.formula(s.data[0], a / ga.XS_REF_M, b / ga.Q_REF_M3_S),
        [(xh[:, 0], qh[0], 0.0, 0.0, ph)])
    acc['nominal_fit_on_random_wear_offgrid'] = _summary(map_errors(s.p12, maps))
    acc['small_signal'] = _small_signal(s.p12, small)
    # the function's limit per wear pair: refit on each DB1 map
    db1 = get_database('DB1')
    pairs = [(i, j) for i in range(db1.overlap_m.size) for j in range(db1.clearance_m.size)]
    pairs = pairs[:SMOKE['db1_pairs']] if smoke else pairs
    fresh = lut_build.heldout_maps(0, wear=[(db1.overlap_m[i], db1.clearance_m[j])
                                            for i, j in pairs])
    on_map, off_grid = [], []
    for (i, j), (fx, fq, _, _, fp) in zip(pairs, fresh):
        xi, qi = np.meshgrid(db1.xs_m, db1.q_m3_s, indexing='ij')
        c, e, _ = ga_fit.gradient_fit(xi, qi, db1.p12_pa[:, :, i, j], stroke, x0=s.data[0])
        on_map.append(e)
        fxx, fqq = np.meshgrid(fx, fq, indexing='ij')
        off_grid.append(ga_fit.coefficient_errors(c, fxx, fqq, fp)[0])
    acc['refit_per_db1_map'] = {'on_the_db1_map': _summary(on_map),
                                'fresh_offgrid_map_same_wear': _summary(off_grid)}
    out['accuracy'] = acc
    out['speed'] = _timing(s, rand, smooth)
    # scipy differential evolution: same function, fitness, admissibility and bounds
    free = ga_fit.THESIS_UB > ga_fit.THESIS_LB
    count = [0]

    def fitness(v):  # v: (7, S) with vectorized=True
        count[0] += v.shape[1]
        c = np.tile(ga_fit.THESIS_LB, (v.shape[1], 1))
        c[:, free] = v.T
        f = ga_fit.coefficient_errors(c, x, q, p12)
        poles = ga_fit.min_denominators(c, stroke) < ga_fit.MIN_DENOMINATOR
        f[np.any(poles, axis=1)] = np.inf
        return f

    t0 = time.perf_counter()
    bounds = list(zip(ga_fit.THESIS_LB[free], ga_fit.THESIS_UB[free]))
    r = differential_evolution(fitness, bounds,
                               x0=ga_fit.THESIS_INITIAL[free], maxiter=de_maxiter, popsize=15,
                               seed=0, polish=False, vectorized=True, updating='deferred',
                               tol=0.0)
    wall = time.perf_counter() - t0
    c_de = ga_fit.THESIS_LB.copy()
    c_de[free] = r.x
    out['scipy_differential_evolution'] = {
        'settings': {'maxiter': de_maxiter, 'popsize': 15, 'polish': False, 'seed': 0,
                     'x0': 'reference initial coefficients'},
        'evaluations': count[0], 'wall_s': round(wall, 1), **errs(c_de),
        'coefficients': c_de.tolist()}
    if build:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            settings = ga_fit.GASettings(**SMOKE['ga']) if smoke else None
            bp = ga_fit.build_artefact(path=Path(d) / 'ga.npz', settings=settings,
                                       gradient=not smoke)
            out['build_s'] = round(time.perf_counter() - t0, 1)
            built = load_artefact(bp, 'eha_ros.training.ga')[0][0]
            # a smoke build runs other settings: it is not expected to reproduce the shipped
            out['build_reproduces_shipped'] = (None if smoke else
                                               bool(np.array_equal(built, s.data[0])))
    else:
        out['build_s_recorded'] = meta.get('build_wall_s')
    return out


def run(build: bool = True, de_maxiter: int = 300, smoke: bool = False) -> dict:
    """All figures as one dict (see the module docstring); ``smoke``: the sizes of
    :data:`SMOKE`."""
    t0 = time.perf_counter()
    n_maps = SMOKE['maps'] if smoke else 12
    rand, smooth = _inputs(SMOKE['calls'] if smoke else N_CALLS)
    maps = lut_build.heldout_maps(n_maps, seed=2024, n_q=30)
    db_maps = _db_grid_maps(n_maps, seed=4242)
    small = {'xs_25um_q_1e-5': _small_signal_maps(1e-5),
             'xs_25um_q_1e-6': _small_signal_maps(1e-6)}
    de_maxiter = SMOKE['de_maxiter'] if smoke else de_maxiter
    res = {'smoke': smoke,
           'lut': _bench_lut(rand, smooth, maps, db_maps, small, build, smoke),
           'ga': _bench_ga(rand, smooth, maps, small, build, de_maxiter, smoke)}
    res['bench_wall_s'] = round(time.perf_counter() - t0, 1)
    return res


if __name__ == '__main__':
    ap = argparse.ArgumentParser()
    ap.add_argument('--no-build', action='store_true',
                    help='report the recorded build times instead of rebuilding')
    ap.add_argument('--de-maxiter', type=int, default=300)
    ap.add_argument('--smoke', action='store_true',
                    help='the same code on tiny sets: a check, no figure')
    a = ap.parse_args()
    print(json.dumps({'benchmark': 'surrogates_lut_ga',
                      **run(not a.no_build, a.de_maxiter, a.smoke)}))
