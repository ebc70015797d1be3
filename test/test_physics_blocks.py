"""Blocks one by one: Borello friction, torque motor, first stage, spool, jack, commands."""

import math
import sys
from pathlib import Path

import numpy as np
from numpy.testing import assert_allclose
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import physics_reference as ref  # noqa: E402

from eha_ros.physics import default_params, load_scenarios  # noqa: E402
from eha_ros.physics.commands import Scenario  # noqa: E402
from eha_ros.physics.friction import (BREAKAWAY, SLIDING, STOPPING, STUCK,  # noqa: E402
                                      borello_mass, borello_massless)
from eha_ros.physics.jack import jack_step, quantise, surface_position  # noqa: E402
from eha_ros.physics.params import ParameterError, replace  # noqa: E402
from eha_ros.physics.servovalve import (coil_current, dead_zone, flapper_damping,  # noqa: E402
                                        flapper_step, magnetic_stiffness, play, spool_gains,
                                        spool_step, torque_motor_force)

P = default_params()
RNG = np.random.default_rng(7)


# --- Borello friction ---------------------------------------------------------------------------

def test_borello_mass_four_cases():
    fs, fd, m, dt = 10.0, 5.0, 2.0, 1e-3
    v, ff, case = borello_mass(0.0, 8.0, fs, fd, m, dt)  # stuck: friction balances
    assert (v, ff, case) == (0.0, 8.0, STUCK)
    v, ff, case = borello_mass(0.0, -12.0, fs, fd, m, dt)  # breakaway: static friction
    assert case == BREAKAWAY and ff == -fs
    assert_allclose(v, (-12.0 + 10.0) / m * dt, rtol=1e-15)
    v, ff, case = borello_mass(0.1, 3.0, fs, fd, m, dt)  # sliding: dynamic friction
    assert case == SLIDING and ff == fd
    assert_allclose(v, 0.1 + (3.0 - 5.0) / m * dt, rtol=1e-15)
    v, ff, case = borello_mass(1e-4, -50.0, fs, fd, m, dt)  # would reverse: stops exactly
    assert (v, case) == (0.0, STOPPING)


def test_borello_massless_four_cases():
    fs, fd, c = 1.0, 0.5, 100.0
    assert borello_massless(0.0, 0.9, fs, fd, c)[::2] == (0.0, STUCK)
    v, ff, case = borello_massless(0.0, 1.5, fs, fd, c)
    assert case == BREAKAWAY and _close(v, 0.5 / c)
    v, ff, case = borello_massless(0.01, 0.8, fs, fd, c)
    assert case == SLIDING and _close(v, 0.3 / c)
    assert borello_massless(0.01, 0.4, fs, fd, c)[::2] == (0.0, STOPPING)  # below sliding
    assert borello_massless(0.01, -3.0, fs, fd, c)[::2] == (0.0, STOPPING)  # reversal


def _close(a, b):
    return math.isclose(a, b, rel_tol=1e-14)


def test_borello_kernels_match_reference():
    for _ in range(2000):
        v = RNG.choice([0.0, RNG.normal(0, 1e-2)])
        f = RNG.normal(0, 20)
        fs = RNG.uniform(0, 15)
        fd = RNG.uniform(0, fs)
        assert_allclose(borello_mass(v, f, fs, fd, 3.0, 1e-4)[0],
                        ref.borello_mass(v, f, fs, fd, 3.0, 1e-4), rtol=1e-14, atol=0)
        assert_allclose(borello_massless(v, f, fs, fd, 50.0)[0],
                        ref.borello_massless(v, f, fs, fd, 50.0), rtol=1e-14, atol=0)


def test_jack_friction_holds_load_below_breakaway():
    """A body pushed with less than FS never moves; with more it accelerates at
    (F - FS)/m then (F - FD)/m."""
    p = replace(P, jack_viscous_n_s_m=0.0, aero_stiffness_n_m=0.0)
    f_hold = 0.99 * p.jack_static_friction_n / p.jack_area_m2
    xj, vj = 0.0, 0.0
    for _ in range(1000):
        xj, vj = jack_step(xj, vj, f_hold, p, 1e-5)
    assert xj == 0.0 and vj == 0.0
    p12 = 2.0 * p.jack_static_friction_n / p.jack_area_m2
    n, dt = 1000, 1e-5
    for _ in range(n):
        xj, vj = jack_step(xj, vj, p12, p, dt)
    f = p12 * p.jack_area_m2
    v_expect = ((f - p.jack_static_friction_n) + (n - 1) * (f - p.jack_dynamic_friction_n)
                ) / p.jack_mass_kg * dt
    assert_allclose(vj, v_expect, rtol=1e-12)


# --- torque motor -----------------------------------------------------------------------------

def test_play_hysteresis_branches_and_threshold():
    h = 1e-4
    y = 0.0
    ys = []
    u = np.concatenate([np.linspace(0, 1e-3, 50), np.linspace(1e-3, -1e-3, 100)])
    for ui in u:
        y = play(y, ui, h)
        ys.append(y)
    ys = np.array(ys)
    assert_allclose(ys[49], 1e-3 - h)  # rising branch: u - His
    assert_allclose(ys[-1], -1e-3 + h)  # falling branch: u + His
    # reversal: the output holds until the input has moved 2 His back (the threshold)
    held = ys[50:][u[50:] > 1e-3 - 2 * h]
    assert_allclose(held, 1e-3 - h)
    for _ in range(200):
        a, b, hh = RNG.normal(0, 1e-3, 3)
        assert play(a, b, abs(hh)) == ref.play(a, b, abs(hh))


def test_coil_current_offset_noise_and_saturation():
    p = replace(P, hysteresis_a=0.0, offset_a=1e-4)
    assert_allclose(coil_current(0.0, 2e-3, 5e-6, p)[1], 2e-3 + 1e-4 + 5e-6, rtol=1e-15)
    assert coil_current(0.0, 1.0, 0.0, p)[1] == p.current_limit_a
    assert coil_current(0.0, -1.0, 0.0, p)[1] == -p.current_limit_a


def test_fixed_gain_force_and_demagnetisation():
    assert_allclose(torque_motor_force(4e-3, 1e-5, P), P.torque_motor_gain_n_a * 4e-3)
    p = replace(P, demagnetisation=0.3)
    assert_allclose(torque_motor_force(4e-3, 0.0, p), 0.7 * P.torque_motor_gain_n_a * 4e-3)


def test_magnetic_force_closed_forms():
    """At null: F/i = Vp n La / (2 R0 f lg ls); at zero current: F = +k_m XF (negative
    stiffness), F linear in i and XF with no cross term, matching the flux formula."""
    p = replace(P, torque_motor_model='magnetic')
    mu0 = 4e-7 * math.pi
    r0 = p.air_gap_m / (mu0 * p.air_gap_area_m2)
    gain = (p.magnet_mmf_a * p.coil_turns * p.armature_length_m
            / (2 * r0 * p.fringing_factor * p.air_gap_m * p.flapper_arm_m))
    assert_allclose(torque_motor_force(1e-3, 0.0, p) / 1e-3, gain, rtol=1e-12)
    assert_allclose(gain, P.torque_motor_gain_n_a, rtol=0.02)  # config consistency
    k_m = magnetic_stiffness(p)
    assert_allclose(torque_motor_force(0.0, 1e-5, p), k_m * 1e-5, rtol=1e-12)
    assert 0 < k_m < p.flapper_stiffness_n_m
    for _ in range(100):
        i, x = RNG.uniform(-1e-2, 1e-2), RNG.uniform(-4e-5, 4e-5)
        assert_allclose(torque_motor_force(i, x, p), ref.torque_force(p, i, x), rtol=1e-12)
        assert_allclose(torque_motor_force(i, x, p), gain * i + k_m * x, rtol=1e-9)


# --- first stage ---------------------------------------------------------------------------------

def test_flapper_static_deflection_and_natural_frequency():
    """Spool held at 0: XF -> F/(KF + KSF); free oscillation at sqrt((KF+KSF)/MF)
    damped by ZF (log decrement), within 0.5 %."""
    p = replace(P, flapper_damping_ratio=0.05)
    cf = flapper_damping(p)
    f, dt = 0.1, 1e-8
    k = p.flapper_stiffness_n_m + p.feedback_spring_stiffness_n_m
    xf, vf = 0.0, 0.0
    peaks, prev, rising = [], 0.0, True
    for n in range(200000):
        xf, vf = flapper_step(xf, vf, 0.0, f, cf, p, dt)
        if rising and xf < prev:
            peaks.append((n * dt, prev))
        rising = xf >= prev
        prev = xf
    wn = math.sqrt(k / p.flapper_mass_kg)
    wd = wn * math.sqrt(1 - 0.05 ** 2)
    period = peaks[1][0] - peaks[0][0]
    assert_allclose(2 * math.pi / period, wd, rtol=5e-3)
    x_static = f / k
    decay = (peaks[0][1] - x_static) / (peaks[1][1] - x_static)
    assert_allclose(math.log(decay), 2 * math.pi * 0.05 / math.sqrt(1 - 0.05 ** 2), rtol=0.02)
    cf = flapper_damping(P)  # nominal damping: settled after 5 ms
    xf, vf = 0.0, 0.0
    for _ in range(50000):
        xf, vf = flapper_step(xf, vf, 0.0, f, cf, P, 1e-7)
    assert_allclose(xf, x_static, rtol=1e-4)


def test_flapper_end_stop_resets_velocity_and_backlash_dead_zone():
    cf = flapper_damping(P)
    xf, vf = flapper_step(P.flapper_stroke_m * 0.999, 1.0, 0.0, 10.0, cf, P, 1e-6)
    assert xf == P.flapper_stroke_m and vf == 0.0
    assert dead_zone(1e-6, 2e-6) == 0.0
    assert_allclose(dead_zone(5e-6, 2e-6), 3e-6)
    assert_allclose(dead_zone(-5e-6, 2e-6), -3e-6)
    p = replace(P, feedback_backlash_m=4e-6)  # spool inside the ball play: no spring force
    xf, vf = flapper_step(0.0, 0.0, 1.5e-6, 0.0, cf, p, 1e-6)
    assert xf == 0.0 and vf == 0.0


def test_spool_velocity_massless_closed_form_and_clogging():
    """No friction, no flow force: XS' = ASV GPF XF / (CS + ASV^2 GPF/GQF); a clogged filter
    scales GPF by s and GQF by sqrt(s), s = (1 - K_intas) PSR/PSR0."""
    p = replace(P, spool_static_friction_n=0.0, spool_dynamic_friction_n=0.0,
                flow_force_coeff_n_s_m3=0.0)
    xf = 2e-6
    for k_intas in (0.0, 0.5, 0.9):
        pk = replace(p, filter_clogging=k_intas)
        s = (1 - k_intas) * (p.supply_pressure_pa - p.return_pressure_pa
                             ) / p.nominal_supply_return_pa
        gpf = p.first_stage_pressure_gain_pa_m * s
        gqf = p.first_stage_flow_gain_m2_s * math.sqrt(s)
        v = p.spool_end_area_m2 * gpf * xf / (p.spool_damping_n_s_m
                                              + p.spool_end_area_m2 ** 2 * gpf / gqf)
        drive, c_eq = spool_gains(pk)
        xs, vs = spool_step(0.0, 1e-9, xf, 0.0, drive, c_eq, pk, 1e-6)
        assert_allclose(vs, v, rtol=1e-12)
        assert_allclose(xs, v * 1e-6, rtol=1e-12)
    drive, c_eq = spool_gains(replace(p, filter_clogging=1.0))
    assert drive == 0.0 and c_eq == p.spool_damping_n_s_m


def test_spool_end_stop():
    drive, c_eq = spool_gains(P)
    xs, vs = spool_step(P.spool_stroke_m, 0.1, 4e-5, 0.0, drive, c_eq, P, 1e-6)
    assert xs == P.spool_stroke_m and vs == 0.0


# --- jack, surface, sensor --------------------------------------------------------------------

def test_jack_viscous_response_closed_form():
    """No friction, no aero: v(t) = F/CJ (1 - exp(-CJ t / MJ)) within 0.1 %."""
    p = replace(P, jack_static_friction_n=0.0, jack_dynamic_friction_n=0.0,
                aero_stiffness_n_m=0.0)
    p12, dt, n = 1e6, 1e-6, 20000
    xj, vj = 0.0, 0.0
    for _ in range(n):
        xj, vj = jack_step(xj, vj, p12, p, dt)
    f = p12 * p.jack_area_m2
    t = n * dt
    assert_allclose(vj, f / p.jack_viscous_n_s_m * (1 - math.exp(
        -p.jack_viscous_n_s_m * t / p.jack_mass_kg)), rtol=1e-3)


def test_jack_end_stop_and_sensor():
    xj, vj = jack_step(P.jack_stroke_m, 0.5, 1e7, P, 1e-6)
    assert xj == P.jack_stroke_m and vj == 0.0
    assert quantise(1.4e-6, 1e-6) == 1e-6 and quantise(-1.6e-6, 1e-6) == -2e-6
    assert quantise(1.234567e-6, 0.0) == 1.234567e-6
    p = replace(P, surface_backlash_m=2e-5)
    assert surface_position(0.0, 5e-6, p) == 0.0  # inside the play
    assert_allclose(surface_position(0.0, 3e-5, p), 2e-5)


# --- commands -----------------------------------------------------------------------------------

def test_waveforms():
    step = Scenario('s', 'step', 1.0, amplitude_m=2e-4, start_s=0.1)
    assert step.value(0.05) == 0.0 and step.value(0.1) == 2e-4
    ramp = Scenario('r', 'ramp', 1.0, amplitude_m=1e-4, start_s=0.1, ramp_time_s=0.2)
    assert_allclose(ramp.value([0.0, 0.2, 0.3, 0.9]), [0.0, 5e-5, 1e-4, 1e-4])
    sine = Scenario('w', 'sine', 1.0, amplitude_m=1e-4, frequency_rad_s=5 * math.pi)
    assert_allclose(sine.value(0.1), 1e-4 * math.sin(0.5 * math.pi))
    chirp = Scenario('c', 'chirp', 2.0, amplitude_m=1.0, f0_hz=1.0, f1_hz=5.0,
                     sweep_time_s=2.0)
    t = np.linspace(0, 2, 200001)
    phase = np.unwrap(np.arcsin(np.clip(chirp.value(t[:2000]), -1, 1)))
    assert_allclose(np.gradient(phase, t[:2000])[10] / (2 * math.pi), 1.0, rtol=1e-2)
    com = Scenario('k', 'com', 1.0, com_times_s=(0.1, 0.3), com_values_m=(1e-4, -2e-4))
    assert_allclose(com.value([0.0, 0.1, 0.2, 0.3, 0.5]), [0, 1e-4, 1e-4, -2e-4, -2e-4])


def test_thesis_scenarios_are_named_in_config():
    sc = load_scenarios()
    for name, amp, w in [('step_0p1', 1e-4, 0), ('step_0p01', 1e-5, 0), ('ramp_0p1', 1e-4, 0),
                         ('ramp_0p01', 1e-5, 0), ('sine_0p1_5pi', 1e-4, 5 * math.pi),
                         ('sine_0p1_10pi', 1e-4, 10 * math.pi),
                         ('sine_0p01_5pi', 1e-5, 5 * math.pi),
                         ('sine_0p01_10pi', 1e-5, 10 * math.pi),
                         ('sine_0p01_2pi', 1e-5, 2 * math.pi)]:
        assert sc[name].amplitude_m == amp
        assert_allclose(sc[name].frequency_rad_s, w)
    assert {'chirp', 'com'} <= {s.waveform for s in sc.values()}


@pytest.mark.parametrize('kw, msg', [
    (dict(waveform='square'), 'unknown waveform'),
    (dict(waveform='sine', frequency_rad_s=0.0), 'positive frequency'),
    (dict(waveform='ramp', ramp_time_s=0.0), 'ramp_time_s'),
    (dict(waveform='com', com_times_s=(0.2, 0.1), com_values_m=(1.0, 2.0)), 'increasing'),
    (dict(waveform='step', duration_s=-1.0), 'duration_s'),
])
def test_bad_scenarios_are_refused(kw, msg):
    args = dict(name='bad', waveform='step', duration_s=1.0)
    args.update(kw)
    with pytest.raises(ParameterError, match=msg):
        Scenario(**args)
