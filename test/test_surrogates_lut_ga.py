"""Lookup table and genetic-algorithm surrogates: the kernels against numpy references and
closed forms, accuracy on freshly generated maps, the fit, and artefact handling."""

from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from eha_ros.physics import default_params
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, transient_map
from eha_ros.physics.params import replace
from eha_ros.artefacts import models_dir
from eha_ros.surrogates import ga, lut
from eha_ros.training import ga as ga_fit
from eha_ros.training import lut as lut_build
from eha_ros.surrogates.base import SurrogateError
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.physics.maps import FLOW_MAX_M3_S, fluid_hash
from eha_ros.training.database import map_errors


@pytest.fixture(scope='module')
def shipped_lut():
    return load_surrogate('lut')


@pytest.fixture(scope='module')
def shipped_ga():
    return load_surrogate('ga')


def _multilinear_reference(axes, table, pts):
    """Plain numpy multilinear interpolation (inputs clamped to the axes)."""
    idx, frac = [], []
    for d, a in enumerate(axes):
        x = np.clip(pts[:, d], a[0], a[-1])
        i = np.clip(np.searchsorted(a, x, side='right') - 1, 0, a.size - 2)
        idx.append(i)
        frac.append((x - a[i]) / (a[i + 1] - a[i]))
    out = np.zeros(pts.shape[0])
    for corner in range(16):
        bits = [(corner >> d) & 1 for d in range(4)]
        w = np.ones(pts.shape[0])
        for d in range(4):
            w *= frac[d] if bits[d] else 1.0 - frac[d]
        out += w * table[tuple(idx[d] + bits[d] for d in range(4))]
    return out


def _random_table(rng, sizes=(9, 5, 4, 3)):
    """Random non-uniform axes and values."""
    axes = [np.sort(rng.uniform(-1.0, 1.0, n)) * s
            for n, s in zip(sizes, (3e-4, 6e-5, 4e-6, 3e-6))]
    axes[3] = axes[3] + 4e-6
    return axes, rng.normal(0.0, 1e7, sizes)


def _points(rng, axes, n, margin=0.0):
    lo = np.array([a[0] for a in axes])
    hi = np.array([a[-1] for a in axes])
    span = hi - lo
    return rng.uniform(lo - margin * span, hi + margin * span, (n, 4))


# --- lookup table: the kernel ------------------------------------------------------------------

def test_lut_reproduces_shipped_table_at_every_grid_point(shipped_lut):
    xs, q, lap, clr, table = shipped_lut.data[:5]
    g = np.meshgrid(xs, q, lap, clr, indexing='ij')
    got = shipped_lut.p12(*g)
    ref = table.astype(np.float64)
    assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_lut_is_multilinear_between_grid_points(shipped_lut):
    rng = np.random.default_rng(1)
    axes, table = shipped_lut.data[:4], shipped_lut.data[4].astype(np.float64)
    pts = _points(rng, axes, 20000)
    got = shipped_lut.p12(*pts.T)
    assert_allclose(got, _multilinear_reference(axes, table, pts), rtol=1e-9,
                    atol=1e-9 * np.abs(table).max())


def test_lut_matches_scipy_regular_grid_interpolator():
    from scipy import interpolate as interp
    rng = np.random.default_rng(2)
    axes, table = _random_table(rng)
    s = lut.make_lut(*axes, table, dtype=np.float64)
    pts = _points(rng, axes, 5000)
    ref = interp.RegularGridInterpolator(axes, table, method='linear')(pts)
    assert_allclose(s.p12(*pts.T), ref, rtol=1e-10, atol=1e-10 * np.abs(table).max())


def test_lut_is_exact_for_a_multilinear_function():
    """A function linear in each input separately is interpolated without error anywhere,
    on non-uniform axes."""
    rng = np.random.default_rng(3)
    axes, _ = _random_table(rng)
    scales = [1.0 / np.abs(a).max() for a in axes]

    def f(x, q, a, c):
        u, v, w, z = (x * scales[0], q * scales[1], a * scales[2], c * scales[3])
        return 1e6 * (3.0 + 2.0 * u - v + 0.5 * w + 4.0 * z + 7.0 * u * v - 2.0 * v * w * z
                      + u * v * w * z)

    table = f(*np.meshgrid(*axes, indexing='ij'))
    s = lut.make_lut(*axes, table, dtype=np.float64)
    pts = _points(rng, axes, 5000)
    assert_allclose(s.p12(*pts.T), f(*pts.T), rtol=1e-10, atol=1e-3)


def test_lut_clamps_outside_the_grid():
    rng = np.random.default_rng(4)
    axes, table = _random_table(rng)
    s = lut.make_lut(*axes, table, dtype=np.float64)
    pts = _points(rng, axes, 4000, margin=1.0)  # most points outside on some axis
    lo = np.array([a[0] for a in axes])
    hi = np.array([a[-1] for a in axes])
    assert np.mean(np.any((pts < lo) | (pts > hi), axis=1)) > 0.5
    clamped = np.clip(pts, lo, hi)
    assert_allclose(s.p12(*pts.T), s.p12(*clamped.T), rtol=1e-12, atol=0.0)
    far = s.p12(1.0, 1.0, 1.0, 1.0)  # far beyond every axis: the table's last corner
    assert far == pytest.approx(table[-1, -1, -1, -1], rel=1e-12)


def test_lut_nan_input_gives_nan():
    rng = np.random.default_rng(5)
    axes, table = _random_table(rng)
    s = lut.make_lut(*axes, table)
    assert np.isnan(s.p12(np.nan, 0.0, 0.0, 4e-6))
    assert np.isnan(s.p12(0.0, 0.0, 0.0, np.nan))


@pytest.mark.parametrize('bad, match', [
    ({'axis': np.array([0.0, 0.0, 1.0])}, 'strictly increasing'),
    ({'axis': np.array([0.0])}, 'at least 2'),
    ({'table_shape': (3, 3, 2, 2)}, 'does not match'),
    ({'nan': True}, 'non-finite'),
])
def test_make_lut_rejects_malformed_tables(bad, match):
    axes = [np.linspace(0, 1, 3), np.linspace(0, 1, 4), np.linspace(0, 1, 2),
            np.linspace(1, 2, 2)]
    table = np.zeros((3, 4, 2, 2))
    if 'axis' in bad:
        axes[0] = bad['axis']
        table = np.zeros((bad['axis'].size, 4, 2, 2))
    if 'table_shape' in bad:
        table = np.zeros(bad['table_shape'])
    if 'nan' in bad:
        table[0, 0, 0, 0] = np.nan
    with pytest.raises(SurrogateError, match=match):
        lut.make_lut(*axes, table)


def test_axis_tables_refuse_extremely_non_uniform_axes():
    with pytest.raises(SurrogateError, match='too non-uniform'):
        lut.axis_tables(np.array([0.0, 1e-9, 1.0]))


# --- lookup table: accuracy --------------------------------------------------------------------

def test_shipped_lut_error_on_fresh_maps_at_random_wear(shipped_lut):
    """Maps at random wear, at spool positions and flows off the table grid: the measured
    error is about 0.15 % (mean), 0.25 % (max); the bound leaves room for other seeds."""
    maps = lut_build.heldout_maps(4, seed=11, n_q=12)
    err = map_errors(shipped_lut.p12, maps)
    assert np.all(err < 0.01), err


def test_shipped_lut_error_in_the_small_signal_region(shipped_lut):
    """Where the closed loop of the shipped scenarios stays (|XS| < 25 um, |Q| < 1e-6 m^3/s),
    at nominal and at worn values: measured up to 1.1 %."""
    rng = np.random.default_rng(12)
    xs = rng.uniform(-25e-6, 25e-6, 60)
    q = rng.uniform(-1e-6, 1e-6, 10)
    x, qq = np.meshgrid(xs, q, indexing='ij')
    for lap, clr in ((1e-6, 2.5e-6), (4e-6, 1.5e-6)):
        p = transient_map(x, qq, lap, clr)['p12_pa']
        err = np.linalg.norm(shipped_lut.p12(x, qq, lap, clr) - p) / np.linalg.norm(p)
        assert err < 0.02, (lap, clr, err)


def test_lut_build_round_trip(tmp_path):
    """A tiny table built through ``build_artefact`` loads back and interpolates it."""
    p = default_params()
    grid = {'n_xs': 9, 'n_q': 5, 'n_overlap': 2, 'n_clearance': 2}
    path = lut_build.build_artefact(p, tmp_path / 'lut.npz', grid=grid, n_validation_maps=0)
    s = load_surrogate('lut', p, path=path)
    assert s.meta['data']['n_q'] == 5 and s.meta['fluid_hash'] == fluid_hash(p)
    xs, q, lap, clr, table = lut_build.build_table(p, **grid)
    assert_allclose(s.p12(*np.meshgrid(xs, q, lap, clr, indexing='ij')),
                    table.astype(np.float32), rtol=1e-9, atol=1.0)


# --- genetic-algorithm function -----------------------------------------------------------------

def test_ga_kernel_equals_the_numpy_formula(shipped_ga):
    rng = np.random.default_rng(6)
    stroke = default_params().spool_stroke_m
    xs = rng.uniform(-stroke, stroke, 5000)
    q = rng.uniform(-FLOW_MAX_M3_S, FLOW_MAX_M3_S, 5000)
    c = np.array(shipped_ga.meta['coefficients'])
    assert_array_equal(shipped_ga.data[0], c)
    ref = ga.formula(c, xs / ga.XS_REF_M, q / ga.Q_REF_M3_S)
    got = shipped_ga.p12(xs, q, 1e-6, 2.5e-6)
    assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    # wear is not an input; inputs beyond the training ranges are clamped
    assert_array_equal(shipped_ga.p12(xs, q, -2e-6, 6e-6), got)
    assert_array_equal(shipped_ga.p12(10 * stroke, 3 * FLOW_MAX_M3_S, 0.0, 1e-6),
                       shipped_ga.p12(stroke, FLOW_MAX_M3_S, 0.0, 1e-6))
    assert np.isnan(shipped_ga.p12(np.nan, 0.0, 0.0, 1e-6))


def test_ga_kernel_with_random_coefficients():
    rng = np.random.default_rng(7)
    for _ in range(5):
        c = ga_fit.THESIS_INITIAL * rng.uniform(0.5, 2.0, 8)
        s = ga.make_ga(c, 3e-4)
        xs = rng.uniform(-3e-4, 3e-4, 200)
        q = rng.uniform(-6e-5, 6e-5, 200)
        ref = ga.formula(c, xs / ga.XS_REF_M, q / ga.Q_REF_M3_S)
        assert_allclose(s.p12(xs, q, 0.0, 1e-6), ref, rtol=1e-12,
                        atol=1e-12 * np.abs(ref).max())


def test_relative_error_matches_its_definition():
    rng = np.random.default_rng(8)
    xs = rng.uniform(-3e-4, 3e-4, 300)
    q = rng.uniform(-6e-5, 6e-5, 300)
    p = rng.normal(0, 3e7, 300)
    pop = ga_fit.THESIS_INITIAL * rng.uniform(0.5, 2.0, (4, 8))
    got = ga_fit.coefficient_errors(pop, xs, q, p)
    for k in range(4):
        r = ga.formula(pop[k], xs / ga.XS_REF_M, q / ga.Q_REF_M3_S) - p
        assert got[k] == pytest.approx(np.linalg.norm(r) / np.linalg.norm(p), rel=1e-12)


def test_min_denominators_against_a_dense_scan():
    rng = np.random.default_rng(9)
    pop = rng.uniform(ga_fit.THESIS_LB, ga_fit.THESIS_UB, (50, 8))
    s = np.linspace(0.0, (3e-4 / ga.XS_REF_M) ** 2, 200001)
    got = ga_fit.min_denominators(pop, 3e-4)
    for k in range(pop.shape[0]):
        c = pop[k]
        for col, (a, b) in enumerate(((c[3], c[4]), (c[6], c[7]))):
            scan = (1.0 + a * s + b * s * s).min()
            assert got[k, col] <= scan + 1e-9 * max(1.0, abs(scan))
            assert got[k, col] == pytest.approx(scan, rel=1e-6, abs=1e-6)


@pytest.fixture(scope='module')
def small_nominal_map():
    """A coarse nominal-wear map: 41 spool positions x 9 flows."""
    xs = spool_grid(41)
    q = np.linspace(-FLOW_MAX_M3_S, FLOW_MAX_M3_S, 9)
    x, qq = np.meshgrid(xs, q, indexing='ij')
    return x, qq, transient_map(x, qq)['p12_pa']


def test_ga_improves_respects_bounds_and_is_reproducible(small_nominal_map):
    x, q, p = small_nominal_map
    stroke = default_params().spool_stroke_m
    settings = ga_fit.GASettings(population=16, generations=12, seed=3)
    r1 = ga_fit.genetic_fit(x, q, p, stroke, settings)
    r2 = ga_fit.genetic_fit(x, q, p, stroke, settings)
    r3 = ga_fit.genetic_fit(x, q, p, stroke,
                            ga_fit.GASettings(population=16, generations=12, seed=4))
    initial = ga_fit.coefficient_errors(ga_fit.THESIS_INITIAL, x, q, p)[0]
    assert r1.error < 0.5 * initial
    assert r1.error == pytest.approx(ga_fit.coefficient_errors(r1.coefficients, x, q, p)[0],
                                     rel=1e-12)
    assert np.all(np.diff(r1.history) <= 0)  # elitism: the best never gets worse
    assert np.all(r1.coefficients >= ga_fit.THESIS_LB)
    assert np.all(r1.coefficients <= ga_fit.THESIS_UB)
    assert r1.coefficients[0] == ga_fit.THESIS_LB[0]  # pinned
    assert np.all(ga_fit.min_denominators(r1.coefficients, stroke) >= ga_fit.MIN_DENOMINATOR)
    assert_array_equal(r1.coefficients, r2.coefficients)
    assert_array_equal(r1.history, r2.history)
    assert not np.array_equal(r1.coefficients, r3.coefficients)
    assert r1.evaluations == 16 + r1.generations * (16 - settings.elite)


def test_ga_stops_on_stall(small_nominal_map):
    x, q, p = small_nominal_map
    settings = ga_fit.GASettings(population=8, generations=500, stall_generations=3,
                                 mutation_rate=0.0, crossover_rate=0.0, seed=0)
    r = ga_fit.genetic_fit(x, q, p, 3e-4, settings)
    assert r.generations < 500


@pytest.mark.parametrize('kw, match', [
    ({'population': 2}, 'population'), ({'tournament': 0}, 'tournament'),
    ({'mutation_rate': 1.5}, 'mutation_rate'), ({'mutation_sigma_end': 0.0}, 'mutation'),
])
def test_ga_settings_are_checked(small_nominal_map, kw, match):
    x, q, p = small_nominal_map
    with pytest.raises(SurrogateError, match=match):
        ga_fit.genetic_fit(x, q, p, 3e-4, ga_fit.GASettings(**kw))


def test_ga_refuses_start_outside_bounds(small_nominal_map):
    x, q, p = small_nominal_map
    bad = ga_fit.THESIS_INITIAL.copy()
    bad[1] = 5.0
    with pytest.raises(SurrogateError, match='outside the bounds'):
        ga_fit.genetic_fit(x, q, p, 3e-4, ga_fit.GASettings(population=8, generations=1), x0=bad)


def test_gradient_fit_does_not_worsen_the_ga(small_nominal_map):
    x, q, p = small_nominal_map
    r = ga_fit.genetic_fit(x, q, p, 3e-4, ga_fit.GASettings(population=16, generations=10, seed=1))
    c, err, info = ga_fit.gradient_fit(x, q, p, 3e-4, x0=r.coefficients)
    assert err <= r.error * (1 + 1e-9)
    assert info['admissible']
    assert np.all(c >= ga_fit.THESIS_LB) and np.all(c <= ga_fit.THESIS_UB)


def test_shipped_ga_error_on_the_nominal_map_off_its_grid(shipped_ga):
    """Nominal wear, spool positions and flows off the DB5 grid: measured 7.5 % over the
    full 132 x 132 midpoint map; the bound is the goal of the function."""
    g = spool_grid(133)
    xs = 0.5 * (g[1:] + g[:-1])
    q = np.linspace(-FLOW_MAX_M3_S, FLOW_MAX_M3_S, 133)
    q = 0.5 * (q[1:] + q[:-1])[::6]
    x, qq = np.meshgrid(xs, q, indexing='ij')
    p = transient_map(x, qq)['p12_pa']
    err = np.linalg.norm(shipped_ga.p12(x, qq, 1e-6, 2.5e-6) - p) / np.linalg.norm(p)
    assert err < 0.08, err
    rec = shipped_ga.meta['ga']
    assert rec['heldout_error'] < 0.08 and rec['train_error'] < rec['initial_error']


# --- artefacts -----------------------------------------------------------------------------------

@pytest.mark.parametrize('name', ['lut', 'ga'])
def test_artefact_for_other_fluid_parameters_is_refused(name):
    other = replace(default_params(), supply_pressure_pa=2.1e7)
    with pytest.raises(SurrogateError, match='fluid parameters'):
        load_surrogate(name, other)


@pytest.mark.parametrize('name', ['lut', 'ga'])
def test_truncated_artefact_is_refused_in_one_line(name, tmp_path):
    src = models_dir('surrogates') / f'{name}.npz'
    blob = src.read_bytes()
    bad = tmp_path / f'{name}.npz'
    bad.write_bytes(blob[:len(blob) // 2])
    with pytest.raises(SurrogateError, match='corrupt') as exc:
        load_surrogate(name, path=bad)
    assert '\n' not in str(exc.value)


def test_artefacts_carry_units_normalisation_and_hash(shipped_lut, shipped_ga):
    for s in (shipped_lut, shipped_ga):
        assert s.meta['fluid_hash']
        assert [i['name'] for i in s.meta['inputs']] == ['xs_m', 'q_m3_s', 'overlap_m',
                                                         'clearance_m']
        assert s.meta['output'] == {'name': 'p12_pa', 'unit': 'Pa'}
    assert shipped_ga.meta['normalisation']['xs_ref_m'] == ga.XS_REF_M
    assert shipped_ga.meta['normalisation']['q_ref_m3_s'] == ga.Q_REF_M3_S
    assert shipped_lut.meta['ranges']['overlap_m'] == list(WEAR_RANGES['overlap_m'])
    size = (models_dir('surrogates') / 'lut.npz').stat().st_size
    assert size <= 2_000_000


_FRESH_PROCESS = """
from numba import njit
from eha_ros.physics import Plant
from eha_ros.surrogates.base import FluidSurrogate
from eha_ros.surrogates.registry import load_surrogate

@njit
def local_kernel(data, xs, q, lap, clr):  # a kernel numba can only pickle by value
    return data[0][0] * xs

Plant().advance(0.0, 10)
shipped = load_surrogate('lut')
Plant(fluid=shipped).advance(0.0, 10)
s = FluidSurrogate('local', local_kernel, (__import__('numpy').ones(1),), {})
Plant(fluid=s).advance(0.0, 10)
print(s.p12(1.0, 0.0, 0.0, 1e-6))
form = shipped.loops[0]
print(sum(form.stats.cache_hits.values()), sum(form.stats.cache_misses.values()))
"""


def test_kernels_passed_as_arguments_never_reach_the_disk_cache(tmp_path):
    """Fresh processes, one after the other, each running the plant with the hf block, a
    shipped surrogate and a kernel of their own: every one succeeds (a numba function typed
    by its object in a disk-cache key breaks the cache for later processes); the loop's forms
    that take a kernel leave no cache entry, its high-fidelity forms do, and the shipped
    surrogate's own form is loaded from the cache by the second process, not compiled."""
    import eha_ros.physics.loop as loop
    for k in range(2):
        out = subprocess.run([sys.executable, '-c', _FRESH_PROCESS], capture_output=True,
                             text=True, cwd=tmp_path, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        p12, hits = out.stdout.strip().splitlines()
        assert p12 == '1.0'
        if k == 1:
            assert hits == '1 0', 'the shipped form was compiled again (hits, misses: ' + hits
    cache = Path(loop.__file__).parent / '__pycache__'
    assert not list(cache.glob('loop.*kernel-*')), sorted(p.name for p in cache.iterdir())
    assert list(cache.glob('loop._run_hf-*.nbi')), sorted(p.name for p in cache.iterdir())
