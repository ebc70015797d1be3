"""Fluid-dynamic model of the servovalve's second stage (metering edges and outlet chambers).

Four metering edges connect supply S and return R to the outlets 1 and 2.  Each edge is an
annular passage: while the spool covers it (displacement inside the overlap) fluid leaks
through the radial clearance ``c`` over the covered length ``X0`` (laminar resistance ``RL``)
and through the annulus ``w*c`` (quadratic resistance ``RQ``); once uncovered, the passage
is the truncated cone ``w*sqrt(c^2 + x^2)`` with ``RL = 0``::

    RL = 12 mu X0 / (w c^3 (1 + 1.5 (e/c)^2))          RQ = rho / (2 Cd^2 A^2)
    dp = RL Q + RQ Q |Q|   =>   Q = 2 dp / (RL + sqrt(RL^2 + 4 RQ |dp|))

The last form is the root of the quadratic written so that it loses no digits when
``RL^2 >> 4 RQ |dp|`` (covered edges).

Discharge coefficient.  ``cd_model = constant``: ``Cd = Cd_inf``.  ``cd_model = reynolds``:
``Cd = Cd_inf * x / sqrt(1 + x^2)`` with ``x = 2 lambda / lambda_crit`` and the flow number
``lambda = (D_h / nu) sqrt(2 |dp| / rho)``, ``D_h = 2 h`` the hydraulic diameter of the gap
``h``.  It has the laminar (``Cd ~ lambda``) and turbulent (``Cd -> Cd_inf``) limits of the
usual ``tanh`` law and lets ``4 RQ |dp|`` be written without ``Cd``::

    4 RQ |dp| = B_lam + R4 |dp|,   R4 = 2 rho / (Cd_inf^2 A^2),
                                   B_lam = mu^2 lambda_crit^2 / (16 Cd_inf^2 w^2 h^4)

so one square root gives the flow in either model (``B_lam = 0`` for a constant Cd).
``valve_degradation`` (Khsv) scales ``Cd_inf`` by ``1 - Khsv`` (silted metering edges).

Chambers.  ``dP1T/dt = (Q1L - QM) Bet/Vol``, ``dP2T/dt = (QM - Q2L) Bet/Vol`` with
``Q1L = Q1S - Q1R`` (net into 1), ``Q2L = Q2R - Q2S`` (net out of 2) and
``QM = AJ dXJ/dt + Clk (P1 - P2)``.  Cavitation: ``P = max(PVap, PT)``; the unclipped
``PT`` keeps the memory of the vapour volume, as in the reference.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

__all__ = ['FluidConstants', 'fluid_constants', 'edge_constants', 'valve_constants', 'net_flow',
           'edge_coefficients', 'orifice_flow', 'valve_coefficients', 'valve_flows',
           'chamber_step', 'chamber_step_implicit', 'edge_conductance',
           'net_flow_conductance', 'orifice_pressure_drop', 'steady_pressures',
           'steady_pressures_rtol']

_TINY = 1e-300


#: The wear-independent constants of the metering edges, as :func:`edge_constants` takes them
#: after the clearance and laps: ``cd_eff = Cd_inf (1 - Khsv)``, ``mu_pa_s = rho nu``,
#: ``reynolds`` the Reynolds-dependent Cd (``cd_model``).
FluidConstants = namedtuple('FluidConstants', 'port_width_m cd_eff mu_pa_s rho_kg_m3 '
                            'eccentricity critical_flow_number reynolds')


@njit(cache=True, inline='always')
def fluid_constants(p):
    """:class:`FluidConstants` of the parameters ``p``: their one derivation, for every
    caller of :func:`edge_constants`."""
    return FluidConstants(p.port_width_m, p.discharge_coefficient * (1.0 - p.valve_degradation),
                          p.fluid_density_kg_m3 * p.fluid_kinematic_viscosity_m2_s,
                          p.fluid_density_kg_m3, p.eccentricity_ratio, p.critical_flow_number,
                          p.cd_model == 0.0)


@njit(cache=True, inline='always')
def edge_constants(clearance_m, lap_supply_m, lap_return_m, port_width_m, cd_eff, mu_pa_s,
                   rho_kg_m3, eccentricity, critical_flow_number, reynolds):
    """Spool-independent constants of the metering edges for one clearance and pair of laps:
    ``(c^2, k_rl, k_r4, k_bl, OSSV, ORSV)`` with ``RL = k_rl X0``, ``R4 = k_r4 / h^2`` and
    ``B_lam = k_bl / h^4`` (``k_bl = 0`` unless ``reynolds``); ``cd_eff`` includes Khsv."""
    c = clearance_m
    w = port_width_m
    k_rl = 12.0 * mu_pa_s / (w * c * c * c * (1.0 + 1.5 * eccentricity * eccentricity))
    k_r4 = 2.0 * rho_kg_m3 / (cd_eff * cd_eff * w * w)
    if reynolds:
        lc = critical_flow_number
        k_bl = mu_pa_s * mu_pa_s * lc * lc / (16.0 * cd_eff * cd_eff * w * w)
    else:
        k_bl = 0.0
    return c * c, k_rl, k_r4, k_bl, lap_supply_m, lap_return_m


@njit(cache=True, inline='always')
def valve_constants(p):
    """Spool-independent constants of the metering edges (:func:`edge_constants` at the
    parameters' clearance and laps), computed once per run."""
    w, cd, mu, rho, ecc, lc, reynolds = fluid_constants(p)
    return edge_constants(p.radial_clearance_m, p.overlap_supply_m, p.overlap_return_m, w, cd,
                          mu, rho, ecc, lc, reynolds)


@njit(cache=True, inline='always')
def edge_coefficients(opening_m, vc):
    """(RL, B_lam, R4) of one metering edge; ``vc`` from :func:`valve_constants`.

    ``opening_m`` is how far the spool has passed the edge's lap: > 0 open, <= 0 covered
    (the covered length is ``-opening_m``).
    """
    c2, k_rl, k_r4, k_bl = vc[0], vc[1], vc[2], vc[3]
    if opening_m > 0.0:
        rl = 0.0
        g = 1.0 / (c2 + opening_m * opening_m)
    else:
        rl = -k_rl * opening_m
        g = 1.0 / c2
    return rl, k_bl * g * g, k_r4 * g


@njit(cache=True, inline='always')
def orifice_flow(dp_pa, rl, blam, r4):
    """Flow [m^3/s] through an edge for a pressure drop ``dp_pa`` (same sign as ``dp_pa``)."""
    den = rl + math.sqrt(rl * rl + blam + r4 * abs(dp_pa))
    return 2.0 * dp_pa / max(den, _TINY)


@njit(cache=True, inline='always')
def edge_conductance(dp_pa, rl, blam, r4):
    """``d orifice_flow / d dp_pa`` [m^3/(s Pa)] of one edge at the drop ``dp_pa``: with ``S =
    sqrt(RL^2 + B_lam + R4 |dp|)`` and ``D = RL + S``, ``2/D - R4 |dp| / (S D^2)`` (positive;
    unbounded only for an open edge under a constant Cd at a vanishing drop)."""
    adp = abs(dp_pa)
    sq = max(math.sqrt(rl * rl + blam + r4 * adp), _TINY)
    den = rl + sq
    return 2.0 / den - (r4 * adp / sq / den / den if adp > 0.0 else 0.0)


@njit(cache=True, inline='always')
def net_flow_conductance(dp_in, rl_in, bl_in, r4_in, dp_out, rl_out, bl_out, r4_out):
    """``(net flow, conductance)``: the net flow of :func:`net_flow` (to rounding) and the sum
    of the two edges' :func:`edge_conductance`, sharing their square roots."""
    a_in = abs(dp_in)
    a_out = abs(dp_out)
    s_in = max(math.sqrt(rl_in * rl_in + bl_in + r4_in * a_in), _TINY)
    s_out = max(math.sqrt(rl_out * rl_out + bl_out + r4_out * a_out), _TINY)
    d_in = rl_in + s_in
    d_out = rl_out + s_out
    q = 2.0 * (dp_in / d_in - dp_out / d_out)
    g = 2.0 / d_in + 2.0 / d_out  # less the drops' share of the square roots
    if a_in > 0.0:
        g -= r4_in * a_in / s_in / d_in / d_in
    if a_out > 0.0:
        g -= r4_out * a_out / s_out / d_out / d_out
    return q, g


@njit(cache=True, inline='always')
def net_flow(dp_in, rl_in, bl_in, r4_in, dp_out, rl_out, bl_out, r4_out):
    """``orifice_flow(dp_in, ...) - orifice_flow(dp_out, ...)`` with a single division."""
    d_in = max(rl_in + math.sqrt(rl_in * rl_in + bl_in + r4_in * abs(dp_in)), _TINY)
    d_out = max(rl_out + math.sqrt(rl_out * rl_out + bl_out + r4_out * abs(dp_out)), _TINY)
    return 2.0 * (dp_in * d_out - dp_out * d_in) / (d_in * d_out)


def orifice_pressure_drop(q_m3_s, dp_pa, rl, blam, r4):
    """Pressure drop ``RL Q + RQ Q|Q|`` with ``RQ`` evaluated at the drop ``dp_pa``.

    With the Reynolds-dependent Cd, ``RQ`` depends on the drop itself; passing the drop that
    produced ``q_m3_s`` makes this the exact inverse of :func:`orifice_flow`.
    """
    adp = np.abs(dp_pa)
    with np.errstate(divide='ignore', invalid='ignore'):
        rq = np.where(adp > 0, (blam / np.where(adp > 0, adp, 1.0) + r4) / 4.0, r4 / 4.0)
    return rl * q_m3_s + rq * q_m3_s * np.abs(q_m3_s)


@njit(cache=True, inline='always')
def valve_coefficients(xs_m, vc):
    """Edge coefficients of the four edges 1S, 1R, 2S, 2R at spool position ``xs_m``."""
    oss = vc[4]
    ors = vc[5]
    rl1s, bl1s, r41s = edge_coefficients(xs_m - oss, vc)
    rl1r, bl1r, r41r = edge_coefficients(-xs_m - ors, vc)
    rl2s, bl2s, r42s = edge_coefficients(-xs_m - oss, vc)
    rl2r, bl2r, r42r = edge_coefficients(xs_m - ors, vc)
    return (rl1s, bl1s, r41s, rl1r, bl1r, r41r, rl2s, bl2s, r42s, rl2r, bl2r, r42r)


@njit(cache=True, inline='always')
def valve_flows(xs_m, p1_pa, p2_pa, p):
    """(Q1L, Q2L) [m^3/s]: net flow into outlet 1 and net flow out of outlet 2."""
    (rl1s, bl1s, r41s, rl1r, bl1r, r41r,
     rl2s, bl2s, r42s, rl2r, bl2r, r42r) = valve_coefficients(xs_m, valve_constants(p))
    ps = p.supply_pressure_pa
    pr = p.return_pressure_pa
    q1s = orifice_flow(ps - p1_pa, rl1s, bl1s, r41s)
    q1r = orifice_flow(p1_pa - pr, rl1r, bl1r, r41r)
    q2s = orifice_flow(ps - p2_pa, rl2s, bl2s, r42s)
    q2r = orifice_flow(p2_pa - pr, rl2r, bl2r, r42r)
    return q1s - q1r, q2r - q2s


@njit(cache=True, inline='always')
def chamber_step(p1t, p2t, q1l, q2l, qm, stiffness_pa_m3, pvap_pa, dt):
    """Advance the unclipped chamber pressures; return (P1T, P2T, P1, P2).

    ``stiffness_pa_m3`` is ``Bet/Vol``; P1, P2 are clipped at the vapour pressure.
    """
    p1t = p1t + (q1l - qm) * stiffness_pa_m3 * dt
    p2t = p2t + (qm - q2l) * stiffness_pa_m3 * dt
    return p1t, p2t, max(pvap_pa, p1t), max(pvap_pa, p2t)


@njit(cache=True, inline='always')
def chamber_step_implicit(p1t, p2t, q1l, q2l, qm, stiffness_pa_m3, pvap_pa, dt, rate1, rate2):
    """:func:`chamber_step` linearly implicit in each chamber's own pressure: ``rate1``,
    ``rate2`` [1/s] are ``-d(dPkT/dt)/dPk`` (Bet/Vol times the chamber's valve conductance and
    the leakage), and each increment is divided by ``1 + dt rate`` (Rosenbrock-Euler on the
    diagonal: exact for a chamber relaxing linearly, stable at any step)."""
    p1t = p1t + (q1l - qm) * stiffness_pa_m3 * dt / (1.0 + dt * rate1)
    p2t = p2t + (qm - q2l) * stiffness_pa_m3 * dt / (1.0 + dt * rate2)
    return p1t, p2t, max(pvap_pa, p1t), max(pvap_pa, p2t)


# --- steady state -------------------------------------------------------------------------------

@njit(cache=True, inline='always')
def _side_flow(k, pk, co, ps, pr):
    """Q1L (``k = 0``) at P1 = ``pk`` or Q2L (``k = 1``) at P2 = ``pk``, from the edge
    coefficients ``co`` of :func:`valve_coefficients` (as :func:`valve_flows`)."""
    if k == 0:
        return orifice_flow(ps - pk, co[0], co[1], co[2]) - orifice_flow(pk - pr, co[3], co[4],
                                                                         co[5])
    return orifice_flow(pk - pr, co[9], co[10], co[11]) - orifice_flow(ps - pk, co[6], co[7],
                                                                       co[8])


@njit(cache=True)
def _chamber_pressure(k, co, ps, pr, qm, lo, hi):
    """P1 (``k = 0``) with Q1L(P1) = qm (Q1L decreases with P1) or P2 (``k = 1``) with
    Q2L(P2) = qm (Q2L increases with P2), clipped at PVap; ``co``: the edge coefficients at
    the spool position."""
    sgn = 1.0 if k == 0 else -1.0
    if sgn * (_side_flow(k, lo, co, ps, pr) - qm) <= 0.0:
        return lo
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if sgn * (_side_flow(k, mid, co, ps, pr) - qm) > 0.0:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * max(1.0, abs(mid)):
            break
    return 0.5 * (lo + hi)


@njit(cache=True)
def steady_pressures(xs_m, q_m3_s, p, p_max_pa):
    """Steady (P1, P2) [Pa] for spool ``xs_m`` and imposed jack flow ``q_m3_s``.

    Solves ``Q1L(P1) = QM = Q2L(P2)`` with ``QM = q + Clk (P1 - P2)``.  For a given QM each
    chamber pressure is unique (each chamber's net inflow is monotonic in its pressure), and
    ``QM - q - Clk (P1(QM) - P2(QM))`` increases with QM, so nested bisections find the unique
    solution.  A chamber that would need a pressure below PVap sits at PVap (cavitating);
    pressures are searched up to ``p_max_pa``.  The edge coefficients at ``xs_m`` are
    computed once (the flows are those of :func:`valve_flows`, bit for bit).
    """
    lo_p = p.vapour_pressure_pa
    clk = p.leakage_coeff_m3_s_pa
    ps = p.supply_pressure_pa
    pr = p.return_pressure_pa
    co = valve_coefficients(xs_m, valve_constants(p))
    # bracket QM: flows achievable lie between the extremes of both chambers' curves
    qmin = min(_side_flow(0, p_max_pa, co, ps, pr), _side_flow(1, lo_p, co, ps, pr))
    qmax = max(_side_flow(0, lo_p, co, ps, pr), _side_flow(1, p_max_pa, co, ps, pr))
    qa = min(qmin, q_m3_s + clk * (lo_p - p_max_pa)) - 1e-12
    qb = max(qmax, q_m3_s + clk * (p_max_pa - lo_p)) + 1e-12
    p1 = lo_p
    p2 = lo_p
    for _ in range(200):
        qm = 0.5 * (qa + qb)
        p1 = _chamber_pressure(0, co, ps, pr, qm, lo_p, p_max_pa)
        p2 = _chamber_pressure(1, co, ps, pr, qm, lo_p, p_max_pa)
        r = qm - q_m3_s - clk * (p1 - p2)
        if r > 0.0:
            qb = qm
        else:
            qa = qm
        if qb - qa <= 1e-16 + 1e-13 * abs(qm):
            break
    return p1, p2


@njit(cache=True, inline='always')
def _illinois_point(a, fa, b, fb, slow):
    """The next point of an Illinois search on the bracket ``[a, b]`` with ``fa < 0 < fb``:
    the secant's root, or the midpoint after ``slow >= 3`` steps that did not halve the
    bracket (or where the secant leaves it); returns (point, slow)."""
    if slow >= 3 or not fa < 0.0 < fb:
        return 0.5 * (a + b), 0
    c = (a * fb - b * fa) / (fb - fa)
    if not a < c < b:
        c = 0.5 * (a + b)
    return c, slow


@njit(cache=True, inline='always')
def _illinois_update(a, fa, b, fb, c, fc, side, width, slow):
    """The bracket after the value ``fc`` at ``c``: the end of ``fc``'s sign moves to ``c``,
    and the other end's value is halved when the same end moves twice in a row; ``slow``
    counts the steps since the bracket last halved.  Returns (a, fa, b, fb, side, width,
    slow, found), ``found`` where ``fc`` is 0."""
    if fc < 0.0:
        a, fa = c, fc
        if side == -1:
            fb *= 0.5
        side = -1
    elif fc > 0.0:
        b, fb = c, fc
        if side == 1:
            fa *= 0.5
        side = 1
    else:
        return a, fa, b, fb, side, width, slow, True
    if b - a > 0.5 * width:
        slow += 1
    else:
        width, slow = b - a, 0
    return a, fa, b, fb, side, width, slow, False


@njit(cache=True)
def _chamber_pressure_rtol(k, co, ps, pr, qm, lo, hi, rtol):
    """:func:`_chamber_pressure` by the Illinois method (a bracketing secant whose stale end
    is halved; a bisection step wherever the bracket fails to halve in three steps), to a
    bracket of ``rtol`` of the pressure."""
    sgn = 1.0 if k == 0 else -1.0
    # g(P) = sgn (qm - flow(P)) increases with P
    fa = sgn * (qm - _side_flow(k, lo, co, ps, pr))
    if fa >= 0.0:
        return lo
    fb = sgn * (qm - _side_flow(k, hi, co, ps, pr))
    if fb <= 0.0:
        return hi
    a, b = lo, hi
    side, width, slow = 0, b - a, 0
    c = a
    for _ in range(200):
        c, slow = _illinois_point(a, fa, b, fb, slow)
        fc = sgn * (qm - _side_flow(k, c, co, ps, pr))
        a, fa, b, fb, side, width, slow, found = _illinois_update(a, fa, b, fb, c, fc, side,
                                                                  width, slow)
        if found or b - a <= rtol * max(1.0, abs(c)):
            break
    return c


@njit(cache=True)
def steady_pressures_rtol(xs_m, q_m3_s, p, p_max_pa, rtol):
    """:func:`steady_pressures` to a relative tolerance ``rtol`` (of the pressures, and of
    the metered flow), by the Illinois method at both levels: the same solution, found in a
    tenth of the flow evaluations, for the estimators that need many maps and no more than
    ``rtol``.  Each chamber pressure is monotonic in the metered flow, so the search stops
    once the pressures at both ends of the flow bracket agree to ``rtol``, not the flow
    alone: where an edge drops much more than a chamber's pressure (a saturated point), a
    flow to ``rtol`` leaves that pressure off by ``2 dp / p`` times as much."""
    lo_p = p.vapour_pressure_pa
    clk = p.leakage_coeff_m3_s_pa
    ps = p.supply_pressure_pa
    pr = p.return_pressure_pa
    co = valve_coefficients(xs_m, valve_constants(p))
    qmin = min(_side_flow(0, p_max_pa, co, ps, pr), _side_flow(1, lo_p, co, ps, pr))
    qmax = max(_side_flow(0, lo_p, co, ps, pr), _side_flow(1, p_max_pa, co, ps, pr))
    a = min(qmin, q_m3_s + clk * (lo_p - p_max_pa)) - 1e-12
    b = max(qmax, q_m3_s + clk * (p_max_pa - lo_p)) + 1e-12
    # r(qm) = qm - q - clk (P1(qm) - P2(qm)) increases with qm: r(a) < 0 < r(b)
    pa1 = _chamber_pressure_rtol(0, co, ps, pr, a, lo_p, p_max_pa, 0.1 * rtol)
    pa2 = _chamber_pressure_rtol(1, co, ps, pr, a, lo_p, p_max_pa, 0.1 * rtol)
    pb1 = _chamber_pressure_rtol(0, co, ps, pr, b, lo_p, p_max_pa, 0.1 * rtol)
    pb2 = _chamber_pressure_rtol(1, co, ps, pr, b, lo_p, p_max_pa, 0.1 * rtol)
    fa = a - q_m3_s - clk * (pa1 - pa2)
    fb = b - q_m3_s - clk * (pb1 - pb2)
    p1, p2 = pa1, pa2
    side, width, slow = 0, b - a, 0
    for _ in range(200):
        qm, slow = _illinois_point(a, fa, b, fb, slow)
        p1 = _chamber_pressure_rtol(0, co, ps, pr, qm, lo_p, p_max_pa, 0.1 * rtol)
        p2 = _chamber_pressure_rtol(1, co, ps, pr, qm, lo_p, p_max_pa, 0.1 * rtol)
        r = qm - q_m3_s - clk * (p1 - p2)
        a, fa, b, fb, side, width, slow, found = _illinois_update(a, fa, b, fb, qm, r, side,
                                                                  width, slow)
        if r < 0.0:
            pa1, pa2 = p1, p2
        elif r > 0.0:
            pb1, pb2 = p1, p2
        if found or b - a <= 1e-16 + 1e-13 * abs(qm):  # or at the bisection's own stop
            break
        if (b - a <= rtol * abs(qm) and abs(pb1 - pa1) <= rtol * max(1.0, abs(p1))
                and abs(pb2 - pa2) <= rtol * max(1.0, abs(p2))):
            break
    return p1, p2
