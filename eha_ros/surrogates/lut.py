"""Lookup table of the fluid-dynamic block (the reference's section 5.2): ``P12(XS, Q, overlap,
clearance)`` on a 4-D grid, multilinear interpolation between the grid points.

Kernel
------
:func:`lut_kernel` locates each input on its axis through a bucket index (equal buckets
narrower than half the finest breakpoint spacing, see :func:`axis_tables`): one lookup and at
most one step, both branch-free, so the axes need not be uniform (the spool axis is
:func:`eha_ros.physics.maps.spool_grid`, 27x denser near null) and random inputs cost no
mispredicted branches.  Inputs outside an axis are clamped to its end (the table is held
constant beyond its edges, it does not extrapolate); the 16 surrounding table values are
blended with the product of the four linear weights.  The kernel is allocation-free and runs
in float64 whatever the table's storage type; a NaN input gives a NaN output.

The shipped table (its grid, and why) is built by :mod:`eha_ros.training.lut`; its artefact's
meta and ``bench/surrogates_lut_ga.py`` give its errors.

Inputs outside the table (``|Q| > FLOW_MAX_M3_S``, wear outside ``WEAR_RANGES``) are clamped:
the surrogate is only meant for the ranges it was built on.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from eha_ros.physics.loop import advance
from eha_ros.surrogates.base import FluidSurrogate, Forms, SurrogateError

__all__ = ['lut_kernel', 'axis_tables', 'make_lut', 'AXES']

#: Input names, in the kernel's order, and their units.
AXES = (('xs_m', 'm'), ('q_m3_s', 'm^3/s'), ('overlap_m', 'm'), ('clearance_m', 'm'))


#: Buckets of an axis index per finest breakpoint spacing, and the most an axis may need.
_BUCKETS_PER_SPACING = 2
_MAX_BUCKETS = 1 << 16


def axis_tables(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two arrays :func:`_locate` needs besides the breakpoints of an axis.

    The axis span is cut into ``nb`` equal buckets narrower than half the finest breakpoint
    spacing, so that a bucket holds at most one breakpoint.

    Returns
    -------
    aux : ndarray of float64
        ``[axis[0], nb / span, nb - 1, 1 / (axis[1] - axis[0]), ..., 1 / (axis[n-1] -
        axis[n-2])]``.
    index : ndarray of int64
        ``index[b]``: the interval ``i`` (``axis[i] <= x < axis[i + 1]``, ``i <= n - 2``)
        holding the start of bucket ``b``; a point of bucket ``b`` lies in interval
        ``index[b]`` or the next one.

    Raises
    ------
    SurrogateError
        When the axis is so non-uniform that it would need more than 65536 buckets.
    """
    axis = np.asarray(axis, dtype=np.float64)
    span = axis[-1] - axis[0]
    dx = np.diff(axis)
    nb = int(np.ceil(_BUCKETS_PER_SPACING * span / dx.min()))
    if nb > _MAX_BUCKETS:
        raise SurrogateError(f'lookup-table axis too non-uniform: finest spacing {dx.min():g} '
                             f'over a span of {span:g} needs {nb} index buckets '
                             f'(at most {_MAX_BUCKETS})')
    starts = axis[0] + span * np.arange(nb) / nb
    index = np.minimum(np.searchsorted(axis, starts, side='right') - 1, axis.size - 2)
    aux = np.concatenate([[axis[0], nb / span, nb - 1.0], 1.0 / dx])
    return aux, index.astype(np.int64)


@njit(cache=True, inline='always')
def _locate(axis, aux, index, x):
    """``(i, t)`` with ``x = (1 - t) axis[i] + t axis[i + 1]``, ``t`` clamped to [0, 1].

    The bucket of ``x`` gives its interval to within one step (see :func:`axis_tables`):
    no search loop, and the step is a conditional move, so random inputs cost no
    mispredicted branches.  A NaN ``x`` gives a NaN ``t``.
    """
    u = (x - aux[0]) * aux[1]
    if not u > 0.0:  # also NaN
        u = 0.0
    if u > aux[2]:
        u = aux[2]
    i = index[int(u)]
    i = min(i + (axis[i + 1] <= x), axis.size - 2)
    t = (x - axis[i]) * aux[3 + i]
    if t < 0.0:
        t = 0.0
    elif t > 1.0:
        t = 1.0
    return i, t


@njit(cache=True)
def lut_kernel(data, xs_m, q_m3_s, overlap_m, clearance_m):
    """P12 [Pa] by multilinear interpolation; inputs [m, m^3/s, m, m] clamped to the axes.

    ``data = (xs_axis, q_axis, overlap_axis, clearance_axis, table, xs_aux, q_aux,
    overlap_aux, clearance_aux, xs_index, q_index, overlap_index, clearance_index)``, the
    ``aux``/``index`` arrays from :func:`axis_tables`.
    """
    table = data[4]
    i, a = _locate(data[0], data[5], data[9], xs_m)
    j, b = _locate(data[1], data[6], data[10], q_m3_s)
    k, c = _locate(data[2], data[7], data[11], overlap_m)
    m, d = _locate(data[3], data[8], data[12], clearance_m)
    acc = 0.0
    for di in range(2):
        wi = a if di else 1.0 - a
        for dj in range(2):
            wj = wi * (b if dj else 1.0 - b)
            for dk in range(2):
                wk = wj * (c if dk else 1.0 - c)
                v0 = np.float64(table[i + di, j + dj, k + dk, m])
                v1 = np.float64(table[i + di, j + dj, k + dk, m + 1])
                acc += wk * (v0 + d * (v1 - v0))
    return acc


@njit(cache=True)
def _run_lut(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, lut_kernel, None, data, False)


@njit(cache=True)
def _run_split_lut(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, lut_kernel, None, data, True)


@njit(cache=True)
def _points_lut(data, xs, q, lap, clr, out):
    for i in range(xs.size):
        out[i] = lut_kernel(data, xs[i], q[i], lap[i], clr[i])


#: The compiled forms of :func:`lut_kernel`, cached on disk (:class:`.base.Forms`).
LUT_FORMS = Forms(_run_lut, _run_split_lut, _points_lut)


def make_lut(xs_m, q_m3_s, overlap_m, clearance_m, p12_pa, meta: dict | None = None,
             dtype=np.float32, name: str = 'lut') -> FluidSurrogate:
    """A lookup-table surrogate from a grid and P12 on it.

    Parameters
    ----------
    xs_m, q_m3_s, overlap_m, clearance_m : array_like
        Strictly increasing breakpoints [m, m^3/s, m, m], at least 2 each.
    p12_pa : array_like
        P12 [Pa], shape ``(n_xs, n_q, n_overlap, n_clearance)``, finite.
    meta : dict, optional
        Metadata to carry (``kind`` and ``inputs`` are filled in).
    dtype : numpy dtype
        Storage type of the table (interpolation runs in float64 regardless).

    Raises
    ------
    SurrogateError
        On a malformed grid or table.
    """
    axes = []
    for (label, _), a in zip(AXES, (xs_m, q_m3_s, overlap_m, clearance_m)):
        a = np.ascontiguousarray(a, dtype=np.float64)
        if a.ndim != 1 or a.size < 2 or not np.all(np.isfinite(a)) or np.any(np.diff(a) <= 0):
            raise SurrogateError(f'lookup table axis {label} must be a finite, strictly '
                                 'increasing 1-D array of at least 2 breakpoints')
        axes.append(a)
    table = np.ascontiguousarray(p12_pa, dtype=dtype)
    shape = tuple(a.size for a in axes)
    if table.shape != shape:
        raise SurrogateError(f'lookup table of shape {table.shape} does not match its axes '
                             f'{shape}')
    if not np.all(np.isfinite(table)):
        raise SurrogateError('lookup table holds non-finite values')
    meta = dict(meta or {})
    meta.setdefault('kind', 'lut')
    meta.setdefault('inputs', [{'name': n, 'unit': u} for n, u in AXES])
    meta.setdefault('output', {'name': 'p12_pa', 'unit': 'Pa'})
    extra = [axis_tables(a) for a in axes]
    data = (*axes, table, *(e[0] for e in extra), *(e[1] for e in extra))
    return FluidSurrogate(name=name, kernel=lut_kernel, forms=LUT_FORMS, data=data, meta=meta,
                          rebuild='eha_ros.training.lut')
