"""Fluid-dynamic block: orifice law, edge geometry, symmetry, saturation, cavitation, maps."""

import sys
from pathlib import Path

from hypothesis import example, given, settings, strategies as st
import numpy as np
from numpy.testing import assert_allclose
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import physics_reference as ref  # noqa: E402

from eha_ros.physics import default_params  # noqa: E402
from eha_ros.physics.maps import (settling_mask, spool_grid, steady_map,  # noqa: E402
                                  transient_map)
from eha_ros.physics.params import replace  # noqa: E402
from eha_ros.physics.valve import (chamber_step, edge_coefficients, orifice_flow,  # noqa: E402
                                   orifice_pressure_drop, valve_constants, valve_flows)

P = default_params()
P_CONST = replace(P, cd_model='constant')
RNG = np.random.default_rng(1234)


def _random_edges(n):
    opening = RNG.uniform(-8e-6, 3e-4, n)
    opening[: n // 4] = RNG.uniform(-8e-6, 8e-6, n // 4)  # dense near the lap
    dp = RNG.uniform(-2.5e7, 2.5e7, n)
    dp[:5] = [0.0, 1e-3, -1e-3, 1.0, 2e7]
    return opening, dp


@pytest.mark.parametrize('p', [P, P_CONST], ids=['reynolds', 'constant'])
def test_orifice_flow_inverts_its_pressure_drop(p):
    """dp = RL Q + RQ(dp) Q|Q| recovers the drop to 1e-9 relative (1e-6 Pa absolute)."""
    opening, dp = _random_edges(2000)
    vc = valve_constants(p)
    for o, d in zip(opening, dp):
        rl, bl, r4 = edge_coefficients(o, vc)
        q = orifice_flow(d, rl, bl, r4)
        assert np.sign(q) == np.sign(d)
        back = orifice_pressure_drop(q, d, rl, bl, r4)
        assert_allclose(back, d, rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize('p', [P, P_CONST], ids=['reynolds', 'constant'])
def test_orifice_flow_matches_numpy_reference(p):
    """Kernel (stable root, Cd folded into B_lam) vs the textbook root with Cd(Re): 1e-7
    relative where the textbook root does not cancel (|Q| above 1e-12 m^3/s)."""
    opening, dp = _random_edges(3000)
    vc = valve_constants(p)
    got = np.array([orifice_flow(d, *edge_coefficients(o, vc)) for o, d in zip(opening, dp)])
    want = ref.orifice_flow(p, opening, dp)
    mask = np.abs(want) > 1e-12
    assert mask.sum() > 2500
    assert_allclose(got[mask], want[mask], rtol=1e-7)
    assert_allclose(got[~mask], want[~mask], atol=1e-12)


def test_valve_flows_match_numpy_reference():
    xs = RNG.uniform(-3e-4, 3e-4, 500)
    xs[:100] = RNG.uniform(-5e-6, 5e-6, 100)
    p1 = RNG.uniform(1e3, 3e7, 500)
    p2 = RNG.uniform(1e3, 3e7, 500)
    got = np.array([valve_flows(a, b, c, P) for a, b, c in zip(xs, p1, p2)])
    want = np.stack(ref.valve_flows(P, xs, p1, p2), axis=1)
    assert_allclose(got, want, rtol=1e-7, atol=1e-13)


def test_laminar_leakage_of_covered_edge_matches_closed_form():
    """Deeply covered edge, small drop.  Constant Cd: Q -> dp/RL with RL = 12 mu X0/(w c^3)
    (concentric).  Reynolds Cd: the annulus exit adds the laminar-orifice term in quadrature,
    Q -> 2 dp/(RL + sqrt(RL^2 + B_lam)), B_lam = mu^2 lambda_c^2 / (16 Cd^2 w^2 c^4)."""
    x0 = 20e-6
    dp = 1e3
    mu = P.fluid_density_kg_m3 * P.fluid_kinematic_viscosity_m2_s
    w, c = P.port_width_m, P.radial_clearance_m
    rl_closed = 12 * mu * x0 / (w * c ** 3)
    rl, bl, r4 = edge_coefficients(-x0, valve_constants(P_CONST))
    assert_allclose(rl, rl_closed, rtol=1e-12)
    assert_allclose(orifice_flow(dp, rl, bl, r4), dp / rl_closed, rtol=1e-3)
    bl_closed = (mu * P.critical_flow_number) ** 2 / (16 * (P.discharge_coefficient * w) ** 2
                                                      * c ** 4)
    rl, bl, r4 = edge_coefficients(-x0, valve_constants(P))
    assert_allclose(bl, bl_closed, rtol=1e-12)
    assert_allclose(orifice_flow(dp, rl, bl, r4),
                    2 * dp / (rl_closed + np.sqrt(rl_closed ** 2 + bl_closed)), rtol=1e-3)


def test_eccentricity_raises_leakage_by_one_plus_1p5_e2():
    pe = replace(P, eccentricity_ratio=1.0)
    rl0 = edge_coefficients(-5e-6, valve_constants(P))[0]
    rl1 = edge_coefficients(-5e-6, valve_constants(pe))[0]
    assert_allclose(rl0 / rl1, 2.5, rtol=1e-12)


@pytest.mark.parametrize('lap', [0.0, 1e-6, 4e-6, -2e-6])
def test_symmetric_valve_is_antisymmetric(lap):
    """OSSV = ORSV: P12(-XS, -Q) = -P12(XS, Q), transient and steady (1e-9 relative, 1 Pa)."""
    p = replace(P, overlap_supply_m=lap, overlap_return_m=lap)
    xs = spool_grid(21)
    q = np.array([-5e-5, -1e-5, 0.0, 1e-5, 5e-5])
    for fn in (transient_map, steady_map):
        a = fn(xs[:, None], q[None, :], params=p)['p12_pa']
        b = fn(-xs[:, None], -q[None, :], params=p)['p12_pa']
        assert_allclose(b, -a, rtol=1e-9, atol=1.0)


def test_zero_flow_saturates_to_supply_minus_return():
    """Q = 0, |XS| >> lap: P12 -> +-(PS - PR) within 0.5 % (leakage through the covered edges
    is all that keeps it below)."""
    big = np.array([-3e-4, -1e-4, 1e-4, 3e-4])
    dps = P.supply_pressure_pa - P.return_pressure_pa
    for fn in (transient_map, steady_map):
        p12 = fn(big, 0.0)['p12_pa']
        assert_allclose(p12, np.sign(big) * dps, rtol=5e-3)
        assert np.all(np.abs(p12) <= dps)


def test_water_hammer_above_supply_near_null():
    """With flow imposed and the spool near null, the map transient drives one chamber above
    supply (the reference's 'water hammer'), while at large openings it stays below."""
    r = transient_map(np.array([0.0, 2.5e-4]), 5e-5)
    assert abs(r['p12_pa'][0]) > P.supply_pressure_pa
    assert abs(r['p12_pa'][1]) < P.supply_pressure_pa
    assert max(r['p1_pa'][0], r['p2_pa'][0]) > P.supply_pressure_pa


def test_cavitation_clip_keeps_memory():
    """P = max(PVap, PT): the clipped pressure never drops below PVap, the unclipped one keeps
    the deficit and the clipped one rises above PVap only once PT has refilled it."""
    pv = P.vapour_pressure_pa
    p1t, p2t = 1e5, 1e7
    k = P.bulk_modulus_pa / P.chamber_volume_m3
    dt = 1e-6
    trace = []
    for step in range(400):
        q1l = -2e-4 if step < 200 else 2e-4  # drain chamber 1, then refill at the same rate
        p1t, p2t, p1, p2 = chamber_step(p1t, p2t, q1l, 0.0, 0.0, k, pv, dt)
        trace.append((p1t, p1))
    pt, pc = np.array(trace).T
    assert np.all(pc >= pv)
    assert pt.min() < -1e6  # memory of the vapour volume
    assert_allclose(pc[pt <= pv], pv)
    assert_allclose(pc[pt > pv], pt[pt > pv])
    # refilling takes as long as draining: back to the start after 400 steps
    assert_allclose(pt[-1], 1e5, rtol=1e-9)


def test_transient_map_matches_numpy_reference():
    xs = RNG.uniform(-3e-4, 3e-4, 40)
    xs[:10] = RNG.uniform(-4e-6, 4e-6, 10)
    q = RNG.uniform(-8e-5, 8e-5, 40)
    n_steps, dt = 300, 1e-6
    got = transient_map(xs, q, t_end_s=n_steps * dt, dt_s=dt)['p12_pa']
    want = ref.map_transient(P, xs, q, n_steps, dt)
    assert_allclose(got, want, rtol=1e-8, atol=1e-2)


def test_transient_map_per_point_wear_matches_separate_runs():
    xs = np.array([-1e-5, 0.0, 2e-6, 1e-4])
    laps = np.array([-2e-6, 0.0, 3e-6, 6e-6])
    clrs = np.array([1e-6, 2e-6, 4e-6, 6e-6])
    got = transient_map(xs, 3e-5, laps, clrs)['p12_pa']
    for i in range(4):
        p = replace(P, overlap_supply_m=laps[i], overlap_return_m=laps[i],
                    radial_clearance_m=clrs[i])
        assert_allclose(got[i], transient_map(xs[i], 3e-5, params=p)['p12_pa'], rtol=1e-12)


def test_steady_state_satisfies_flow_balance():
    xs = RNG.uniform(-3e-4, 3e-4, 50)
    q = RNG.uniform(-5e-5, 5e-5, 50)
    r = steady_map(xs, q)
    for x, qq, p1, p2 in zip(xs, q, r['p1_pa'], r['p2_pa']):
        if p1 <= P.vapour_pressure_pa or p2 <= P.vapour_pressure_pa:
            continue
        if max(p1, p2) >= 0.99 * 20 * P.supply_pressure_pa:
            continue  # solution beyond the search bound
        q1l, q2l = valve_flows(x, p1, p2, P)
        qm = qq + P.leakage_coeff_m3_s_pa * (p1 - p2)
        scale = max(abs(qm), 1e-9)
        assert abs(q1l - qm) <= 1e-6 * scale
        assert abs(q2l - qm) <= 1e-6 * scale


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), rtol=st.sampled_from([1e-12, 1e-10, 1e-8]))
@example(seed=33178, rtol=1e-8)  # a saturated point: P2 2.8e-7 off when only the flow stopped
def test_steady_map_to_a_tolerance_is_the_bisections_solution(seed, rtol):
    """The Illinois solver (``rtol``) on random valves over and beyond the wear ranges, Cd
    law, conditions, flows and positions (cavitating and saturated points included): the
    bisections' pressures within ``rtol`` (plus the bisections' own resolution, which their
    stop on the metered flow sets at 1e-7 of the pressure where the flow gain is small), and
    the flow balance it solves."""
    rng = np.random.default_rng([seed, 0x57EA])
    lap = rng.uniform(-5e-6, 10e-6)
    v = replace(P, radial_clearance_m=rng.uniform(0.3e-6, 10e-6), overlap_supply_m=lap,
                overlap_return_m=lap, leakage_coeff_m3_s_pa=rng.uniform(0.0, 1e-11),
                supply_pressure_pa=rng.uniform(1.5e7, 2.5e7),
                return_pressure_pa=rng.uniform(2e5, 1.5e6),
                discharge_coefficient=rng.uniform(0.3, 0.9),
                critical_flow_number=10 ** rng.uniform(1.2, 3.5),
                cd_model=str(rng.choice(['constant', 'reynolds'])))
    xs = np.concatenate([spool_grid(21, v.spool_stroke_m), rng.uniform(-3e-4, 3e-4, 20)])
    q = rng.uniform(-8e-5, 8e-5, xs.size) * rng.choice([0.0, 0.1, 1.0], xs.size)
    exact = steady_map(xs, q, params=v)
    fast = steady_map(xs, q, params=v, rtol=rtol)
    for k in ('p1_pa', 'p2_pa'):
        scale = np.maximum(1.0, np.abs(exact[k]))
        assert np.all(np.abs(fast[k] - exact[k]) <= (rtol + 2e-7) * scale), k


def test_steady_map_refuses_a_tolerance_outside_its_range():
    with pytest.raises(ValueError, match='rtol'):
        steady_map(np.zeros(2), np.zeros(2), rtol=0.1)


def test_transient_and_steady_agree_open_and_differ_near_null():
    """Open spool (|XS| >= 100 um, an opening that passes 5e-5 m^3/s with less than the supply
    pressure): settled within 1 % after 1e-2 s.  Near null with flow: the transient has not
    converged (the documented difference)."""
    xs = spool_grid(133)
    q = np.array([-5e-5, 0.0, 5e-5])
    tr = transient_map(xs[:, None], q[None, :])
    st = steady_map(xs[:, None], q[None, :])
    ok = settling_mask(tr, st)
    open_ = np.abs(xs) >= 1e-4
    assert ok[open_].all()
    near = np.abs(xs) <= 2e-6
    assert not ok[near][:, [0, 2]].any()


def test_spool_grid_is_denser_near_null():
    x = spool_grid(133)
    assert x.size == 133 and x[66] == 0.0
    assert_allclose(x, -x[::-1], atol=0)
    d = np.diff(x)
    assert np.all(d > 0)
    assert d[66] * 10 < d[0]


def test_fluid_constants_are_the_one_derivation_of_the_edge_constants():
    """Cd_eff = Cd (1 - Khsv), mu = rho nu, the Reynolds flag from cd_model; the valve's
    constants and the maps' are built from them (exact: the same products)."""
    from eha_ros.physics.maps import _consts
    from eha_ros.physics.valve import edge_constants, fluid_constants
    for p in (replace(P, valve_degradation=0.3), P_CONST):
        fc = fluid_constants(p)
        assert fc.cd_eff == p.discharge_coefficient * (1.0 - p.valve_degradation)
        assert fc.mu_pa_s == p.fluid_density_kg_m3 * p.fluid_kinematic_viscosity_m2_s
        assert fc.reynolds == (p is not P_CONST)
        assert valve_constants(p) == edge_constants(p.radial_clearance_m, p.overlap_supply_m,
                                                    p.overlap_return_m, *fc)
        assert list(_consts(p)[5:]) == [float(v) for v in fc]
