"""Borello's friction model for a body with mass and for a massless (first-order) body.

The model tells apart the four kinematic cases without a velocity dead band:

* stuck      ``v = 0`` and ``|F| <= FS``: friction balances the active force, the body stays;
* breakaway  ``v = 0`` and ``|F| > FS``: friction ``FS sign(F)`` and the body starts;
* sliding    ``v != 0``: friction ``FD sign(v)``;
* stopping   the velocity would change sign within the step: it is set to exactly zero, and
  the next step decides between stuck and breakaway.

Friction is positive when it opposes positive motion.  The kernels return status codes, not
exceptions, and draw no random numbers.
"""

from __future__ import annotations

from numba import njit

__all__ = ['borello_mass', 'borello_massless', 'STUCK', 'BREAKAWAY', 'SLIDING', 'STOPPING']

STUCK, BREAKAWAY, SLIDING, STOPPING = 0, 1, 2, 3


@njit(cache=True, inline='always')
def _sign(x):
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@njit(cache=True, inline='always')
def borello_mass(v, f_active, fs, fd, mass, dt):
    """One explicit step of ``m dv/dt = F - FF``.

    Returns ``(v_new, friction, case)``.
    """
    if v == 0.0:
        if abs(f_active) <= fs:
            return 0.0, f_active, STUCK
        ff = fs * _sign(f_active)
        return v + (f_active - ff) / mass * dt, ff, BREAKAWAY
    ff = fd * _sign(v)
    v_new = v + (f_active - ff) / mass * dt
    if v_new * v < 0.0:
        return 0.0, ff, STOPPING
    return v_new, ff, SLIDING


@njit(cache=True, inline='always')
def borello_massless(v_prev, f_active, fs, fd, c_eq):
    """Velocity of a massless body ``c_eq v = F - FF`` (the spool of the reference).

    ``v_prev`` is the velocity of the previous step.  Returns ``(v, friction, case)``.
    """
    if c_eq <= 0.0:
        return 0.0, f_active, STUCK
    if v_prev == 0.0:
        if abs(f_active) <= fs:
            return 0.0, f_active, STUCK
        ff = fs * _sign(f_active)
        return (f_active - ff) / c_eq, ff, BREAKAWAY
    ff = fd * _sign(v_prev)
    v = (f_active - ff) / c_eq
    if v * v_prev <= 0.0:
        return 0.0, ff, STOPPING
    return v, ff, SLIDING
