"""Dynamic surrogates: the valve's metering edges learned, the fluid's dynamics kept.  This
module holds what ``dlut`` (a table, :mod:`.dlut`), ``dnn`` (a network, :mod:`.dnn`) and ``dga``
(a closed form, :mod:`.dga`) share: the edge law (:func:`edge_flows`), its validity
(:func:`valid_range`), their base class and the hf chamber flows (:func:`hf_chamber_flows`).

The reference's surrogates (``lut``, ``ga``, ``nn``, ``nn2``) return the load pressure as an
algebraic function ``P12(XS, Q)``: the chamber pressures stop being states and the hydraulic
spring and the pressure build-up that drives stick-slip vanish from the loop.  The surrogates
here replace only what is algebraic in the high-fidelity (hf) model, the flows through the
metering edges; the chamber compressibility, the leakage, the cavitation clip and the jack stay
the physical ones of :mod:`eha_ros.physics.plant`.

What is learned
    One edge law, the flow [m^3/s] through a metering edge::

        q(s, dp; c) = sign(dp) |dp| G(s, |dp|, c)

    with ``s`` [m] how far the spool has passed the edge's lap (> 0 open, <= 0 covered by
    ``-s``), ``dp`` [Pa] the pressure drop across it and ``c`` [m] the radial clearance.  The
    four edges of the valve are this law at the openings ``XS - OSSV`` (1S), ``-XS - ORSV``
    (1R), ``-XS - OSSV`` (2S) and ``XS - ORSV`` (2R), exactly as in :mod:`.valve`, so unequal
    supply and return laps are exact.  ``G > 0`` is the secant conductance; it is finite at
    ``dp = 0`` (the Reynolds-number discharge coefficient makes the edge laminar there), which
    is why the surrogates learn ``G`` (or ``K = G sqrt|dp|``) rather than ``q``.  The training
    data come from :func:`eha_ros.physics.valve.edge_coefficients` and
    :func:`eha_ros.physics.valve.orifice_flow` themselves: no transient, no map volume.

Validity (stored in each artefact's ``meta['valid_range']``)
    Spool position ``|XS| <=`` the stroke, overlaps (supply and return, each) in
    ``WEAR_RANGES['overlap_m']``, clearance in ``WEAR_RANGES['radial_clearance_m']``, pressure
    drops ``|dp| <= DP_MAX_PA`` (twice the nominal supply; above it ``dlut`` extends its
    table's last cell, the others their formula).  :meth:`prepare`
    refuses wear outside the ranges with a one-line :class:`SurrogateError`.  The edge law
    depends on the fluid and port parameters :data:`EDGE_PARAMETERS` only (not on the
    pressures, volumes or leakage, which stay physical); an artefact built for others is
    refused.

Kernel interface (:func:`eha_ros.physics.loop.advance`, ``kernel_output`` CHAMBER_FLOWS)
    ``kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m) -> (Q1L, Q2L)`` [m^3/s]:
    the net flow into chamber 1 (edges 1S at ``xs - lap_supply``, 1R at ``-xs - lap_return``)
    and out of chamber 2 (2R at ``xs - lap_return``, 2S at ``-xs - lap_supply``), as
    :func:`eha_ros.physics.valve.valve_flows`.  ``data`` is what
    :meth:`DynamicSurrogate.prepare` returns for the current wear and pressures (the
    clearance is folded in once per run or parameter change, not per step).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from eha_ros.artefacts import check_hash
from eha_ros.physics import PlantParams, default_params, params_hash
from eha_ros.physics.maps import WEAR_RANGES, spool_grid
from eha_ros.physics.loop import CHAMBER_FLOWS
from eha_ros.physics.valve import (edge_coefficients, edge_constants, fluid_constants,
                                   orifice_flow, valve_flows)
from eha_ros.surrogates.base import FluidSurrogate, SurrogateError

__all__ = ['EDGE_PARAMETERS', 'edge_hash', 'DP_MAX_PA', 'edge_flows', 'edge_conductance',
           'DynamicSurrogate', 'hf_chamber_flows', 'valid_range']

#: Parameters the edge law depends on (the wear, clearance and laps, are inputs).
EDGE_PARAMETERS = ('fluid_density_kg_m3', 'fluid_kinematic_viscosity_m2_s', 'port_width_m',
                   'eccentricity_ratio', 'discharge_coefficient', 'cd_model',
                   'critical_flow_number', 'valve_degradation')

#: Largest pressure drop [Pa] the surrogates are built for: twice the nominal supply (a chamber
#: transiently above supply, or at the vapour pressure, stays inside).
DP_MAX_PA = 4.2e7


def edge_hash(p: PlantParams) -> str:
    """Hash of :data:`EDGE_PARAMETERS`."""
    return params_hash(p, EDGE_PARAMETERS)


# the fluid constants travel as the scalars edge_constants takes (physics.valve), not packed
@njit(cache=True)
def _edge_flows(s, dp, c, w, cd, mu, rho, ecc, lc, reynolds, out):
    for i in range(s.size):
        vc = edge_constants(c[i], 0.0, 0.0, w, cd, mu, rho, ecc, lc, reynolds)
        rl, bl, r4 = edge_coefficients(s[i], vc)
        out[i] = orifice_flow(dp[i], rl, bl, r4)


def edge_flows(s_m, dp_pa, clearance_m, params: PlantParams | None = None) -> np.ndarray:
    """Flow [m^3/s] through one metering edge from the hf model's own edge equations, for
    broadcastable openings [m], pressure drops [Pa] and clearances [m]."""
    p = params if params is not None else default_params()
    arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (s_m, dp_pa, clearance_m)))
    flat = [np.ascontiguousarray(a.ravel()) for a in arrs]
    out = np.empty(flat[0].size)
    _edge_flows(*flat, *fluid_constants(p), out)
    return out.reshape(arrs[0].shape)


def edge_conductance(s_m, dp_pa, clearance_m, params: PlantParams | None = None) -> np.ndarray:
    """Secant conductance ``G = q / dp`` [m^3/(s Pa)] of one edge (the limit at ``dp = 0``)."""
    dp = np.asarray(dp_pa, dtype=float)
    d = np.where(np.abs(dp) > 0.0, dp, 1e-6)
    return edge_flows(s_m, d, clearance_m, params) / d


@njit  # not cached: a kernel argument's type names the kernel object (see .base.Forms)
def _chamber_loop(kernel, data, xs, p1, p2, lap_s, lap_r, out1, out2):
    for i in range(xs.size):
        out1[i], out2[i] = kernel(data, xs[i], p1[i], p2[i], lap_s[i], lap_r[i])


@njit  # not cached: see _chamber_loop
def _edge_loop(kernel, data, consts, s, dp, out):
    for i in range(s.size):
        consts[0] = dp[i]  # supply pressure: the supply edge sees dp, the return edge none
        consts[1] = 0.0
        out[i] = kernel(data, s[i], 0.0, 0.0, 0.0, 0.0)[0]


class DynamicSurrogate(FluidSurrogate):
    """A dynamic surrogate: the kernel gives chamber flows (module docstring); ``data`` holds
    the artefact's arrays, :meth:`prepare` the kernel's data for given parameters."""

    kernel_output = CHAMBER_FLOWS

    def check_params(self, p: PlantParams) -> None:
        check_hash(self.meta, 'edge_hash', edge_hash(p), f'surrogate {self.name}',
                   self.rebuild, SurrogateError)
        self.check_wear(p)

    def check_wear(self, p: PlantParams) -> None:
        """Refuse wear or a stroke outside the range the surrogate was built for."""
        vr = self.meta['valid_range']
        for name, value in (('overlap_supply_m', p.overlap_supply_m),
                            ('overlap_return_m', p.overlap_return_m),
                            ('radial_clearance_m', p.radial_clearance_m)):
            lo, hi = vr['radial_clearance_m' if name.startswith('radial') else 'overlap_m']
            if not lo - 1e-15 <= value <= hi + 1e-15:
                raise SurrogateError(f'parameter {name} = {value:g} m is outside the range '
                                     f'[{lo:g}, {hi:g}] m of surrogate {self.name}')
        if p.spool_stroke_m > vr['spool_stroke_m'] * (1 + 1e-12):
            raise SurrogateError(f'parameter spool_stroke_m = {p.spool_stroke_m:g} m exceeds '
                                 f'the stroke {vr["spool_stroke_m"]:g} m of surrogate '
                                 f'{self.name}')

    def prepare(self, p: PlantParams) -> tuple:
        """The kernel's data for the wear and pressures of ``p`` (checked first)."""
        self.check_params(p)
        key = (p.radial_clearance_m, p.supply_pressure_pa, p.return_pressure_pa)
        cache = self.__dict__.setdefault('_prepared', {})
        if key not in cache:
            if len(cache) > 16:
                cache.clear()
            cache[key] = self._prepare(p)
        return cache[key]

    def _prepare(self, p: PlantParams) -> tuple:
        raise NotImplementedError

    def chamber_flows(self, xs_m, p1_pa, p2_pa, params: PlantParams | None = None):
        """(Q1L, Q2L) [m^3/s] at spool ``xs_m`` [m] and chamber pressures [Pa]
        (broadcastable), at the wear of ``params`` (default nominal)."""
        p = params if params is not None else default_params()
        data = self.prepare(p)
        arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (xs_m, p1_pa, p2_pa)))
        xs, a1, a2 = (np.ascontiguousarray(a.ravel()) for a in arrs)
        o1, o2 = np.empty(xs.size), np.empty(xs.size)
        laps = np.full(xs.size, p.overlap_supply_m), np.full(xs.size, p.overlap_return_m)
        if self.forms is not None:
            self.forms.points(data, xs, a1, a2, *laps, o1, o2)
        else:
            _chamber_loop(self.kernel, data, xs, a1, a2, *laps, o1, o2)
        return o1.reshape(arrs[0].shape), o2.reshape(arrs[0].shape)

    def chamber_flow(self, xs_m, p_pa, params: PlantParams | None = None):
        """Net flow [m^3/s] into chamber 1 (Q1L) at spool ``xs_m`` [m] and its pressure
        ``p_pa`` [Pa] (broadcastable)."""
        return self.chamber_flows(xs_m, p_pa, p_pa, params)[0]

    def stability_limit(self, p: PlantParams) -> tuple[float, str]:
        """Largest stable step [s] of the chamber pressures under this surrogate's flows:
        ``dt < 2 Vol / (Bet g)`` with ``g`` the largest conductance ``|dQ1L/dP1|`` measured on
        the surrogate (over the stroke, pressures from the vapour pressure to twice the
        supply, and within 1 kPa of supply and return where it peaks)."""
        xs = spool_grid(41, p.spool_stroke_m)
        ps, pr = p.supply_pressure_pa, p.return_pressure_pa
        near = np.array([-1e3, -100.0, -10.0, -1.0, 0.0, 1.0, 10.0, 100.0, 1e3])
        pp = np.unique(np.concatenate([np.linspace(p.vapour_pressure_pa, 2.0 * ps, 61),
                                       ps + near, pr + near]))
        q = self.chamber_flow(xs[:, None], pp[None, :], p)
        g = float(np.max(np.abs(np.diff(q, axis=1)) / np.diff(pp)[None, :]))
        if not g > 0:
            return math.inf, f'surrogate {self.name} chamber flows (flat)'
        return (2.0 * p.chamber_volume_m3 / (p.bulk_modulus_pa * g),
                f'chamber pressures (Bet/Vol x surrogate {self.name} conductance)')

    def edge_flow(self, s_m, dp_pa, params: PlantParams | None = None):
        """Flow [m^3/s] of one edge at openings ``s_m`` [m] and drops ``dp_pa`` [Pa] (1-D
        arrays) at the clearance of ``params``: the chamber kernel with the chamber at the
        return pressure, zero laps and the supply pressure set to ``dp`` per point."""
        p = params if params is not None else default_params()
        data = list(self.prepare(p))
        data[-1] = data[-1].copy()  # every kind keeps [ps, pr, ...] last
        s = np.ascontiguousarray(s_m, dtype=float).ravel()
        dp = np.ascontiguousarray(np.broadcast_to(np.asarray(dp_pa, dtype=float), s.shape))
        out = np.empty(s.size)
        _edge_loop(self.kernel, tuple(data), data[-1], s, dp, out)
        return out

    def p12(self, *args, **kwargs):
        raise SurrogateError(f'surrogate {self.name} is dynamic: it gives chamber flows '
                             '(chamber_flow), not an algebraic P12')


def hf_chamber_flows(xs_m, p1_pa, p2_pa, params: PlantParams | None = None):
    """(Q1L, Q2L) [m^3/s] of the hf model (:func:`eha_ros.physics.valve.valve_flows`),
    vectorised, for checks against :meth:`DynamicSurrogate.chamber_flows`."""
    p = params if params is not None else default_params()
    arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (xs_m, p1_pa, p2_pa)))
    out = np.array([valve_flows(x, a, b, p) for x, a, b in zip(*(a.ravel() for a in arrs))])
    return out[:, 0].reshape(arrs[0].shape), out[:, 1].reshape(arrs[0].shape)


def valid_range(p: PlantParams) -> dict:
    """The validity of the shipped dynamic surrogates (see the module docstring)."""
    return {'spool_stroke_m': float(p.spool_stroke_m),
            'overlap_m': [float(v) for v in WEAR_RANGES['overlap_m']],
            'radial_clearance_m': [float(v) for v in WEAR_RANGES['radial_clearance_m']],
            'dp_pa': [0.0, DP_MAX_PA],
            'opening_m': [-float(p.spool_stroke_m + WEAR_RANGES['overlap_m'][1]),
                          float(p.spool_stroke_m - WEAR_RANGES['overlap_m'][0])]}
