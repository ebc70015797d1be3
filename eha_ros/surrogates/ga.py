"""The reference's 8-coefficient function of the fluid-dynamic block (section 5.3), fitted by a
real-coded genetic algorithm::

    P12 = c1 tanh(c2 wxs) + c3 wq / (1 + c4 wxs^2 + c5 wxs^4) + c6 wq^3 / (1 + c7 wxs^2 + c8 wxs^4)

with ``wxs = XS / XS_REF_M`` and ``wq = Q / Q_REF_M3_S``; P12 in Pa.

Normalisation
-------------
The reference scaled XS, Q and P by constants and bounded the coefficients with
``lb = [2e7 1e2 -1e9 -1e7 -1e7 -1e7 -1e7 -1e7]``, ``ub = [2e7 1e3 1e9 1e7 1e7 1e7 1e7 1e7]``,
starting from ``[2e7 2e2 -1.5e7 800 1e4 -8e5 5e3 1e4]``.  ``c1 = 2e7`` pinned is the zero-flow
plateau in Pa (our maps saturate at +-20.0 MPa), so P12 is left in Pa.  XS and Q are divided by
powers of ten chosen so that those bounds hold the optimum of our valve and the initial ``c2``
and ``c3`` lie near it:

* ``XS_REF_M = 1e-2`` (XS in cm): the fitted tanh slope for the nominal map is 1.49e4 /m,
  i.e. ``c2 = 149``, inside ``[100, 1000]`` and near the initial 200.  An order-one ``wxs``
  (``XS / stroke``) would put it at ``c2 = 4.5``, far below the reference's lower bound.
* ``Q_REF_M3_S = 1e-5`` (Q in units of 10 cm^3/s): the fitted linear flow term,
  -2.0e12 Pa s/m^3, gives ``c3 = -2.0e7`` (initial -1.5e7), and the cubic ``c6 = -5.8e4``
  lies well inside +-1e7.

So ``wxs`` spans +-0.03 and ``wq`` +-6 over the maps; the reference's bounds are used unchanged.

Admissible coefficients: both denominators stay >= ``MIN_DENOMINATOR`` over the spool
stroke.  The bounds allow negative ``c4, c5, c7, c8``, hence denominators that cross zero: a
pole between the map's spool positions would not show in the fit error but would blow up the
plant.  The genetic algorithm gives such individuals an infinite fitness.

Limits (figures: the artefact's meta and ``bench/surrogates_lut_ga.py``)
-------------------------------------------------------------------------
* The function has no wear inputs: it is fitted on the nominal-wear map (DB5) and the kernel
  ignores overlap and clearance, so it errs more on worn valves.
* It is odd in Q at fixed XS apart from the tanh term, while the maps carry ``Q |Q|`` terms
  where the valve is open; most of its squared error sits on the flanks of the water-hammer
  peaks.  Near null, where the shipped scenarios' loop stays, its tanh is shallower than the
  zero-flow curve (its slope is set by the large peaks): there it errs far more than the
  lookup table.
* Inputs are clamped to the training ranges (``|XS| <= stroke``, ``|Q| <= FLOW_MAX_M3_S``): the
  cubic term grows fast outside them and the admissibility check covers the stroke only.

The fit (genetic algorithm, gradient refit) is :mod:`eha_ros.training.ga`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from eha_ros.physics.maps import FLOW_MAX_M3_S
from eha_ros.physics.loop import advance
from eha_ros.surrogates.base import FluidSurrogate, Forms, SurrogateError

__all__ = ['XS_REF_M', 'Q_REF_M3_S', 'ga_p12', 'formula', 'ga_kernel', 'make_ga']

#: Spool-position scale [m]: ``wxs = XS / XS_REF_M``.
XS_REF_M = 1e-2
#: Flow scale [m^3/s]: ``wq = Q / Q_REF_M3_S``.
Q_REF_M3_S = 1e-5


@njit(cache=True, inline='always')
def ga_p12(c, wx, wq):
    """The function at one point (the one place it is written): ``c`` the 8 coefficients,
    ``wx = XS / XS_REF_M`` and ``wq = Q / Q_REF_M3_S``; P12 in Pa."""
    w2 = wx * wx
    w4 = w2 * w2
    return (c[0] * math.tanh(c[1] * wx) + c[2] * wq / (1.0 + c[3] * w2 + c[4] * w4)
            + c[5] * wq * wq * wq / (1.0 + c[6] * w2 + c[7] * w4))


@njit(cache=True)
def _formula_loop(c, wx, wq, out):
    for i in range(out.size):
        out[i] = ga_p12(c, wx[i], wq[i])


def formula(c, wxs, wq):
    """:func:`ga_p12` on arrays: one coefficient vector ``c`` (8,), broadcasting inputs."""
    c = np.ascontiguousarray(c, dtype=float)
    wx, q = np.broadcast_arrays(np.asarray(wxs, dtype=float), np.asarray(wq, dtype=float))
    out = np.empty(wx.shape)
    _formula_loop(c, np.ravel(wx), np.ravel(q), out.reshape(-1))
    return out


@njit(cache=True)
def ga_kernel(data, xs_m, q_m3_s, overlap_m, clearance_m):
    """P12 [Pa] of the fitted function; ``data = (coefficients[8], [xs_ref_m, q_ref_m3_s,
    xs_max_m, q_max_m3_s])``.  Overlap and clearance are ignored; XS and Q are clamped to
    ``+-xs_max_m``, ``+-q_max_m3_s``."""
    n = data[1]
    x = min(max(xs_m, -n[2]), n[2])
    q = min(max(q_m3_s, -n[3]), n[3])
    return ga_p12(data[0], x / n[0], q / n[1])


@njit(cache=True)
def _run_ga(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, ga_kernel, None, data, False)


@njit(cache=True)
def _run_split_ga(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, ga_kernel, None, data, True)


@njit(cache=True)
def _points_ga(data, xs, q, lap, clr, out):
    for i in range(xs.size):
        out[i] = ga_kernel(data, xs[i], q[i], lap[i], clr[i])


#: The compiled forms of :func:`ga_kernel`, cached on disk (:class:`.base.Forms`).
GA_FORMS = Forms(_run_ga, _run_split_ga, _points_ga)


def make_ga(coefficients, xs_max_m: float, q_max_m3_s: float = FLOW_MAX_M3_S,
            meta: dict | None = None, name: str = 'ga') -> FluidSurrogate:
    """A surrogate from fitted coefficients; inputs clamped to ``+-xs_max_m``,
    ``+-q_max_m3_s``."""
    c = np.ascontiguousarray(coefficients, dtype=np.float64)
    if c.shape != (8,) or not np.all(np.isfinite(c)):
        raise SurrogateError('the GA function needs 8 finite coefficients')
    if not (xs_max_m > 0 and q_max_m3_s > 0):
        raise SurrogateError('xs_max_m and q_max_m3_s must be positive')
    norm = np.array([XS_REF_M, Q_REF_M3_S, float(xs_max_m), float(q_max_m3_s)])
    meta = dict(meta or {})
    meta.setdefault('kind', 'ga')
    return FluidSurrogate(name=name, kernel=ga_kernel, forms=GA_FORMS, data=(c, norm), meta=meta,
                          rebuild='eha_ros.training.ga')
