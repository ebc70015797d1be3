"""The ``dga`` dynamic surrogate (:mod:`.edge`): a closed form of the edge law designed from the
physics of an annular orifice (:func:`ga_edge_flow`), coefficients fitted by the genetic
algorithm, then polished by a gradient fit from its best; its kernel :func:`dga_kernel`, the
kernel's compiled forms :data:`DGA_FORMS` and :class:`DgaSurrogate`."""

import math

import numpy as np
from numba import njit

from eha_ros.physics import PlantParams
from eha_ros.physics.loop import advance
from eha_ros.surrogates.base import Forms
from eha_ros.surrogates.edge import DynamicSurrogate

__all__ = ['GA_GENES', 'ga_edge_flow', 'dga_kernel', 'DGA_FORMS', 'DgaSurrogate']

#: Genes of the closed form (:func:`ga_edge_flow`), in order.
GA_GENES = ('k_lam', 'n_lam', 'k_turb', 'k_rey')


@njit(cache=True, inline='always')
def _ga_edge(s, dp, c2, a_lam, k_turb, k_rey):
    """``(2 dp h^2, den h^2)`` of :func:`ga_edge_flow`: the flow is their ratio.  Multiplying
    through by ``h^2`` leaves no division in the edge; the kernel divides once per chamber."""
    if s > 0.0:
        rl = 0.0
        h2 = c2 + s * s
    else:
        rl = -a_lam * s
        h2 = c2
    rh = rl * h2
    return 2.0 * dp * h2, rh + math.sqrt(rh * rh + k_rey + k_turb * h2 * abs(dp))


@njit(cache=True, inline='always')
def ga_edge_flow(s, dp, c2, a_lam, k_turb, k_rey):
    """The closed-form edge law of ``dga``, its coefficients ``[c^2, a_lam, k_turb, k_rey]``
    prepared for one clearance ``c`` (:meth:`DgaSurrogate._prepare`)::

        h^2 = c^2 + max(s, 0)^2                     (annulus, then truncated cone)
        RL  = a_lam max(-s, 0),  a_lam = k_lam / c^n_lam   (laminar, covered length)
        R4  = k_turb / h^2                          (orifice: rho / (2 Cd^2 A^2), A ~ h)
        B   = k_rey / h^4                           (Reynolds-number laminar limit)
        q   = 2 dp / (RL + sqrt(RL^2 + B + R4 |dp|))

    The root form of ``dp = RL q + RQ q|q|`` (laminar and quadratic resistances in series,
    the orifice law of every metering edge); with ``n_lam = 3`` (Poiseuille flow in a slit)
    it is the form of the hf model, whose coefficients the fit does not know.  The area
    exponent is fixed at the orifice's 1 (a free exponent fitted close to it and cost a power
    per edge and step).  Scalars only: an array passed into an inlined function with branches
    costs reference counting on every call.
    """
    num, den = _ga_edge(s, dp, c2, a_lam, k_turb, k_rey)
    return num / max(den, 1e-300)


@njit(cache=True)
def dga_kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m):
    """(Q1L, Q2L) [m^3/s] from the closed form; ``data = (cf, consts)``, ``consts = [ps, pr]``."""
    cf = data[0]
    c2, a, kt, kr = cf[0], cf[1], cf[2], cf[3]
    ps = data[1][0]
    pr = data[1][1]
    n1s, d1s = _ga_edge(xs_m - lap_supply_m, ps - p1_pa, c2, a, kt, kr)
    n1r, d1r = _ga_edge(-xs_m - lap_return_m, p1_pa - pr, c2, a, kt, kr)
    n2r, d2r = _ga_edge(xs_m - lap_return_m, p2_pa - pr, c2, a, kt, kr)
    n2s, d2s = _ga_edge(-xs_m - lap_supply_m, ps - p2_pa, c2, a, kt, kr)
    # one division per chamber: n_in / d_in - n_out / d_out over the common denominator
    d1s = max(d1s, 1e-300)
    d1r = max(d1r, 1e-300)
    d2r = max(d2r, 1e-300)
    d2s = max(d2s, 1e-300)
    q1l = (n1s * d1r - n1r * d1s) / (d1s * d1r)
    q2l = (n2r * d2s - n2s * d2r) / (d2r * d2s)
    return q1l, q2l


@njit(cache=True)
def _run_dga(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, None, dga_kernel, data, False)


@njit(cache=True)
def _run_split_dga(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, None, dga_kernel, data, True)


@njit(cache=True)
def _points_dga(data, xs, p1, p2, lap_s, lap_r, out1, out2):
    for i in range(xs.size):
        out1[i], out2[i] = dga_kernel(data, xs[i], p1[i], p2[i], lap_s[i], lap_r[i])


#: The compiled forms of :func:`dga_kernel`, cached on disk (:class:`.base.Forms`).
DGA_FORMS = Forms(_run_dga, _run_split_dga, _points_dga)


class DgaSurrogate(DynamicSurrogate):
    """``dga``: the designed edge formula with the clearance's terms evaluated once."""

    def _prepare(self, p: PlantParams) -> tuple:
        k_lam, n_lam, k_turb, k_rey = (float(v) for v in self.data[0])
        c = p.radial_clearance_m
        cf = np.array([c * c, k_lam / c ** n_lam, k_turb, k_rey])
        return (cf, np.array([p.supply_pressure_pa, p.return_pressure_pa]))
