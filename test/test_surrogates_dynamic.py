"""Dynamic surrogates (metering-edge flows learned, fluid dynamics physical): flows against the
hf model's edge equations, the valve's symmetry, monotonicity, the plant over the whole range,
refusals, and the time-step bound they feed back."""

import numpy as np
import pytest

from eha_ros.graph import DYNAMIC_MODELS, MODELS
from eha_ros.physics import default_params, simulate
from eha_ros.physics.maps import WEAR_RANGES, spool_grid
from eha_ros.physics.params import ParameterError, replace
from eha_ros.physics.plant import Plant
from eha_ros.physics.stability import CHAMBER, FLUID, check_dt, stability_limits
from eha_ros.physics.valve import valve_flows
from eha_ros.surrogates.base import SurrogateError, relative_error
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.surrogates.edge import DynamicSurrogate, edge_flows

P = default_params()

#: Stated tolerances of the chamber flows against hf's ``valve_flows``, relative to the largest
#: |flow| over the pressures at the same spool position (a chamber flow crosses zero at its
#: balance pressure).  Measured maxima (``python -m eha_ros.training.dynamic``, in each
#: artefact's meta, nominal and two off-grid wear points): dlut 1.2e-4, dga 2.5e-15 (its form
#: is hf's and its polished coefficients hf's: 1e-12 leaves room for rounding only), dnn
#: 5.0e-4 (4.5e-4 on this test's grid).
CHAMBER_TOL = {'dlut': 5e-4, 'dga': 1e-12, 'dnn': 2e-3}
#: Stated tolerances of one edge's flow, relative, 99th percentile over random inputs
#: (measured: dlut 2.2e-4, dga 5.6e-15, dnn 7.1e-4; dnn on this test's points 1.6e-3 at the
#: smallest clearance, 8.1e-4 at the largest).
EDGE_P99_TOL = {'dlut': 1e-3, 'dga': 1e-12, 'dnn': 8e-3}

#: Wear points (overlap, clearance) [m]: nominal, off every grid, and the corners.
WEAR = [(1e-6, 2.5e-6), (3.1e-6, 3.9e-6), (-0.7e-6, 1.6e-6),
        (WEAR_RANGES['overlap_m'][0], WEAR_RANGES['radial_clearance_m'][0]),
        (WEAR_RANGES['overlap_m'][1], WEAR_RANGES['radial_clearance_m'][1])]


def _worn(lap, clr, p=P):
    return replace(p, overlap_supply_m=lap, overlap_return_m=lap, radial_clearance_m=clr)


@pytest.fixture(scope='module', params=DYNAMIC_MODELS)
def dyn(request):
    return load_surrogate(request.param)


def test_dynamic_models_are_plant_choices_and_self_describing(dyn):
    assert dyn.name in MODELS and isinstance(dyn, DynamicSurrogate)
    m = dyn.meta
    assert m['family'] == 'dynamic' and m['reproduction_of_reference'] is False
    assert m['edge_hash'] and m['valid_range']['radial_clearance_m'] == list(
        WEAR_RANGES['radial_clearance_m'])
    assert m['output']['unit'] == 'm^3/s' and 'errors' in m
    with pytest.raises(SurrogateError, match='dynamic'):
        dyn.p12(0.0, 0.0, 1e-6, 2.5e-6)


@pytest.mark.parametrize('lap,clr', WEAR[:3])
def test_chamber_flows_equal_hf_edge_equations(dyn, lap, clr):
    p = _worn(lap, clr)
    xs = spool_grid(41, p.spool_stroke_m)
    pp = np.linspace(p.vapour_pressure_pa, 1.2 * p.supply_pressure_pa, 37)
    q1 = np.array([[valve_flows(x, a, a, p)[0] for a in pp] for x in xs])
    q2 = np.array([[valve_flows(x, a, a, p)[1] for a in pp] for x in xs])
    got1, got2 = dyn.chamber_flows(xs[:, None], pp[None, :], pp[None, :], p)
    for got, ref in ((got1, q1), (got2, q2)):
        scale = np.max(np.abs(ref), axis=1, keepdims=True)
        assert np.max(np.abs(got - ref) / scale) < CHAMBER_TOL[dyn.name]


def test_edge_flows_equal_hf_edge_equations(dyn):
    rng = np.random.default_rng(11)
    n = 4000
    s = np.concatenate([rng.uniform(-300e-6, 300e-6, n // 2), rng.uniform(-10e-6, 10e-6, n // 2)])
    dp = np.exp(rng.uniform(np.log(10.0), np.log(4e7), n))
    for clr in (1.2e-6, 2.5e-6, 5.3e-6):
        p = replace(P, radial_clearance_m=clr)
        err = np.abs(dyn.edge_flow(s, dp, p) / edge_flows(s, dp, clr) - 1.0)
        assert np.quantile(err, 0.99) < EDGE_P99_TOL[dyn.name], (clr, np.quantile(err, 0.99))
        # odd in the pressure drop, exactly
        np.testing.assert_array_equal(dyn.edge_flow(s, -dp, p), -dyn.edge_flow(s, dp, p))


#: Tolerances of one edge's flow, relative, at every point of the large-flow corners: dlut
#: 5e-4 (its bilinear cells in |dp| bend by up to (1/16)^2 / 32 = 1.2e-4 where q ~ sqrt|dp|,
#: plus the float32 storage of ln G and the cubic interpolation in ln c; measured 1.6e-4), dga
#: 1e-12 (its form is hf's, the polished coefficients hf's to rounding), dnn 5e-3 (twice the
#: largest edge error its build records, meta['errors']); clamping the drop anywhere below
#: DP_MAX_PA, or holding the opening short of the axis' end, errs by several percent.
CORNER_TOL = {'dlut': 5e-4, 'dga': 1e-12, 'dnn': 5e-3}


def test_edge_flows_at_the_large_flow_corners(dyn):
    """Where each surrogate's range ends: pressure drops at DP_MAX_PA (dlut's table ends,
    dnn's drop feature is clamped) and at the cavitation boundary (supply against a chamber at
    the vapour pressure), openings at full stroke and at both ends of the opening range (the
    end of dlut's axis), clearances at both ends of their range."""
    from eha_ros.surrogates.edge import DP_MAX_PA, valid_range
    vr = valid_range(P)
    ops = np.array([vr['opening_m'][0], -P.spool_stroke_m, 0.0, P.spool_stroke_m,
                    vr['opening_m'][1]])
    dps = np.array([P.supply_pressure_pa - P.vapour_pressure_pa, DP_MAX_PA])
    o, d = (a.ravel() for a in np.meshgrid(ops, dps))
    for clr in WEAR_RANGES['radial_clearance_m']:
        got = dyn.edge_flow(o, d, replace(P, radial_clearance_m=clr))
        err = np.abs(got / edge_flows(o, d, clr) - 1.0)
        assert err.max() < CORNER_TOL[dyn.name], (clr, o[np.argmax(err)], d[np.argmax(err)],
                                                  err.max())


@pytest.mark.parametrize('lap,clr', WEAR[:3])
def test_valve_symmetry(dyn, lap, clr):
    """With equal laps the valve is antisymmetric: Q1L(XS, P) = -Q1L(-XS, PS + PR - P)."""
    p = _worn(lap, clr)
    rng = np.random.default_rng(3)
    xs = rng.uniform(-p.spool_stroke_m, p.spool_stroke_m, 500)
    pp = rng.uniform(p.vapour_pressure_pa, p.supply_pressure_pa, 500)
    a = dyn.chamber_flow(xs, pp, p)
    b = dyn.chamber_flow(-xs, p.supply_pressure_pa + p.return_pressure_pa - pp, p)
    np.testing.assert_allclose(a, -b, rtol=1e-9, atol=1e-9 * np.max(np.abs(a)))


@pytest.mark.parametrize('lap,clr', WEAR)
def test_monotonic(dyn, lap, clr):
    """A chamber's net inflow falls with its pressure (over the whole range) and, while the
    chamber lies between return and supply pressure, rises with the spool position (above
    supply the supply edge flows back, the more the wider it opens)."""
    p = _worn(lap, clr)
    xs = np.linspace(-p.spool_stroke_m, p.spool_stroke_m, 161)
    pp = np.linspace(p.vapour_pressure_pa, 2.0 * p.supply_pressure_pa, 161)
    q = dyn.chamber_flow(xs[:, None], pp[None, :], p)
    scale = np.max(np.abs(q))
    assert np.all(np.diff(q, axis=1) <= 1e-9 * scale)
    inside = (pp >= p.return_pressure_pa) & (pp <= p.supply_pressure_pa)
    assert np.all(np.diff(q[:, inside], axis=0) >= -1e-9 * scale)


@pytest.mark.parametrize('lap,clr', [WEAR[0], WEAR[3], WEAR[4]])
def test_plant_state_finite_over_the_full_range(dyn, lap, clr):
    """Open loop at full current both ways (spool to its stops, chambers from supply to the
    vapour pressure) and back to null, at nominal wear and at the corners of the wear range."""
    p = replace(_worn(lap, clr), noise_std_a=0.0)
    plant = Plant(p, fluid=dyn)
    for i_a in (p.current_limit_a, -p.current_limit_a, 0.0):
        plant.advance(i_a, 15000)
        s = plant.snapshot()
        assert all(np.isfinite(v) for v in s.values())
        for k in ('p1_pa', 'p2_pa'):
            assert p.vapour_pressure_pa <= s[k] <= 2.0 * p.supply_pressure_pa


def test_outside_the_range_is_refused(dyn):
    lo, hi = WEAR_RANGES['radial_clearance_m']
    with pytest.raises(SurrogateError, match='radial_clearance_m'):
        load_surrogate(dyn.name, replace(P, radial_clearance_m=1.5 * hi))
    plant = Plant(P, fluid=dyn)
    with pytest.raises(ParameterError, match='overlap_return_m'):
        plant.set_params(replace(P, overlap_return_m=WEAR_RANGES['overlap_m'][1] + 1e-6))
    with pytest.raises(SurrogateError, match='edge parameters'):
        load_surrogate(dyn.name, replace(P, discharge_coefficient=0.7))
    # parameters the edge law does not depend on may change: they stay physical
    load_surrogate(dyn.name, replace(P, chamber_volume_m3=2 * P.chamber_volume_m3,
                                     supply_pressure_pa=0.9 * P.supply_pressure_pa))


def test_time_step_bound_comes_from_what_the_surrogate_feeds_back(dyn):
    lim, block = dyn.stability_limit(P)
    hf = {x.key: x.dt_s for x in stability_limits(P)}
    hf_chamber = hf[CHAMBER]
    # the surrogate's conductance is the valve's: the same order as hf's (conservative) bound
    assert 0.5 * hf_chamber < lim < 4 * hf_chamber and dyn.name in block
    below, above = (round(f * lim, 9) for f in (0.9, 1.1))  # whole nanoseconds
    check_dt(P, below, dyn)
    with pytest.raises(ParameterError, match=dyn.name):
        check_dt(P, above, dyn)


def test_algebraic_surrogate_bound_is_its_pressure_flow_slope():
    s = load_surrogate('lut')
    lim, block = s.stability_limit(P)
    assert 'P12(Q) feedback' in block
    # AJ^2 |dP12/dQ| as a damper on the jack: dt < 2 MJ / (AJ^2 slope)
    slope = float(block.split('up to ')[1].split(' ')[0])
    assert lim == pytest.approx(2 * P.jack_mass_kg / (P.jack_area_m2 ** 2 * slope), rel=1e-3)
    keys = [x.key for x in stability_limits(P, s)]
    assert CHAMBER not in keys and keys[-1] == FLUID


def test_dynamic_lut_follows_hf_in_the_loop():
    """Noise off, 0.1 mm step: the dynamic table's plant stays within 1 % (jack) and 5 %
    (P12) of hf (measured: 0.01 % and 0.1 %, bench/inloop.py)."""
    p = replace(P, noise_std_a=0.0)
    kw = dict(duration_s=0.06, controller_period_s=1e-3, record_dt_s=1e-3)
    ref = simulate(p, 'step_0p1', **kw)
    got = simulate(p, 'step_0p1', fluid=load_surrogate('dlut'), **kw)
    assert relative_error(got['jack_position_m'], ref['jack_position_m']) < 0.01
    assert relative_error(got['p12_pa'], ref['p12_pa']) < 0.05


def test_dlut_cells_come_from_the_bits_of_its_axes():
    """The kernel's cell of a point (exponent and top mantissa bits of |x| + 2^e) is the
    interval of the artefact's axis holding it, and its weight the position within."""
    from eha_ros.surrogates.dlut import _axis_consts, _log_cell
    s = load_surrogate('dlut')
    g = s.meta['table']['grid']
    for nodes, e, m in ((s.data[0], g['s_exp2'], g['s_log2_cells']),
                        (s.data[1], g['dp_exp2'], g['dp_log2_cells'])):
        consts = _axis_consts(e, m)
        for k in range(nodes.size - 1):
            for frac in (0.0, 0.25, 0.5, 0.999):
                x = nodes[k] + frac * (nodes[k + 1] - nodes[k])
                cell, t = _log_cell(x, 2.0 ** e, *consts)
                assert cell == k and abs(t - frac) < 1e-9, (k, frac, cell, t)


def test_dlut_is_the_hf_edge_law_at_its_nodes():
    """At a clearance of the table, the kernel returns the hf edge flow at every node it
    holds (up to the float32 storage of ln G), on both sides of the edge."""
    s = load_surrogate('dlut')
    s_nodes, dp_nodes, ln_c = s.data[0], s.data[1], s.data[2]
    clr = float(np.exp(ln_c[3]))
    p = replace(P, radial_clearance_m=clr)
    ss, dd = np.meshgrid(np.concatenate([s_nodes[::7], -s_nodes[1::7]]), dp_nodes[1::5])
    got = s.edge_flow(ss.ravel(), dd.ravel(), p)
    ref = edge_flows(ss.ravel(), dd.ravel(), clr)
    assert np.max(np.abs(got / ref - 1.0)) < 1e-5


def test_dlut_flow_keeps_rising_beyond_its_pressure_range():
    from eha_ros.surrogates.edge import DP_MAX_PA
    s = load_surrogate('dlut')
    dp = np.linspace(0.9, 3.0, 200) * DP_MAX_PA
    for opening in (-50e-6, 0.0, 20e-6, 300e-6):
        q = s.edge_flow(np.full(dp.size, opening), dp)
        assert np.all(np.diff(q) > 0)
        inside = dp <= DP_MAX_PA
        ref = edge_flows(opening, dp[inside], P.radial_clearance_m)
        assert np.max(np.abs(q[inside] / ref - 1.0)) < 2e-3


# --- dnn: the kernel against its own network, the libm-free functions it uses ------------------

def test_dnn_kernel_equals_its_network():
    """The kernel (normalisations and the clearance folded into the weights by prepare, the
    logarithms and the exponential without libm) gives the flows of the network as trained,
    evaluated in numpy: within 1e-10 relative (the kernel's logarithm errs by up to 4.6e-13
    absolute in each feature, its exponential by 6.4e-15 relative; through the weights, a few
    tens at most, they move ln G, hence the flow, by well under 1e-10)."""
    from eha_ros.surrogates.dnn import dnn_numpy
    s = load_surrogate('dnn')
    rng = np.random.default_rng(5)
    n = 3000
    op = np.concatenate([rng.uniform(-306e-6, 306e-6, n // 2), rng.uniform(-5e-6, 5e-6, n // 2),
                         [0.0, 1e-12, -1e-12]])
    dp = np.concatenate([np.exp(rng.uniform(0.0, np.log(8e7), n)) * rng.choice([-1.0, 1.0], n),
                         [3e6, -1.0, 5e7]])
    for clr in (1.0e-6, 2.5e-6, 6.0e-6):
        got = s.edge_flow(op, dp, replace(P, radial_clearance_m=clr))
        ref = dnn_numpy(s.data, op, dp, clr)
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=0.0)
    assert s.edge_flow(np.array([1e-6]), np.array([0.0]))[0] == 0.0


#: Truncation bounds of the kernel's IR helpers (their docstrings in :func:`_v4_ir`): the odd
#: series of ``2 atanh z`` to ``z^13`` at ``|z| <= (sqrt2 - 1) / (sqrt2 + 1)`` and the degree-11
#: Taylor polynomial of ``exp f`` at ``|f| <= ln2 / 2``.
_Z_MAX = (np.sqrt(2.0) - 1.0) / (np.sqrt(2.0) + 1.0)
LOG_TRUNCATION = 2.0 * _Z_MAX ** 15 / (15.0 * (1.0 - _Z_MAX ** 2))
EXP_TRUNCATION = (np.log(2.0) / 2.0) ** 12 / 479001600.0


def test_dnn_ir_log_over_every_binade_of_the_positive_doubles():
    """The kernel's logarithm against numpy over its whole input range (every exponent of the
    positive normal doubles, the mantissa boundaries at sqrt(2), and near 1): within the
    series' truncation plus 4 ulp of the result, and within 4 ulp near 1."""
    from eha_ros.surrogates.dnn_ir import dnn_ir_log
    rng = np.random.default_rng(21)
    e = np.repeat(np.arange(-1022, 1024), 64)
    x = np.ldexp(rng.uniform(1.0, 2.0, e.size), e)
    edges = np.ldexp(np.sqrt(2.0), np.arange(-1022, 1023))
    x = np.concatenate([x, edges, np.nextafter(edges, 0.0), np.nextafter(edges, np.inf),
                        [np.finfo(float).tiny, np.finfo(float).max, 1.0, 2.0, 0.5]])
    ref = np.log(x)
    err = np.abs(dnn_ir_log(x) - ref)
    assert np.all(err <= LOG_TRUNCATION + 4.0 * np.spacing(np.abs(ref))), err.max()
    near = 1.0 + rng.uniform(-1e-3, 1e-3, 20000)
    ref = np.log(near)
    assert np.all(np.abs(dnn_ir_log(near) - ref) <= 4.0 * np.finfo(float).eps)


def test_dnn_ir_exp_over_its_range():
    """The kernel's exponential against numpy over its documented range ``|y| < 700`` (the
    network's ``ln G`` lies far inside): relative error within the truncation plus 16 ulp (the
    rounding of the reduction ``y - n ln2`` and of the polynomial)."""
    from eha_ros.surrogates.dnn_ir import dnn_ir_exp
    rng = np.random.default_rng(22)
    y = np.concatenate([rng.uniform(-700.0, 700.0, 100000), np.linspace(-700.0, 700.0, 14001),
                        (np.arange(-1009, 1010) + 0.5) * np.log(2.0), [0.0, 1e-300, -1e-17]])
    rel = np.abs(dnn_ir_exp(y) / np.exp(y) - 1.0)
    assert np.all(rel <= EXP_TRUNCATION + 16.0 * np.finfo(float).eps), rel.max()


def test_dnn_numpy_is_the_trained_network():
    """The numpy reference of the kernel test is the torch network the trainer fitted (same
    activation, inputs, skip term, normalisations)."""
    torch = pytest.importorskip('torch')
    from eha_ros.surrogates.dnn import dnn_features, dnn_numpy
    from eha_ros.training.networks import make_torch_mlp
    s = load_surrogate('dnn')
    data, arch = s.data, s.meta['architecture']
    m = make_torch_mlp(d_in=4, d_hidden=arch['d_hidden'], activation=arch['activation'],
                       skip=arch['skip'])
    with torch.no_grad():
        m.theta.copy_(torch.as_tensor(np.asarray(data[3], dtype=float)))
    rng = np.random.default_rng(8)
    op, dp = rng.uniform(-20e-6, 20e-6, 2000), rng.uniform(-3e7, 3e7, 2000)
    z = (dnn_features(op, dp, 3.3e-6, float(data[4][0])) - data[1][0]) / data[1][1]
    with torch.no_grad():
        ln_g = data[2][0] + data[2][1] * m(torch.as_tensor(z)).numpy()[:, 0]
    np.testing.assert_allclose(dnn_numpy(data, op, dp, 3.3e-6), dp * np.exp(ln_g), rtol=1e-12)


def test_dnn_refuses_an_artefact_its_kernel_does_not_evaluate(tmp_path):
    from eha_ros.artefacts import load_artefact, models_dir, save_artefact
    data, meta = load_artefact(models_dir('surrogates') / 'dnn.npz', 'eha_ros.training.dynamic')
    meta = dict(meta, architecture=dict(meta['architecture'], activation='tanh'))
    save_artefact(tmp_path / 'dnn.npz', data, meta)
    with pytest.raises(SurrogateError, match='quintic'):
        load_surrogate('dnn', P, path=tmp_path / 'dnn.npz').prepare(P)


@pytest.mark.parametrize('scenario,lap,clr', [('step_0p01', 3.1e-6, 3.9e-6),
                                              ('ramp_0p01', -0.7e-6, 1.6e-6),
                                              ('sine_0p01_10pi', 1e-6, 2.5e-6)])
def test_dnn_follows_hf_on_small_signals(scenario, lap, clr):
    """Noise off, the small-signal cases the earlier network failed (spool near null, the
    chamber pressures set by nearly covered edges): within the in-loop bounds of
    bench/inloop.py (jack <= max(1 %, 2 x yardstick), P12 <= max(5 %, 2 x yardstick))."""
    from eha_ros.evaluation import noise_free
    p = replace(_worn(lap, clr), noise_std_a=0.0)
    case = noise_free(p, scenario, {'dnn': load_surrogate('dnn')})
    got = case['models']['dnn']
    assert got['jack'] <= case['bound']['jack'] and got['p12'] <= case['bound']['p12'], (
        got['jack'], got['p12'], case['bound'])


@pytest.mark.parametrize('integrator, dt', [('explicit', 1e-6), ('split', 1e-5)])
def test_a_scripted_current_in_one_call_is_the_tick_by_tick_plant_with_a_surrogate(
        dyn, integrator, dt):
    """:meth:`Plant.advance_currents` (the pre-flight check's one kernel call) through a
    surrogate's own compiled forms: the states of the plant stepped tick by tick, bit for
    bit, for currents drawn from this test's own stream."""
    rng = np.random.default_rng([4177, DYNAMIC_MODELS.index(dyn.name), dt == 1e-5])
    currents = rng.uniform(-0.01, 0.01, 12)
    a = Plant(P, dt_s=dt, seed=7, fluid=dyn, integrator=integrator)
    b = Plant(P, dt_s=dt, seed=7, fluid=dyn, integrator=integrator)
    rows = []
    for c in currents:
        a.advance(float(c), 20)
        rows.append(a.state.copy())
    rec = b.advance_currents(currents, 20)
    from eha_ros.physics.state import RECORD_FIELDS, STATE_NAMES
    for name in ('spool_position_m', 'p1_pa', 'p2_pa', 'jack_position_m'):
        np.testing.assert_array_equal(rec[:, RECORD_FIELDS.index(name)],
                                      np.array(rows)[:, STATE_NAMES.index(name)])
    np.testing.assert_array_equal(a.state, b.state)
