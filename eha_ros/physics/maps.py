"""Characteristic maps of the valve's fluid-dynamic block: P12 for given (XS, Q, overlap,
clearance).

Transient maps are obtained as the reference does (section 5.1): the spool is held at XS, the
jack flow Q is imposed (``QM = Q + Clk (P1 - P2)``), both chamber pressures start from zero and
the fluid-dynamic block is integrated for ``t_end`` (1e-2 s) at ``dt`` (1e-6 s) with the
capacity ``map_volume_m3``; P12 is read at the end.  Many points are integrated at once: blocks
of points are spread over the cores and, inside a block, the time loop runs over the points so
that the compiler vectorises it.

The steady-state solver (:func:`steady_map`) solves the same equations with the time
derivatives set to zero.  Where the valve is open the transient has settled long before 1e-2 s
and both agree; near null with a non-zero flow the chamber that the flow fills (or empties)
only reaches its balance through the tiny clearance leakage, its time constant is far longer
than 1e-2 s and the transient P12 is still on its way - it is the pressure peak "above supply
near null" of the reference's curves - while the steady solution may lie far beyond it (or at
the vapour pressure).  :func:`settling_mask` tells which points have settled.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit, prange

from .params import PlantParams, default_params, params_hash, replace
from .valve import (edge_constants, fluid_constants, net_flow, steady_pressures,
                    steady_pressures_rtol, valve_coefficients)

__all__ = ['WEAR_RANGES', 'FLUID_PARAMETERS', 'FLOW_MAX_M3_S', 'fluid_hash', 'spool_grid',
           'transient_map', 'transient_trace', 'stepped_trace', 'steady_map', 'MapResult',
           'settling_mask']

_BLOCK = 64

#: Ranges [m] of the wear parameters swept by the map databases (the nominal values of
#: ``config/eha_params.yaml`` lie inside): overlap (supply = return edges) and radial clearance.
WEAR_RANGES = {'overlap_m': (-2e-6, 6e-6), 'radial_clearance_m': (1e-6, 6e-6)}

#: Physics parameters the fluid-dynamic block (and so every map) depends on.  Overlap and
#: clearance are inputs of the maps and are left out.
FLUID_PARAMETERS = (
    'supply_pressure_pa', 'return_pressure_pa', 'vapour_pressure_pa', 'fluid_density_kg_m3',
    'fluid_kinematic_viscosity_m2_s', 'bulk_modulus_pa', 'port_width_m', 'eccentricity_ratio',
    'discharge_coefficient', 'cd_model', 'critical_flow_number', 'valve_degradation',
    'map_volume_m3', 'leakage_coeff_m3_s_pa', 'spool_stroke_m')

#: Flow range [m^3/s] of the maps: about 40 % of the valve's no-load flow at full stroke.
FLOW_MAX_M3_S = 6e-5


def fluid_hash(p: PlantParams) -> str:
    """Hash of the parameters the maps (and every artefact built from them) depend on."""
    return params_hash(p, FLUID_PARAMETERS)


def spool_grid(n: int = 133, stroke_m: float | None = None, density: float = 4.0,
               ) -> np.ndarray:
    """``n`` spool positions over ``+-stroke_m``, denser near null.

    ``x = stroke sinh(a u) / sinh(a)`` for ``u`` uniform in [-1, 1]: the spacing near null
    is ``a cosh(a)`` times (27x for the default ``a = 4``) finer than at the ends.  Odd ``n``
    includes ``x = 0``; the grid is antisymmetric.
    """
    if n < 2:
        raise ValueError('spool_grid needs at least 2 points')
    stroke = default_params().spool_stroke_m if stroke_m is None else float(stroke_m)
    u = np.linspace(-1.0, 1.0, n)
    x = stroke * np.sinh(density * u) / math.sinh(density)
    x[n // 2] = 0.0 if n % 2 else x[n // 2]
    return 0.5 * (x - x[::-1])  # exact antisymmetry


#: The points of a map transient, flat arrays of one length: spool position [m], imposed
#: flow [m^3/s], supply and return overlap [m], radial clearance [m].
MapPoints = namedtuple('MapPoints', 'xs q lap_s lap_r clr')
#: Its chamber pressures [Pa], flat arrays of the same length: the unclipped state the
#: integration goes on from (``raw_*``) and the clipped pressures it reports (``out_*``).
MapState = namedtuple('MapState', 'raw_p1 raw_p2 out_p1 out_p2')


@njit(cache=True, parallel=True)
def _transient_kernel(points, consts, n_steps, dt, state):
    """Integrate every point of ``points`` from the unclipped pressures of ``state`` (zero:
    the map transient) for ``n_steps`` steps of ``dt`` [s], with the valve's own edge
    equations (:mod:`.valve`); ``state`` then holds the unclipped pressures after, and the
    clipped ones.  Integrating in chunks from the raw state repeats the same steps bit for
    bit."""
    ps, pr, pvap, kvol, clk, w, cd, mu, rho, ecc, lc, reynolds = consts
    xs, q, lap_s, lap_r, clr = points
    raw_p1, raw_p2, out_p1, out_p2 = state
    n = xs.size
    n_blocks = (n + _BLOCK - 1) // _BLOCK
    for b in prange(n_blocks):
        i0 = b * _BLOCK
        m = min(_BLOCK, n - i0)
        # per point: (RL, B_lam, R4) of edges 1S, 1R, 2S, 2R
        co = np.empty((12, _BLOCK))
        qq = np.empty(_BLOCK)
        p1t = np.zeros(_BLOCK)
        p2t = np.zeros(_BLOCK)
        for j in range(m):
            i = i0 + j
            p1t[j] = raw_p1[i]
            p2t[j] = raw_p2[i]
            vc = edge_constants(clr[i], lap_s[i], lap_r[i], w, cd, mu, rho, ecc, lc,
                                reynolds != 0.0)
            e = valve_coefficients(xs[i], vc)
            for k in range(12):
                co[k, j] = e[k]
            qq[j] = q[i]
        for _ in range(n_steps):
            for j in range(m):
                p1 = max(pvap, p1t[j])
                p2 = max(pvap, p2t[j])
                q1l = net_flow(ps - p1, co[0, j], co[1, j], co[2, j],
                               p1 - pr, co[3, j], co[4, j], co[5, j])
                q2l = net_flow(p2 - pr, co[9, j], co[10, j], co[11, j],
                               ps - p2, co[6, j], co[7, j], co[8, j])
                qm = qq[j] + clk * (p1 - p2)
                p1t[j] += (q1l - qm) * kvol * dt
                p2t[j] += (qm - q2l) * kvol * dt
        for j in range(m):
            raw_p1[i0 + j] = p1t[j]
            raw_p2[i0 + j] = p2t[j]
            out_p1[i0 + j] = max(pvap, p1t[j])
            out_p2[i0 + j] = max(pvap, p2t[j])


def _consts(p: PlantParams) -> np.ndarray:
    return np.array([p.supply_pressure_pa, p.return_pressure_pa, p.vapour_pressure_pa,
                     p.bulk_modulus_pa / p.map_volume_m3, p.leakage_coeff_m3_s_pa,
                     *fluid_constants(p)], dtype=float)


class MapResult(dict):
    """``p1_pa``, ``p2_pa``, ``p12_pa`` arrays with the broadcast shape of the inputs."""


def _broadcast(xs, q, overlap, clearance, p):
    lap = p.overlap_supply_m if overlap is None else overlap
    clr = p.radial_clearance_m if clearance is None else clearance
    arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (xs, q, lap, clr)))
    shape = arrs[0].shape
    flat = [np.ascontiguousarray(a.ravel()) for a in arrs]
    if not np.all(flat[3] > 0):
        raise ValueError('radial clearance must be positive at every map point')
    for a, name in zip(flat, ('spool position', 'flow', 'overlap', 'clearance')):
        if not np.all(np.isfinite(a)):
            raise ValueError(f'{name} must be finite at every map point')
    return shape, flat


def transient_map(xs_m, q_m3_s, overlap_m=None, clearance_m=None, params=None,
                  t_end_s: float = 1e-2, dt_s: float = 1e-6) -> MapResult:
    """P1, P2, P12 after the reference's map transient, for broadcastable arrays of spool
    position [m], imposed flow [m^3/s], overlap [m] (supply = return edges) and clearance [m].

    ``overlap_m``/``clearance_m`` default to the parameters' values.
    """
    p = params if params is not None else default_params()
    shape, (xs, q, lap, clr) = _broadcast(xs_m, q_m3_s, overlap_m, clearance_m, p)
    n_steps = int(round(t_end_s / dt_s))
    if n_steps < 1:
        raise ValueError('t_end_s must cover at least one step of dt_s')
    p1 = np.empty(xs.size)
    p2 = np.empty(xs.size)
    _transient_kernel(MapPoints(xs, q, lap, lap, clr), _consts(p), n_steps, float(dt_s),
                      MapState(np.zeros(xs.size), np.zeros(xs.size), p1, p2))
    if not (np.all(np.isfinite(p1)) and np.all(np.isfinite(p2))):
        bad = int(np.flatnonzero(~(np.isfinite(p1) & np.isfinite(p2)))[0])
        raise FloatingPointError(
            f'map transient diverged at xs={xs[bad]:g} m, q={q[bad]:g} m^3/s, '
            f'overlap={lap[bad]:g} m, clearance={clr[bad]:g} m: reduce dt_s')
    return MapResult(p1_pa=p1.reshape(shape), p2_pa=p2.reshape(shape),
                     p12_pa=(p1 - p2).reshape(shape))


def transient_trace(xs_m, q_m3_s, n_ticks: int, steps_per_tick: int, params=None,
                    dt_s: float = 1e-6, first: int = 0, start_pa=None) -> tuple:
    """``(p1_pa, p2_pa)`` of the map transient at the end of ticks ``first .. n_ticks - 1``
    of ``steps_per_tick`` steps each, arrays ``(n_ticks - first,) + shape`` for broadcastable
    ``xs_m`` and ``q_m3_s``: row ``m - first`` equals :func:`transient_map` with
    ``t_end_s = (m + 1) steps_per_tick dt_s`` bit for bit (the first ``first`` ticks run as
    one chunk), at the cost of one transient.  ``start_pa``: ``(p1, p2)`` chamber pressures
    [Pa] the transient starts from, broadcast to the points (default zero, the map's)."""
    p = params if params is not None else default_params()
    shape, (xs, q, lap, clr) = _broadcast(xs_m, q_m3_s, None, None, p)
    consts = _consts(p)
    n = xs.size
    raw1, raw2 = np.zeros(n), np.zeros(n)
    if start_pa is not None:
        for raw, v in zip((raw1, raw2), start_pa):
            raw[:] = np.broadcast_to(np.asarray(v, dtype=float), shape).ravel()
        if not (np.all(np.isfinite(raw1)) and np.all(np.isfinite(raw2))):
            raise ValueError('the start pressures of a map transient must be finite')
    o1, o2 = np.empty(n), np.empty(n)
    p1, p2 = np.empty((n_ticks - first, n)), np.empty((n_ticks - first, n))
    points, state = MapPoints(xs, q, lap, lap, clr), MapState(raw1, raw2, o1, o2)
    if first:
        _transient_kernel(points, consts, int(steps_per_tick) * int(first), float(dt_s),
                          state)
    for m in range(n_ticks - first):
        _transient_kernel(points, consts, int(steps_per_tick), float(dt_s), state)
        p1[m], p2[m] = o1, o2
    if not (np.all(np.isfinite(p1)) and np.all(np.isfinite(p2))):
        raise FloatingPointError('map transient diverged: reduce dt_s')
    return (p1.reshape((n_ticks - first,) + shape), p2.reshape((n_ticks - first,) + shape))


def stepped_trace(xs_m, q_m3_s: float, n_ticks: int, steps_per_tick: int, params=None,
                  dt_s: float = 1e-6, first: int = 0, start_pa=(0.0, 0.0)) -> tuple:
    """``(p1_pa, p2_pa)``, arrays ``(n_ticks - first, len(xs_m))``, of a curve stepped point
    by point in the order of ``xs_m`` at one imposed flow, ``n_ticks`` ticks per point, as a
    bench steps the spool: each point's transient starts from the chamber pressures the one
    before ended at (the first from ``start_pa``, default zero).  Column ``j`` equals
    :func:`transient_trace` of point ``j`` started from the last row of column ``j - 1``
    bit for bit, so a plant that runs the points one at a time reads the same samples.

    From zero, the near-null points of a valve with little leakage take seconds to fill both
    chambers through the clearance; from their neighbour's pressures they settle within the
    hold (:data:`eha_ros.physics.maintenance.SETTLED_HOLD_S`)."""
    xs = np.asarray(xs_m, dtype=float).ravel()
    p1 = np.empty((n_ticks - first, xs.size))
    p2 = np.empty((n_ticks - first, xs.size))
    start = start_pa
    for j, x in enumerate(xs):
        a, b = transient_trace(x, q_m3_s, n_ticks, steps_per_tick, params, dt_s, first, start)
        p1[:, j], p2[:, j] = a, b
        start = (float(a[-1]), float(b[-1]))
    return p1, p2


@njit(cache=True, parallel=True)
def _steady_kernel(xs, q, lap, clr, p_list, idx, p_max, out_p1, out_p2):
    for i in prange(xs.size):
        p1, p2 = steady_pressures(xs[i], q[i], p_list[idx[i]], p_max)
        out_p1[i] = p1
        out_p2[i] = p2


@njit(cache=True)
def _steady_kernel_rtol(xs, q, lap, clr, p_list, idx, p_max, rtol, out_p1, out_p2):
    for i in range(xs.size):
        p1, p2 = steady_pressures_rtol(xs[i], q[i], p_list[idx[i]], p_max, rtol)
        out_p1[i] = p1
        out_p2[i] = p2


def steady_map(xs_m, q_m3_s, overlap_m=None, clearance_m=None, params=None,
               p_max_pa: float | None = None, rtol: float | None = None) -> MapResult:
    """Steady-state P1, P2, P12 for the same inputs as :func:`transient_map`.

    Pressures are searched in ``[PVap, p_max_pa]`` (default 20 x supply): by nested
    bisections to the last digits (:func:`~eha_ros.physics.valve.steady_pressures`), or, with
    ``rtol``, to that relative tolerance by the Illinois method in one thread
    (:func:`~eha_ros.physics.valve.steady_pressures_rtol`: for fits that evaluate many small
    maps).
    """
    if rtol is not None and not 1e-15 <= rtol <= 1e-3:
        raise ValueError(f'steady map: rtol {rtol:g} outside [1e-15, 1e-3]')
    p = params if params is not None else default_params()
    shape, (xs, q, lap, clr) = _broadcast(xs_m, q_m3_s, overlap_m, clearance_m, p)
    pmax = 20.0 * p.supply_pressure_pa if p_max_pa is None else float(p_max_pa)
    # one parameter tuple per distinct (overlap, clearance)
    wear = np.stack([lap, clr], axis=1)
    uniq, idx = np.unique(wear, axis=0, return_inverse=True)
    plist = [replace(p, overlap_supply_m=float(a), overlap_return_m=float(a),
                     radial_clearance_m=float(c)) for a, c in uniq]
    from numba.typed import List
    typed = List(plist)
    p1 = np.empty(xs.size)
    p2 = np.empty(xs.size)
    if rtol is None:
        _steady_kernel(xs, q, lap, clr, typed, idx.astype(np.int64).ravel(), pmax, p1, p2)
    else:
        _steady_kernel_rtol(xs, q, lap, clr, typed, idx.astype(np.int64).ravel(), pmax,
                            float(rtol), p1, p2)
    return MapResult(p1_pa=p1.reshape(shape), p2_pa=p2.reshape(shape),
                     p12_pa=(p1 - p2).reshape(shape))


def settling_mask(transient: MapResult, steady: MapResult, rtol: float = 0.01,
                  atol_pa: float = 1e4) -> np.ndarray:
    """Points where the transient P12 is within ``rtol``/``atol_pa`` of the steady P12."""
    return np.abs(transient['p12_pa'] - steady['p12_pa']) <= atol_pa + rtol * np.abs(
        steady['p12_pa'])
