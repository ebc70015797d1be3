"""Plain-numpy reference implementations of the physics kernels, written from the equations
(not from the kernels) to cross-check them: the orifice flow from the quadratic's textbook root
and an explicit Reynolds-number discharge coefficient, the torque from the fluxes, etc."""

import math

import numpy as np

MU0 = 4e-7 * math.pi


def discharge_coefficient(p, gap_m, dp_pa):
    """Cd from the flow number lambda = (D_h / nu) sqrt(2 |dp| / rho), D_h = 2 gap."""
    cd_inf = p.discharge_coefficient * (1.0 - p.valve_degradation)
    if p.cd_model == 1.0:
        return np.full(np.shape(dp_pa), cd_inf)
    lam = 2.0 * gap_m / p.fluid_kinematic_viscosity_m2_s * np.sqrt(
        2.0 * np.abs(dp_pa) / p.fluid_density_kg_m3)
    x = 2.0 * lam / p.critical_flow_number
    return cd_inf * x / np.sqrt(1.0 + x * x)


def edge(p, opening_m):
    """(RL, passage area A, gap h) of an edge; opening > 0 uncovered."""
    c, w = p.radial_clearance_m, p.port_width_m
    mu = p.fluid_density_kg_m3 * p.fluid_kinematic_viscosity_m2_s
    opening_m = np.asarray(opening_m, dtype=float)
    x0 = np.where(opening_m > 0, 0.0, -opening_m)
    rl = 12 * mu * x0 / (w * c ** 3 * (1 + 1.5 * p.eccentricity_ratio ** 2))
    gap = np.where(opening_m > 0, np.sqrt(c ** 2 + opening_m ** 2), c)
    return rl, w * gap, gap


def orifice_flow(p, opening_m, dp_pa):
    """Q = sign(dp) (-RL + sqrt(RL^2 + 4 RQ |dp|)) / (2 RQ), RQ = rho / (2 Cd^2 A^2)."""
    rl, area, gap = edge(p, opening_m)
    dp_pa = np.asarray(dp_pa, dtype=float)
    cd = discharge_coefficient(p, gap, dp_pa)
    with np.errstate(divide='ignore', invalid='ignore'):
        rq = p.fluid_density_kg_m3 / (2 * cd ** 2 * area ** 2)
        q = np.sign(dp_pa) * (-rl + np.sqrt(rl ** 2 + 4 * rq * np.abs(dp_pa))) / (2 * rq)
    return np.where(np.abs(dp_pa) > 0, q, 0.0)


def valve_flows(p, xs, p1, p2):
    """(Q1L, Q2L): net into chamber 1, net out of chamber 2."""
    ps, pr = p.supply_pressure_pa, p.return_pressure_pa
    oss, ors = p.overlap_supply_m, p.overlap_return_m
    q1s = orifice_flow(p, xs - oss, ps - p1)
    q1r = orifice_flow(p, -xs - ors, p1 - pr)
    q2s = orifice_flow(p, -xs - oss, ps - p2)
    q2r = orifice_flow(p, xs - ors, p2 - pr)
    return q1s - q1r, q2r - q2s


def borello_mass(v, f, fs, fd, m, dt):
    if v == 0.0:
        if abs(f) <= fs:
            return 0.0
        return (f - fs * np.sign(f)) / m * dt
    vn = v + (f - fd * np.sign(v)) / m * dt
    return 0.0 if np.sign(vn) != np.sign(v) and vn != 0.0 else vn


def borello_massless(v_prev, f, fs, fd, c):
    if v_prev == 0.0:
        return 0.0 if abs(f) <= fs else (f - fs * np.sign(f)) / c
    v = (f - fd * np.sign(v_prev)) / c
    return 0.0 if v * v_prev <= 0 else v


def play(y, u, h):
    if u - h > y:
        return u - h
    if u + h < y:
        return u + h
    return y


def torque_force(p, i, xf):
    if p.torque_motor_model == 0.0:
        return p.torque_motor_gain_n_a * i * (1 - p.demagnetisation)
    r0 = p.air_gap_m / (MU0 * p.air_gap_area_m2)
    vp_term = p.magnet_mmf_a / (2 * r0) / p.fringing_factor
    xa = xf * (p.armature_length_m / 2) / p.flapper_arm_m
    phi1 = vp_term * (1 + xa / p.air_gap_m) + i * p.coil_turns / (2 * r0)
    phi2 = vp_term * (1 - xa / p.air_gap_m) - i * p.coil_turns / (2 * r0)
    t = (phi1 ** 2 - phi2 ** 2) * p.armature_length_m / (2 * p.air_gap_area_m2 * MU0)
    return t / p.flapper_arm_m * (1 - p.demagnetisation)


def plant_steps(p, state, i_cmd, noise, n_steps, dt):
    """Plain-python plant: dict state -> dict state after n_steps (noise[k] per step)."""
    s = dict(state)
    cf = 2 * p.flapper_damping_ratio * math.sqrt(
        p.flapper_mass_kg * (p.feedback_spring_stiffness_n_m + p.flapper_stiffness_n_m))
    sfac = max(0.0, (1 - p.filter_clogging) * (p.supply_pressure_pa - p.return_pressure_pa)
               / p.nominal_supply_return_pa)
    gpf = p.first_stage_pressure_gain_pa_m * sfac
    gqf = p.first_stage_flow_gain_m2_s * math.sqrt(sfac)
    c_eq = p.spool_damping_n_s_m + p.spool_end_area_m2 ** 2 * gpf / gqf
    for k in range(n_steps):
        old = dict(s)
        s['play'] = play(old['play'], i_cmd, p.hysteresis_a)
        i = min(max(s['play'] + p.offset_a + noise[k], -p.current_limit_a), p.current_limit_a)
        f = torque_force(p, i, old['xf'])
        q1l, q2l = valve_flows(p, old['xs'], old['p1'], old['p2'])
        q1l, q2l = float(q1l), float(q2l)
        s['qj'] = 0.5 * (q1l + q2l)
        # spool (massless, Borello) driven by the old flapper position and this step's flow
        fs = p.spool_end_area_m2 * gpf * old['xf'] - p.flow_force_coeff_n_s_m3 * s['qj']
        s['vs'] = borello_massless(old['vs'], fs, p.spool_static_friction_n,
                                   p.spool_dynamic_friction_n, c_eq)
        s['xs'] = old['xs'] + s['vs'] * dt
        if abs(s['xs']) > p.spool_stroke_m:
            s['xs'] = math.copysign(p.spool_stroke_m, s['xs'])
            s['vs'] = 0.0
        # flapper, semi-implicit
        u = old['xf'] + old['xs']
        hb = p.feedback_backlash_m / 2
        dz = u - hb if u > hb else (u + hb if u < -hb else 0.0)
        acc = (f - cf * old['vf'] - p.flapper_stiffness_n_m * old['xf']
               - p.feedback_spring_stiffness_n_m * dz) / p.flapper_mass_kg
        s['vf'] = old['vf'] + acc * dt
        s['xf'] = old['xf'] + s['vf'] * dt
        if abs(s['xf']) > p.flapper_stroke_m:
            s['xf'] = math.copysign(p.flapper_stroke_m, s['xf'])
            if s['vf'] * s['xf'] > 0:
                s['vf'] = 0.0
        # jack, semi-implicit, Borello
        p12 = old['p1'] - old['p2']
        fj = (p12 * p.jack_area_m2 - p.jack_viscous_n_s_m * old['vj']
              - p.aero_stiffness_n_m * old['xj'] - p.external_force_n)
        vj_old = old['vj']
        if vj_old == 0.0:
            s['vj'] = 0.0 if abs(fj) <= p.jack_static_friction_n else (
                fj - p.jack_static_friction_n * np.sign(fj)) / p.jack_mass_kg * dt
        else:
            vn = vj_old + (fj - p.jack_dynamic_friction_n * np.sign(vj_old)) / p.jack_mass_kg * dt
            s['vj'] = 0.0 if vn * vj_old < 0 else vn
        s['xj'] = old['xj'] + s['vj'] * dt
        if abs(s['xj']) > p.jack_stroke_m:
            s['xj'] = math.copysign(p.jack_stroke_m, s['xj'])
            if s['vj'] * s['xj'] > 0:
                s['vj'] = 0.0
        # chambers from the old jack velocity and pressures
        qm = p.jack_area_m2 * vj_old + p.leakage_coeff_m3_s_pa * p12
        kv = p.bulk_modulus_pa / p.chamber_volume_m3
        s['p1t'] = old['p1t'] + (q1l - qm) * kv * dt
        s['p2t'] = old['p2t'] + (qm - q2l) * kv * dt
        s['p1'] = max(p.vapour_pressure_pa, s['p1t'])
        s['p2'] = max(p.vapour_pressure_pa, s['p2t'])
        s['surf'] = play(old['surf'], s['xj'], p.surface_backlash_m / 2)
    return s


def map_transient(p, xs, q, n_steps, dt):
    """Vectorised numpy version of the map transient (pressures from zero)."""
    p1t = np.zeros_like(xs, dtype=float)
    p2t = np.zeros_like(xs, dtype=float)
    kv = p.bulk_modulus_pa / p.map_volume_m3
    for _ in range(n_steps):
        p1 = np.maximum(p.vapour_pressure_pa, p1t)
        p2 = np.maximum(p.vapour_pressure_pa, p2t)
        q1l, q2l = valve_flows(p, xs, p1, p2)
        qm = q + p.leakage_coeff_m3_s_pa * (p1 - p2)
        p1t = p1t + (q1l - qm) * kv * dt
        p2t = p2t + (qm - q2l) * kv * dt
    return np.maximum(p.vapour_pressure_pa, p1t) - np.maximum(p.vapour_pressure_pa, p2t)
