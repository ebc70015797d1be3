"""Mechanical model of the jack, its load and the position sensor.

``MJ XJ'' = P12 AJ - CJ XJ' - Kaer XJ - F_ext - FF`` with Borello friction ``FF``, end stops
``+-XJM`` that null the velocity, a play (backlash) between jack and surface and a quantised
position sensor on the surface.
"""

from __future__ import annotations

import math

from numba import njit

from .friction import borello_mass
from .servovalve import end_stops, play

__all__ = ['jack_step', 'jack_step_trapezoid', 'surface_position', 'quantise']


@njit(cache=True, inline='always')
def jack_step(xj, vj, p12_pa, p, dt):
    """One step of the jack; returns (XJ, VJ)."""
    f = (p12_pa * p.jack_area_m2 - p.jack_viscous_n_s_m * vj - p.aero_stiffness_n_m * xj
         - p.external_force_n)
    vj, _, _ = borello_mass(vj, f, p.jack_static_friction_n, p.jack_dynamic_friction_n,
                            p.jack_mass_kg, dt)
    xj = xj + vj * dt
    return end_stops(xj, vj, p.jack_stroke_m)


@njit(cache=True, inline='always')
def jack_step_trapezoid(xj, vj, p12_pa, p, dt):
    """:func:`jack_step` as the kick of a position-Verlet (leapfrog) step: the spring force at
    the mid-step position ``XJ + VJ dt/2``, the position advanced by the mean of the
    velocities at the two ends of the step (so a harmonic swing keeps its energy, and a slide
    that stops within the step, at its end, keeps its displacement); ``p12_pa`` is the load
    pressure at mid-step.  Returns (XJ, VJ)."""
    v0 = vj
    f = (p12_pa * p.jack_area_m2 - p.jack_viscous_n_s_m * vj
         - p.aero_stiffness_n_m * (xj + 0.5 * dt * vj) - p.external_force_n)
    vj, _, _ = borello_mass(vj, f, p.jack_static_friction_n, p.jack_dynamic_friction_n,
                            p.jack_mass_kg, dt)
    xj = xj + 0.5 * (v0 + vj) * dt
    return end_stops(xj, vj, p.jack_stroke_m)


@njit(cache=True, inline='always')
def surface_position(surface_prev, xj, p):
    """Surface position behind the jack-to-surface play."""
    return play(surface_prev, xj, 0.5 * p.surface_backlash_m)


@njit(cache=True, inline='always')
def quantise(x, q):
    """Sensor reading: ``x`` rounded to the nearest multiple of ``q`` (``q = 0``: exact)."""
    if q <= 0.0:
        return x
    return q * math.floor(x * (1.0 / q) + 0.5)
