"""Closed loop and steppable plant: tracking, determinism, chunking, divergence, reference."""

import math
import sys
from pathlib import Path

import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
import pytest
from hypothesis import given, settings, strategies as st

sys.path.insert(0, str(Path(__file__).parent))
import physics_reference as ref  # noqa: E402

from eha_ros.physics import (Plant, SimulationDiverged, default_params, get_scenario,  # noqa
                             load_scenarios, simulate, stability_limit)
from eha_ros.physics.loop import P12  # noqa: E402
from eha_ros.physics.params import ParameterError, replace  # noqa: E402
from eha_ros.physics.plant import PositionController  # noqa: E402
from eha_ros.physics.stability import FLAPPER, stability_limits  # noqa: E402
from eha_ros.physics.state import (CAVITATION, END_STOP, OK, S_P1, S_P1T, S_P2,  # noqa: E402
                                   S_XJ, STATE_NAMES, initial_state, operating_condition)
from eha_ros.physics.servovalve import flapper_damping, flapper_step, spool_gains  # noqa

P = default_params()


def _band(p):
    """Static error band of the P loop [m]: current hysteresis, spool breakaway referred to
    the coil current, one sensor quantum, and 3 sigma of current noise, all over Kp."""
    drive, _ = spool_gains(p)
    k1 = p.flapper_stiffness_n_m + p.feedback_spring_stiffness_n_m
    i_friction = p.spool_static_friction_n / drive * k1 / p.torque_motor_gain_n_a
    return ((p.hysteresis_a + i_friction + 3 * p.noise_std_a) / p.kp_a_m
            + p.sensor_resolution_m)


def test_step_reaches_command_within_friction_quantiser_band():
    r = simulate(P, 'step_0p1')
    x, cmd, t = r['jack_position_m'], r['command_m'], r['time_s']
    tail = t >= t[-1] - 0.02
    assert np.all(np.abs(cmd[tail] - x[tail]) <= _band(P))
    assert np.max(x) <= 1.1e-4  # overshoot below 10 %
    t90 = t[np.argmax(x >= 0.9e-4)] - 0.01
    assert 0.005 < t90 < 0.1


def test_ideal_valve_tracks_to_one_quantum():
    """No hysteresis, friction, noise or overlap: the only band left is the sensor's."""
    p = replace(P, hysteresis_a=0.0, spool_static_friction_n=0.0,
                spool_dynamic_friction_n=0.0, noise_std_a=0.0, jack_static_friction_n=0.0,
                jack_dynamic_friction_n=0.0, overlap_supply_m=0.0, overlap_return_m=0.0)
    r = simulate(p, 'step_0p1', duration_s=0.3)
    err = r['command_m'][-1] - r['jack_position_m'][-1]
    assert abs(err) <= p.sensor_resolution_m


def test_same_seed_identical_other_seed_differs():
    a = simulate(P, 'sine_0p1_10pi', duration_s=0.05, seed=3)
    b = simulate(P, 'sine_0p1_10pi', duration_s=0.05, seed=3)
    c = simulate(P, 'sine_0p1_10pi', duration_s=0.05, seed=4)
    for k in a.data:
        assert_array_equal(a[k], b[k])
    assert not np.array_equal(a['coil_current_a'], c['coil_current_a'])


def test_plant_advanced_in_ticks_equals_simulate_bit_for_bit():
    """Plant + PositionController at 1 kHz (the ROS graph's loop) == simulate()."""
    period, dt = 1e-3, 1e-6
    sim = simulate(P, 'step_0p1', duration_s=0.05, dt_s=dt, controller_period_s=period,
                   record_dt_s=None, seed=11)
    plant = Plant(P, dt_s=dt, seed=11)
    ctl = PositionController(P, period_s=period)
    sc = get_scenario('step_0p1')
    xs, cur = [], []
    for _ in range(50):
        i = ctl.update(sc.value(plant.time_ns * 1e-9), plant.measured_position_m())
        xs.append(plant.snapshot()['jack_position_m'])
        cur.append(i)
        plant.advance(i, 1000)
    assert_array_equal(np.array(xs), sim['jack_position_m'][:50])
    assert_array_equal(np.array(cur), sim['current_command_a'][:50])


def test_plant_chunks_do_not_matter():
    a, b = Plant(P, seed=5), Plant(P, seed=5)
    a.advance(3e-4, 3000)
    for n in (1, 999, 1000, 1000):
        b.advance(3e-4, n)
    assert_array_equal(a.state, b.state)


def test_plant_matches_numpy_reference():
    """300 steps from a non-trivial state with noise, every block active."""
    p = replace(P, torque_motor_model='magnetic', feedback_backlash_m=1e-6,
                surface_backlash_m=2e-6, offset_a=1e-5, hysteresis_a=3e-5)
    plant = Plant(p, seed=2)
    s = plant.state
    init = dict(play=2e-4, xf=3e-6, vf=-1e-3, xs=6e-6, vs=1e-4, p1t=1.3e7, p2t=0.8e7,
                p1=1.3e7, p2=0.8e7, xj=1e-5, vj=2e-3, surf=1e-5, qj=1e-6)
    idx = {'play': 0, 'xf': 1, 'vf': 2, 'xs': 3, 'vs': 4, 'p1t': 5, 'p2t': 6, 'p1': 7,
           'p2': 8, 'xj': 9, 'vj': 10, 'surf': 11, 'qj': 12}
    for k, v in init.items():
        s[idx[k]] = v
    n = 300
    noise = plant.noise.samples_until(n * plant.dt_s)
    per_step = [noise[int(j * plant.dt_s / p.noise_sample_time_s)] for j in range(n)]
    want = ref.plant_steps(p, init, 5e-4, per_step, n, plant.dt_s)
    plant.advance(5e-4, n)
    for k, i in idx.items():
        assert_allclose(plant.state[i], want[k], rtol=1e-9, atol=1e-15, err_msg=k)


def test_all_named_scenarios_run_and_stay_bounded():
    for name, sc in load_scenarios().items():
        r = simulate(P, sc, duration_s=min(sc.duration_s, 0.3))
        amp = max(abs(sc.amplitude_m), *map(abs, sc.com_values_m or (0,)))
        assert np.all(np.abs(r['jack_position_m']) <= 2 * amp + _band(P)), name
        assert np.all(np.isfinite(r['p12_pa'])), name


def test_magnetic_and_fixed_torque_motor_agree_on_small_signal():
    a = simulate(P, 'step_0p1', duration_s=0.1)
    b = simulate(replace(P, torque_motor_model='magnetic'), 'step_0p1', duration_s=0.1)
    assert_allclose(b['jack_position_m'][-1], a['jack_position_m'][-1], rtol=0.05)


def test_degradations_change_the_response_the_expected_way():
    base = simulate(P, 'step_1mm', duration_s=0.05)
    clogged = simulate(replace(P, filter_clogging=0.8), 'step_1mm', duration_s=0.05)
    demag = simulate(replace(P, demagnetisation=0.5), 'step_1mm', duration_s=0.05)
    early = np.searchsorted(base['time_s'], 0.016)  # 6 ms into the 1 mm step
    for worse in (clogged, demag):
        assert worse['jack_position_m'][early] < 0.95 * base['jack_position_m'][early]


def test_nonfinite_state_stops_the_run_naming_state_and_time():
    plant = Plant(P)
    plant.advance(0.0, 100)
    plant.state[S_P1T] = np.nan
    with pytest.raises(SimulationDiverged, match=r'p1_unclipped_pa .* t = 0\.000101 s'):
        plant.advance(0.0, 10)


def test_first_stage_stability_limit_is_real():
    """The first stage's bound is exact for its linear oscillator: at 0.9x it decays, at 1.1x
    it grows (until the stops); and steps beyond the plant's limit are refused."""
    p = replace(P, flapper_stroke_m=3e-4)
    dt_lim = {x.key: x.dt_s for x in stability_limits(p)}[FLAPPER]
    cf = flapper_damping(p)
    for fac, grows in ((0.9, False), (1.1, True)):
        xf, vf = 1e-8, 0.0
        for _ in range(2000):
            xf, vf = flapper_step(xf, vf, 0.0, 0.0, cf, p, fac * dt_lim)
        assert (abs(xf) > 1e-8) == grows
    lim = stability_limit(P).dt_s
    assert lim > 1e-6  # the 1 us default is inside
    with pytest.raises(ParameterError, match='dt_s = .* exceeds the stability limit'):
        simulate(P, 'step_0p1', dt_s=math.ceil(1.01 * lim * 1e9) * 1e-9)
    with pytest.raises(ParameterError, match='dt_s'):
        Plant(P, dt_s=-1e-6)


def test_bad_run_arguments():
    with pytest.raises(ParameterError, match='whole multiple'):
        simulate(P, 'step_0p1', controller_period_s=1.5e-6)
    with pytest.raises(ParameterError, match='unknown scenario'):
        simulate(P, 'no_such_scenario')
    with pytest.raises(ParameterError, match='duration_s'):
        simulate(P, 'step_0p1', duration_s=float('nan'))
    with pytest.raises(ParameterError, match='not finite'):
        Plant(P).advance(float('inf'), 10)


def test_fluid_function_replaces_the_fluid_block():
    """A fluid function P12 = f(XS, QJ, overlap, clearance), QJ = AJ dXJ/dt, drives the jack in
    place of the chambers (evaluated on the start-of-step state, reported as mid +- P12/2);
    with a linearised valve (flow gain Kq, flow-pressure coefficient Kc) the loop tracks."""
    from numba import njit

    @njit
    def linear_valve(data, xs, q, lap, clr):
        kq, kc = data[0][0], data[0][1]
        return (kq * xs - q) / kc

    class Linear:  # a FluidBlock
        name = 'linear'
        kernel = linear_valve
        kernel_output = P12

        def prepare(self, p):
            return (np.array([0.9, 1e-11]),)

        def stability_limit(self, p):
            return math.inf, 'linear valve'

        def check_params(self, p):
            pass

    plant = Plant(P, fluid=Linear())
    plant.advance(5e-4, 999)
    s0 = plant.snapshot()
    plant.advance(5e-4, 1)
    s1 = plant.snapshot()
    expect = (0.9 * s0['spool_position_m'] - P.jack_area_m2 * s0['jack_velocity_m_s']) / 1e-11
    assert_allclose(s1['p12_pa'], expect, rtol=1e-12)
    mid = 0.5 * (P.supply_pressure_pa + P.return_pressure_pa)
    assert_allclose(s1['p1_pa'] + s1['p2_pa'], 2 * mid, rtol=1e-12)
    r = simulate(P, 'step_0p1', fluid=Linear())
    assert abs(r['jack_position_m'][-1] - 1e-4) < _band(P)
    for bad in (object(), type('Other', (Linear,), {'kernel_output': 'p1'})()):
        with pytest.raises(ParameterError, match='must be a FluidBlock'):
            simulate(P, 'step_0p1', duration_s=0.01, fluid=bad)


def test_state_names_cover_the_state():
    assert len(STATE_NAMES) == initial_state(P).size
    s = initial_state(P)
    assert_allclose(s[7], s[8], rtol=1e-9)  # symmetric valve at null: P1 = P2


def test_operating_condition_of_the_state():
    """Closed forms: the jack at either end of its stroke is END_STOP (whatever the
    pressures); a chamber clipped at the vapour pressure is CAVITATION; the rest state and the
    jack one ulp inside its stroke are OK."""
    s = initial_state(P)
    assert P.vapour_pressure_pa < min(s[S_P1], s[S_P2]) and operating_condition(s, P) == OK
    for xj in (P.jack_stroke_m, -P.jack_stroke_m):
        e = s.copy()
        e[S_XJ] = xj
        assert operating_condition(e, P) == END_STOP
        e[S_P1] = P.vapour_pressure_pa
        assert operating_condition(e, P) == END_STOP
        e = s.copy()
        e[S_XJ] = np.nextafter(xj, 0.0)
        assert operating_condition(e, P) == OK
    for k in (S_P1, S_P2):
        c = s.copy()
        c[k] = P.vapour_pressure_pa
        assert operating_condition(c, P) == CAVITATION


def _tick_by_tick(plant, currents, steps):
    rows = []
    for c in currents:
        plant.advance(float(c), steps)
        s = plant.snapshot()
        rows.append([s[n] for n in ADVANCE_CURRENTS_SIGNALS])
    return np.array(rows)


#: The snapshot fields :meth:`Plant.advance_currents` must reproduce (those of its record).
ADVANCE_CURRENTS_SIGNALS = ('coil_current_a', 'torque_motor_force_n', 'flapper_position_m',
                            'spool_position_m', 'p1_pa', 'p2_pa', 'p12_pa', 'load_flow_m3_s',
                            'jack_position_m', 'jack_velocity_m_s', 'surface_position_m')


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), integrator=st.sampled_from(['explicit', 'split']),
       steps_ticks=st.integers(1, 200), skip=st.integers(0, 30),
       currents=st.lists(st.floats(-0.02, 0.02), min_size=1, max_size=25))
def test_advance_currents_is_advance_tick_by_tick_bit_for_bit(seed, integrator, steps_ticks,
                                                              skip, currents):
    """A scripted current, one held command per tick, in one kernel call gives the states a
    plant stepped tick by tick gives, bit for bit, after any start (noise on, any seed, both
    integrators, ticks of 1 to 200 steps of 1 us or 10 us)."""
    from eha_ros.physics.state import RECORD_FIELDS
    dt = 1e-6 if integrator == 'explicit' else 1e-5
    a = Plant(P, dt_s=dt, seed=seed, integrator=integrator)
    b = Plant(P, dt_s=dt, seed=seed, integrator=integrator)
    for p_ in (a, b):
        p_.advance(0.003, skip)
    want = _tick_by_tick(a, currents, steps_ticks)
    rec = b.advance_currents(np.array(currents), steps_ticks)
    got = rec[:, [RECORD_FIELDS.index(n) for n in ADVANCE_CURRENTS_SIGNALS]]
    assert_array_equal(got, want)
    assert_array_equal(a.state, b.state)
    assert a.steps == b.steps
    assert_array_equal(rec[:, RECORD_FIELDS.index('current_command_a')], currents)
    assert rec[-1, RECORD_FIELDS.index('time_s')] == b.time_s


@pytest.mark.parametrize('currents, steps, words', [
    ([], 10, 'non-empty'), ([[0.0]], 10, '1-D'), ([0.0, math.nan], 10, 'finite'),
    ([0.0], 0, 'steps_per_tick = 0')])
def test_advance_currents_refuses_what_it_cannot_run(currents, steps, words):
    plant = Plant(P)
    with pytest.raises(ParameterError, match=words):
        plant.advance_currents(np.array(currents), steps)
    assert plant.steps == 0
