"""The ``dlut`` dynamic surrogate (:mod:`.edge`): the table kernel :func:`dlut_kernel`, its
compiled forms :data:`DLUT_FORMS` and :class:`DlutSurrogate`, which collapses the table to the
run's clearance.

The table's axes are spaced as float64 numbers are: :func:`log_axis` puts ``2^m`` equal cells in
each octave of ``|x| + 2^e``, so a point's cell is the exponent and top ``m`` mantissa bits of
``|x| + 2^e`` and its weight the remaining bits (:func:`_log_cell`): no search and no index
table, a few integer operations where a searched axis chains dependent loads.  Openings
``|s|``: ``2^e`` = 1.9 um, 32 cells per octave (cells of 0.06 um at the edge, then steps of
1.6-3.1 % to the end of the stroke), a row per sign, a node at 0 where the edge uncovers;
``|dp|``: ``2^e`` = 1 Pa, 16 cells per octave, up to ``DP_MAX_PA``
(``eha_ros.training.dynamic.DLUT_GRID``).  The cells hold ``q = G |dp|``, linear in the laminar
limit (``q ~ dp``) and bent by at most 1/32 of a cell's relative width squared in the turbulent
one (``q ~ sqrt|dp|``; tabulating ``G sqrt|dp|`` over ``sqrt|dp|``, linear in both, would put a
square root ahead of the table loads in every step).  Prepared for a clearance, each cell
stores the four coefficients of its bilinear form contiguously.  Beyond ``DP_MAX_PA`` the last
cell's line is extended (the flow keeps rising with the drop); openings beyond the stroke are
held at the end of the axis.  Errors: the artefact's ``meta['errors']``
(``bench/surrogates_dynamic.py``).
"""

import math

import numpy as np
from numba import njit

from eha_ros.physics import PlantParams
from eha_ros.physics.loop import advance
from eha_ros.surrogates.base import Forms
from eha_ros.surrogates.edge import DynamicSurrogate

__all__ = ['log_axis', 'dlut_kernel', 'DLUT_FORMS', 'DlutSurrogate']

#: Bits of the float64 1.0: a mantissa ORed into them reads as a number in [1, 2).
_ONE_BITS = np.int64(0x3FF0000000000000)


def log_axis(exp2: int, log2_cells: int, x_max: float) -> np.ndarray:
    """Nodes ``x >= 0`` of a ``dlut`` axis: ``x + 2^exp2`` at the float64 numbers whose
    mantissa keeps only its top ``log2_cells`` bits, i.e. ``2^log2_cells`` equal cells per
    octave of ``x + 2^exp2`` (uniform cells of ``2^(exp2 - log2_cells)`` from ``x = 0`` up to
    ``2^exp2``, then geometric), up to the first node at or beyond ``x_max``."""
    m = 1 << log2_cells
    k = np.arange(0, m * 64)
    a = 2.0 ** (exp2 + k // m) * (1.0 + (k % m) / m)
    x = a - 2.0 ** exp2
    return x[:int(np.searchsorted(x, x_max)) + 1]


@njit(cache=True, inline='always')
def _log_cell(x, offset, shift, code0, mask, log2_cells):
    """Cell ``k`` and fraction ``t`` (linear in ``x``) of ``x >= 0`` on a :func:`log_axis`
    (``offset = 2^exp2``, the integers from :func:`_axis_consts`): the cell is the exponent
    and top mantissa bits of ``x + 2^exp2``, the fraction its remaining mantissa bits.  No
    search, no index table: integer operations on the bits.  ``k`` is not clamped."""
    b = np.float64(x + offset).view(np.int64)
    k = (b >> shift) - code0
    t = np.int64(((b & mask) << log2_cells) | _ONE_BITS).view(np.float64) - 1.0
    return k, t


@njit(cache=True, inline='always')
def _dlut_row(s, offset, shift, code0, mask, log2_cells, k_max, covered, row_cells):
    """Start in the packed table of the row of cells holding the opening ``s`` [m], and the
    weight ``a`` of its far node (held at the end of the axis beyond it)."""
    k, a = _log_cell(abs(s), offset, shift, code0, mask, log2_cells)
    if k > k_max:
        k = k_max
        a = 1.0
    if s < 0.0:
        k += covered
    return k * row_cells, a


@njit(cache=True, inline='always')
def _dlut_col(x, offset, shift, code0, mask, log2_cells, k_max, x_last, inv_last):
    """Cell and weight ``b`` of its far node of ``x = |dp|``; beyond the axis, the last
    cell's line extended."""
    j, b = _log_cell(x, offset, shift, code0, mask, log2_cells)
    if j > k_max:
        j = k_max
        b = (x - x_last) * inv_last
    return j, b


@njit(cache=True)
def dlut_kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m):
    """(Q1L, Q2L) [m^3/s], edges from the prepared table of ``q(s, |dp|)``.

    ``data = (table, int_consts, consts)`` (:meth:`DlutSurrogate._prepare`): per cell the four
    coefficients of its bilinear form ``q = (q00 + b dq_b) + a (dq_a + b dq_ab)``, contiguous,
    ``a`` and ``b`` the weights of the far nodes in ``|s|`` and ``|dp|``; ``q(s, dp) =
    sign(dp) q(s, |dp|)``; ``consts = [ps, pr, ...]``.  With equal laps the edges 1S/2R and
    1R/2S share their openings, so two of the four are located.  The helpers take scalars
    only (an array passed to an inlined helper with branches costs reference counting) and
    the table index is unsigned (no negative-index wrap-around on the way to the loads).
    """
    tab = data[0]
    ic = data[1]
    fc = data[2]
    ps = fc[0]
    pr = fc[1]
    s_off, s_sh, s_c0, s_mask, s_m, s_kmax, s_cov, n_cols = (
        fc[2], ic[0], ic[1], ic[2], ic[3], ic[4], ic[5], ic[11])
    p_off, p_sh, p_c0, p_mask, p_m, p_kmax, p_last, p_inv = (
        fc[3], ic[6], ic[7], ic[8], ic[9], ic[10], fc[4], fc[5])
    r1s, a1s = _dlut_row(xs_m - lap_supply_m, s_off, s_sh, s_c0, s_mask, s_m, s_kmax, s_cov,
                         n_cols)
    r1r, a1r = _dlut_row(-xs_m - lap_return_m, s_off, s_sh, s_c0, s_mask, s_m, s_kmax, s_cov,
                         n_cols)
    if lap_supply_m == lap_return_m:
        r2s, a2s, r2r, a2r = r1r, a1r, r1s, a1s
    else:
        r2s, a2s = _dlut_row(-xs_m - lap_supply_m, s_off, s_sh, s_c0, s_mask, s_m, s_kmax,
                             s_cov, n_cols)
        r2r, a2r = _dlut_row(xs_m - lap_return_m, s_off, s_sh, s_c0, s_mask, s_m, s_kmax,
                             s_cov, n_cols)
    d1s = ps - p1_pa
    d1r = p1_pa - pr
    d2r = p2_pa - pr
    d2s = ps - p2_pa
    # the four edges written out: a helper taking the table array would cost reference
    # counting on every call, as an array passed into an inlined function with branches does
    j, b = _dlut_col(abs(d1s), p_off, p_sh, p_c0, p_mask, p_m, p_kmax, p_last, p_inv)
    c = np.uint64((r1s + j) * 4)
    q1s = (tab[c] + b * tab[c + 1]) + a1s * (tab[c + 2] + b * tab[c + 3])
    j, b = _dlut_col(abs(d1r), p_off, p_sh, p_c0, p_mask, p_m, p_kmax, p_last, p_inv)
    c = np.uint64((r1r + j) * 4)
    q1r = (tab[c] + b * tab[c + 1]) + a1r * (tab[c + 2] + b * tab[c + 3])
    j, b = _dlut_col(abs(d2r), p_off, p_sh, p_c0, p_mask, p_m, p_kmax, p_last, p_inv)
    c = np.uint64((r2r + j) * 4)
    q2r = (tab[c] + b * tab[c + 1]) + a2r * (tab[c + 2] + b * tab[c + 3])
    j, b = _dlut_col(abs(d2s), p_off, p_sh, p_c0, p_mask, p_m, p_kmax, p_last, p_inv)
    c = np.uint64((r2s + j) * 4)
    q2s = (tab[c] + b * tab[c + 1]) + a2s * (tab[c + 2] + b * tab[c + 3])
    q1l = (-q1s if d1s < 0.0 else q1s) - (-q1r if d1r < 0.0 else q1r)
    q2l = (-q2r if d2r < 0.0 else q2r) - (-q2s if d2s < 0.0 else q2s)
    return q1l, q2l


@njit(cache=True)
def _run_dlut(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, None, dlut_kernel, data, False)


@njit(cache=True)
def _run_split_dlut(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, None, dlut_kernel, data, True)


@njit(cache=True)
def _points_dlut(data, xs, p1, p2, lap_s, lap_r, out1, out2):
    for i in range(xs.size):
        out1[i], out2[i] = dlut_kernel(data, xs[i], p1[i], p2[i], lap_s[i], lap_r[i])


#: The compiled forms of :func:`dlut_kernel`, cached on disk (:class:`.base.Forms`).
DLUT_FORMS = Forms(_run_dlut, _run_split_dlut, _points_dlut)


def _ln_c_weights(axis_ln_c, c):
    """Indices and weights of cubic Lagrange interpolation in ``ln c`` (4 nodes around ``c``,
    shifted inwards at the ends; clamped to the axis)."""
    n = axis_ln_c.size
    x = min(max(math.log(c), axis_ln_c[0]), axis_ln_c[-1])
    k = int(np.clip(np.searchsorted(axis_ln_c, x) - 2, 0, n - 4))
    nodes = axis_ln_c[k:k + 4]
    w = np.array([np.prod([(x - nodes[m]) / (nodes[j] - nodes[m]) for m in range(4) if m != j])
                  for j in range(4)])
    return k, w


def _axis_consts(exp2, log2_cells):
    """``_log_cell``'s integer constants of a :func:`log_axis`."""
    shift = 52 - log2_cells
    return [shift, (1023 + exp2) << log2_cells, (1 << shift) - 1, log2_cells]


class DlutSurrogate(DynamicSurrogate):
    """``dlut``: the edge table, collapsed to the run's clearance
    (:meth:`DlutSurrogate._prepare`)."""

    def _prepare(self, p: PlantParams) -> tuple:
        """Collapse the table ``ln G[s, |dp|, ln c]`` to ``q = G |dp|`` at the clearance of ``p``
        (cubic Lagrange interpolation of ``ln G`` in ``ln c``: exact for the power laws of the
        laminar and orifice limits, fourth order between them) and pack each cell's bilinear
        coefficients contiguously (float64)."""
        data, meta = self.data, self.meta
        s_nodes, dp_nodes, ln_c, ln_g = data[:4]
        g = meta['table']['grid']
        k, w = _ln_c_weights(ln_c, p.radial_clearance_m)
        lg = sum(w[j] * ln_g[:, :, k + j].astype(float) for j in range(4))
        q = np.exp(lg) * dp_nodes[None, :]
        n_s = s_nodes.size
        cells = []
        for side in (q[:n_s], q[n_s:]):  # open, then covered (rows at s = node, then -node)
            q00, q01, q10, q11 = side[:-1, :-1], side[:-1, 1:], side[1:, :-1], side[1:, 1:]
            cells.append(np.stack([q00, q01 - q00, q10 - q00, (q11 - q10) - (q01 - q00)], -1))
        table = np.ascontiguousarray(np.concatenate(cells, axis=0)).ravel()
        n_p = dp_nodes.size
        ic = np.array(_axis_consts(g['s_exp2'], g['s_log2_cells']) + [n_s - 2, n_s - 1]
                      + _axis_consts(g['dp_exp2'], g['dp_log2_cells']) + [n_p - 2, n_p - 1],
                      dtype=np.int64)
        fc = np.array([p.supply_pressure_pa, p.return_pressure_pa, 2.0 ** g['s_exp2'],
                       2.0 ** g['dp_exp2'], dp_nodes[-2], 1.0 / (dp_nodes[-1] - dp_nodes[-2])])
        return (table, ic, fc)
