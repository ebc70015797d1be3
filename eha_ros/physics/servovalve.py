"""Electromechanical part of the servovalve: torque motor, first stage (flapper), second stage
(spool).  Pure numba kernels ``(state..., inputs..., p, dt) -> new state``.

Torque motor.  The controller current passes a play (backlash-type) hysteresis of half-width
``His`` - rising, the output is ``u - His``; falling, ``u + His``; in between it holds, which
gives the valve its threshold - then the offset ``Ofs`` and the band-limited noise are added
and the result is saturated at ``+-CorM``.  The force on the flapper is ``GM i (1 - KGM)`` or,
with ``torque_motor_model = magnetic``, comes from the air-gap fluxes::

    phi1 = a (1 + xa/lg) + b,   phi2 = a (1 - xa/lg) - b,   a = Vp / (2 R0 f),  b = n i / (2 R0)
    T = (phi1^2 - phi2^2) La / (2 Ag mu0),   F = T (1 - KGM) / ls,   xa = XF La / (2 ls)

with ``R0 = lg / (mu0 Ag)``.  The armature is attracted to the closing gap, which makes the
magnetic spring destabilising (the torque motor's negative stiffness); the reference writes the
flux terms with the opposite sign of ``xa``, which would make it stabilising.

First stage.  ``MF XF'' + CF XF' + KF XF + KSF dz(XF + XS) = F``, ``CF = 2 ZF sqrt(MF (KSF+KF))``,
``dz`` the dead zone of the feedback-spring ball play (``Kgioco``), end stops ``+-XFM`` that
reset velocity (and so acceleration).  Semi-implicit Euler.

Second stage.  Massless spool (the last equation of the reference's 4.1.2)::

    XS' (CS + ASV^2 GPF/GQF) = ASV GPF XF - FF - Kflow QJ

with Borello friction on the massless spool, end stops ``+-XSM`` and filter clogging
``GPF = GPF0 s``, ``GQF = GQF0 sqrt(s)``, ``s = (1 - K_intas) PSR/PSR0``.
"""

from __future__ import annotations

import math

from numba import njit

from .friction import borello_massless

__all__ = ['play', 'dead_zone', 'coil_current', 'torque_motor_force', 'flapper_step',
           'spool_step', 'flapper_damping', 'magnetic_stiffness', 'end_stops', 'MU0']

MU0 = 4e-7 * math.pi  # vacuum permeability [H/m]


@njit(cache=True, inline='always')
def play(y_prev, u, half_width):
    """Play (backlash) operator: output follows ``u`` within ``+-half_width``."""
    return min(max(y_prev, u - half_width), u + half_width)


@njit(cache=True, inline='always')
def dead_zone(u, half_width):
    """Dead zone of half-width ``half_width`` (zero inside, shifted linear outside)."""
    if u > half_width:
        return u - half_width
    if u < -half_width:
        return u + half_width
    return 0.0


@njit(cache=True, inline='always')
def coil_current(play_prev, i_command, noise_a, p):
    """(new play state, actual coil current [A]) for a commanded current."""
    y = play(play_prev, i_command, p.hysteresis_a)
    i = y + p.offset_a + noise_a
    lim = p.current_limit_a
    return y, min(max(i, -lim), lim)


@njit(cache=True, inline='always')
def torque_motor_force(i_a, xf_m, p):
    """Force [N] on the flapper for coil current ``i_a`` at flapper position ``xf_m``."""
    if p.torque_motor_model == 0.0:
        f = p.torque_motor_gain_n_a * i_a
    else:
        r0 = p.air_gap_m / (MU0 * p.air_gap_area_m2)
        a = p.magnet_mmf_a / (2.0 * r0 * p.fringing_factor)
        b = p.coil_turns * i_a / (2.0 * r0)
        xa = xf_m * p.armature_length_m / (2.0 * p.flapper_arm_m)
        phi1 = a * (1.0 + xa / p.air_gap_m) + b
        phi2 = a * (1.0 - xa / p.air_gap_m) - b
        torque = (phi1 * phi1 - phi2 * phi2) * p.armature_length_m / (
            2.0 * p.air_gap_area_m2 * MU0)
        f = torque / p.flapper_arm_m
    return f * (1.0 - p.demagnetisation)


def magnetic_stiffness(p) -> float:
    """Negative stiffness [N/m] of the magnetic circuit at the flapper (magnetic model)."""
    r0 = p.air_gap_m / (MU0 * p.air_gap_area_m2)
    a = p.magnet_mmf_a / (2.0 * r0 * p.fringing_factor)
    k_arm = p.armature_length_m / (2.0 * p.flapper_arm_m)
    return (4.0 * a * a * k_arm / p.air_gap_m * p.armature_length_m
            / (2.0 * p.air_gap_area_m2 * MU0) / p.flapper_arm_m * (1.0 - p.demagnetisation))


@njit(cache=True, inline='always')
def end_stops(x, v, lim):
    """A body against its stops at ``+-lim``: the position held there, a velocity into the
    stop nulled; returns (x, v)."""
    if x > lim:
        x = lim
        if v > 0.0:
            v = 0.0
    elif x < -lim:
        x = -lim
        if v < 0.0:
            v = 0.0
    return x, v


@njit(cache=True, inline='always')
def flapper_damping(p):
    """CF = 2 ZF sqrt(MF (KSF + KF)) [N s/m]."""
    return 2.0 * p.flapper_damping_ratio * math.sqrt(
        p.flapper_mass_kg * (p.feedback_spring_stiffness_n_m + p.flapper_stiffness_n_m))


@njit(cache=True, inline='always')
def flapper_step(xf, vf, xs, force_n, cf, p, dt):
    """One semi-implicit Euler step of the first stage; returns (XF, VF)."""
    fb = p.feedback_spring_stiffness_n_m * dead_zone(xf + xs, 0.5 * p.feedback_backlash_m)
    acc = (force_n - cf * vf - p.flapper_stiffness_n_m * xf - fb) / p.flapper_mass_kg
    vf = vf + acc * dt
    xf = xf + vf * dt
    return end_stops(xf, vf, p.flapper_stroke_m)


@njit(cache=True, inline='always')
def spool_gains(p):
    """(ASV*GPF, c_eq) of the spool with the filter-clogging correction."""
    s = (1.0 - p.filter_clogging) * (p.supply_pressure_pa - p.return_pressure_pa) / (
        p.nominal_supply_return_pa)
    s = max(s, 0.0)
    gpf = p.first_stage_pressure_gain_pa_m * s
    # ASV^2 GPF/GQF = ASV^2 (GPF0/GQF0) sqrt(s): finite even for a fully clogged filter
    c_eq = p.spool_damping_n_s_m + p.spool_end_area_m2 ** 2 * (
        p.first_stage_pressure_gain_pa_m / p.first_stage_flow_gain_m2_s) * math.sqrt(s)
    return p.spool_end_area_m2 * gpf, c_eq


@njit(cache=True, inline='always')
def spool_step(xs, vs_prev, xf, qj, drive_gain, c_eq, p, dt):
    """One step of the massless spool; returns (XS, VS)."""
    f = drive_gain * xf - p.flow_force_coeff_n_s_m3 * qj
    vs, _, _ = borello_massless(vs_prev, f, p.spool_static_friction_n,
                                p.spool_dynamic_friction_n, c_eq)
    xs = xs + vs * dt
    lim = p.spool_stroke_m
    if xs > lim:
        xs = lim
        vs = 0.0
    elif xs < -lim:
        xs = -lim
        vs = 0.0
    return xs, vs
