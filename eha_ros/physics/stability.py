"""Stability of the explicit plant step: the largest stable step of each block, and the checks
of a step against them and against the ROS clock's resolution.

Named ``stability`` for the analysis it holds; each bound is a :class:`Limit` with a key, so
a surrogate's bound replaces the chamber bound by key (:data:`CHAMBER`).
"""

from __future__ import annotations

import math
from collections import namedtuple

from .loop import FluidBlock
from .params import ParameterError, PlantParams
from .servovalve import magnetic_stiffness, spool_gains
from .valve import fluid_constants, orifice_flow, valve_coefficients, valve_constants

__all__ = ['Limit', 'FLAPPER', 'JACK_SPRING', 'JACK_VISCOUS', 'CHAMBER', 'SPOOL', 'FLUID',
           'stability_limits', 'stability_limit', 'dt_to_ns', 'check_dt', 'EXPLICIT', 'SPLIT',
           'INTEGRATORS', 'SUBSTEP_S', 'integrator_substeps', 'DT_S']

#: The plant's step [s] by default: the reference's fixed step, the explicit scheme's
#: yardstick (within its stability bounds at nominal parameters, :func:`stability_limits`).
DT_S = 1e-6

#: Keys of the bounds (:attr:`Limit.key`); ``FLUID`` is a surrogate's, in place of ``CHAMBER``.
FLAPPER, JACK_SPRING, JACK_VISCOUS, CHAMBER, SPOOL, FLUID = (
    'flapper', 'jack_spring', 'jack_viscous', 'chamber', 'spool', 'fluid')


#: The largest stable step ``dt_s`` [s] of the block ``key``, with the ``reason`` that error
#: messages name.
Limit = namedtuple('Limit', 'key dt_s reason')


def _edge_conductance_max(p: PlantParams) -> float:
    """Largest flow conductance dQ/dp [m^3/(s Pa)] of one chamber, over the spool stroke."""
    worst = 0.0
    dp_ref = (0.0 if fluid_constants(p).reynolds
              else 1e-3 * (p.supply_pressure_pa - p.return_pressure_pa))
    for xs in (-p.spool_stroke_m, 0.0, p.spool_stroke_m):
        co = valve_coefficients(xs, valve_constants(p))
        for e in range(4):
            rl, bl, r4 = co[3 * e], co[3 * e + 1], co[3 * e + 2]
            dp = max(dp_ref, 1.0)
            g_e = orifice_flow(dp, rl, bl, r4) / dp if dp_ref else 2.0 / (
                rl + math.sqrt(rl * rl + bl + r4 * dp))
            worst = max(worst, 2.0 * g_e)
    return worst


def stability_limits(p: PlantParams, fluid: FluidBlock | None = None,
                     integrator: str = 'explicit') -> list[Limit]:
    """Per block, the largest stable step [s] of its linearisation under the explicit scheme.

    With the ``split`` integrator the chambers are linearly implicit and set no bound.  With a
    surrogate ``fluid`` the chamber bound is replaced by the surrogate's own feedback
    bound (``fluid.stability_limit(p)``, key :data:`FLUID`): for an algebraic ``P12(XS, Q)``
    the jack sees ``AJ^2 dP12/dQ`` as a damper, for a dynamic one its flows' conductance sets
    the chamber bound as the valve's does.

    The semi-implicit Euler oscillator ``w dt < min(1/zeta, 2 (sqrt(zeta^2 + 1) - zeta))`` for
    the first stage, ``w dt < 2`` for the jack on its hydraulic spring, ``dt < 2 tau`` for the
    chamber pressures (largest valve conductance: full stroke, vanishing drop), the massless
    spool and the jack's viscous decay.  The chamber bound is conservative: the orifice
    conductance falls as the drop grows, so beyond it the pressures chatter before they
    diverge.
    """
    limits = []
    k_m = magnetic_stiffness(p) if p.torque_motor_model == 1.0 else 0.0
    k_f = p.flapper_stiffness_n_m + p.feedback_spring_stiffness_n_m - k_m
    if k_f <= 0:
        raise ParameterError('parameter flapper_stiffness_n_m must exceed the magnetic '
                             f'negative stiffness {k_m:.4g} N/m less the feedback spring')
    w_f = math.sqrt(k_f / p.flapper_mass_kg)
    z_f = p.flapper_damping_ratio * math.sqrt(
        (p.flapper_stiffness_n_m + p.feedback_spring_stiffness_n_m) / k_f)
    limits.append(Limit(FLAPPER, min(1.0 / z_f, 2.0 * (math.sqrt(z_f ** 2 + 1) - z_f)) / w_f,
                        'first stage (flapper) oscillator'))
    k_h = 2.0 * p.bulk_modulus_pa * p.jack_area_m2 ** 2 / p.chamber_volume_m3
    w_h = math.sqrt((k_h + p.aero_stiffness_n_m) / p.jack_mass_kg)
    limits.append(Limit(JACK_SPRING, 2.0 / w_h, 'jack hydraulic spring'))
    if p.jack_viscous_n_s_m > 0:
        limits.append(Limit(JACK_VISCOUS, 2.0 * p.jack_mass_kg / p.jack_viscous_n_s_m,
                            'jack viscous damping'))
    g = _edge_conductance_max(p)
    limits.append(Limit(CHAMBER, 2.0 * p.chamber_volume_m3 / (p.bulk_modulus_pa * g),
                        'chamber pressures (Bet/Vol x valve conductance)'))
    drive, c_eq = spool_gains(p)
    if drive > 0 and c_eq > 0:
        # quasi-static flapper: XS' = drive/c_eq * (F - KSF XS)/(KF + KSF)
        rate = drive / c_eq * p.feedback_spring_stiffness_n_m / k_f
        limits.append(Limit(SPOOL, 2.0 / rate, 'second stage (spool) lag'))
    if fluid is not None:
        limits = [x for x in limits if x.key != CHAMBER]
        limits.append(Limit(FLUID, *fluid.stability_limit(p)))
    elif integrator != EXPLICIT:  # the chambers are linearly implicit: no bound of their own
        limits = [x for x in limits if x.key != CHAMBER]
    return limits


def stability_limit(p: PlantParams, fluid: FluidBlock | None = None,
                    integrator: str = 'explicit') -> Limit:
    """The smallest of :func:`stability_limits`: the largest stable plant step and the block
    that sets it."""
    return min(stability_limits(p, fluid, integrator), key=lambda x: x.dt_s)


#: The plant's integrators (:func:`.loop.advance`): ``explicit``, the reference's scheme and the
#: default; ``split``, the jack and its chambers as a Stormer-Verlet pair with linearly
#: implicit pressures, every step that holds an event it cannot place taken again in
#: substeps of :data:`SUBSTEP_S`.
EXPLICIT, SPLIT = 'explicit', 'split'
INTEGRATORS = (EXPLICIT, SPLIT)
#: The substep of ``split`` [s]: the reference's step, 1 us, so that a friction transition or
#: an end stop falls on the grid the reference places it on.
SUBSTEP_S = 1e-6


def integrator_substeps(integrator: str, dt_s: float) -> int:
    """``Clock.substeps`` of ``integrator`` at a step of ``dt_s``: 0 for ``explicit``; for
    ``split`` the number of substeps of :data:`SUBSTEP_S` in a step (1 at 1 us and below,
    where a step is its own substep).  Refuses an unknown name, or a ``split`` step above
    1 us that is not a whole number of substeps."""
    if integrator == EXPLICIT:
        return 0
    if integrator != SPLIT:
        raise ParameterError(f'integrator {integrator!r} is not one of {", ".join(INTEGRATORS)}')
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise ParameterError(f'dt_s = {dt_s} must be a positive number of seconds')
    m = round(dt_s / SUBSTEP_S)
    if dt_s <= SUBSTEP_S:
        return 1
    if abs(m * SUBSTEP_S - dt_s) > 1e-9 * dt_s:
        raise ParameterError(f'integrator {SPLIT}: dt_s = {dt_s:g} s must be a whole number of '
                             f'its {SUBSTEP_S:g} s substeps')
    return int(m)


def dt_to_ns(dt_s: float) -> int:
    """The step as a whole number of nanoseconds (ROS time resolution); refuses others."""
    dt_ns = int(round(dt_s * 1e9))
    if dt_ns < 1 or abs(dt_ns * 1e-9 - dt_s) > 1e-6 * dt_s:
        raise ParameterError(f'dt_s = {dt_s:g} s must be a whole number of nanoseconds')
    return dt_ns


def check_dt(p: PlantParams, dt_s: float, fluid: FluidBlock | None = None,
             integrator: str = 'explicit') -> None:
    """Refuse a non-positive step or one beyond the stability limit, with the bound of what
    a surrogate ``fluid`` feeds back in place of the chamber bound (:func:`stability_limits`)."""
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise ParameterError(f'dt_s = {dt_s} must be a positive number of seconds')
    dt_to_ns(dt_s)
    lim = stability_limit(p, fluid, integrator)
    if dt_s > lim.dt_s:
        raise ParameterError(f'dt_s = {dt_s:g} s exceeds the stability limit {lim.dt_s:.3g} s '
                             f'set by the {lim.reason}')
