"""Dynamic surrogates: the valve's metering edges learned, the fluid's dynamics kept.

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

Members (built by :mod:`eha_ros.training.dynamic`)
    ``dlut``: table of ``ln G`` over (s, |dp|, ln c), collapsed to the run's clearance, then
    bilinear per step (below); ``dnn``: a network ``features -> ln G``, see
    below; ``dga``: a closed form designed from the physics of an annular orifice,
    coefficients fitted by the genetic algorithm, then polished by a gradient fit from its
    best, see :func:`ga_edge_flow`.

The ``dlut`` table
    Its axes are spaced as float64 numbers are: :func:`log_axis` puts ``2^m`` equal cells in
    each octave of ``|x| + 2^e``, so a point's cell is the exponent and top ``m`` mantissa bits
    of ``|x| + 2^e`` and its weight the remaining bits (:func:`_log_cell`): no search and no
    index table, a few integer operations where a searched axis chains dependent loads.
    Openings ``|s|``: ``2^e`` = 1.9 um, 32 cells per octave (cells of 0.06 um at the edge,
    then steps of 1.6-3.1 % to the end of the stroke), a row per sign, a node at 0 where the
    edge uncovers; ``|dp|``: ``2^e`` = 1 Pa, 16 cells per octave, up to ``DP_MAX_PA``
    (``eha_ros.training.dynamic.DLUT_GRID``).  The cells hold ``q = G |dp|``, linear in the
    laminar limit (``q ~ dp``) and bent by at most 1/32 of a cell's relative width squared in the
    turbulent one (``q ~ sqrt|dp|``; tabulating ``G sqrt|dp|`` over ``sqrt|dp|``, linear in
    both, would put a square root ahead of the table loads in every step).  Prepared for a
    clearance, each cell stores the four coefficients of its bilinear form contiguously.
    Beyond ``DP_MAX_PA`` the last cell's line is extended (the flow keeps rising with the
    drop); openings beyond the stroke are held at the end of the axis.  Errors: the
    artefact's ``meta['errors']`` (``bench/surrogates_dynamic.py``).

The ``dnn`` network
    Inputs (:func:`dnn_features`, all logarithmic, the opening in units of the clearance):
    ``ln(1 + (s/c)^2) / 2`` while open (the gap of the truncated cone over the clearance),
    ``ln(1 - s/c)`` while covered (the laminar covered length), ``ln(1 + |dp| / dp0)`` and
    ``ln c``.  Two hidden layers of :data:`DNN_WIDTH` units with the activation
    ``x (15 - 10 x^2 + 3 x^4) / 8`` on ``x = clip(z, -1, 1)`` (a polynomial: no
    transcendental per unit), a linear output plus a linear skip term of the inputs (the
    orifice law's log-log asymptotes are linear in these inputs, the hidden layers learn the
    transitions).  Trained (:func:`eha_ros.training.dynamic.build_dnn`) on the hf edge equations
    with
    most points where the loop lives (openings within ~10 um of the edge, drops up to 1.1 x
    supply).  :meth:`DnnSurrogate._prepare` folds the clearance's input (constant within a
    run) and the
    normalisations into the weights; the kernel evaluates the four edges of a step as the
    four lanes of ``<4 x double>`` vectors, its LLVM IR generated for the fixed width
    (:func:`_dnn_flows`: logarithm and exponential from the floating-point bits and
    polynomials, no libm call).  :func:`dnn_numpy` is the same network in numpy.

Why the ``dnn`` kernel is hand-written IR
    A plain ``@njit`` kernel of the same network (loops over the four edges and the 16-unit
    layers, ``math.log1p``/``math.exp``, one scratch array per step) was measured against
    this one in the same process and load (plant at dt = 1 us, controller at 1 kHz, best of 5
    interleaved runs of 0.3 s of ``step_0p1`` and ``sine_0p1_10pi``, load average 2 on 2
    cores): 640-910 ns per plant step against 170-220 ns (3.8-4.1x), and 330-480 ns
    (1.9-2.2x) with ``fastmath`` and ``log`` for ``log1p``; hf 43-46 ns.  The bar for
    replacing it was 1.5x.
    The IR's own logarithm and exponential are tested against numpy over their whole input
    range (``test_dnn_ir_log_*``, ``test_dnn_ir_exp_*``): :func:`dnn_ir_log`,
    :func:`dnn_ir_exp`.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from eha_ros.artefacts import check_hash
from eha_ros.mlp import mlp_forward, split_weights
from eha_ros.physics import PlantParams, default_params, params_hash
from eha_ros.physics.maps import WEAR_RANGES, spool_grid
from eha_ros.physics.loop import CHAMBER_FLOWS, advance
from eha_ros.physics.valve import (edge_coefficients, edge_constants, fluid_constants,
                                   orifice_flow, valve_flows)
from eha_ros.surrogates.base import FluidSurrogate, Forms, SurrogateError

__all__ = ['EDGE_PARAMETERS', 'edge_hash', 'DP_MAX_PA', 'edge_flows', 'edge_conductance',
           'DynamicSurrogate', 'DlutSurrogate', 'DnnSurrogate', 'DgaSurrogate',
           'hf_chamber_flows',
           'dlut_kernel', 'log_axis', 'dnn_kernel', 'dga_kernel', 'ga_edge_flow', 'GA_GENES',
           'DNN_WIDTH', 'dnn_features', 'dnn_numpy', 'dnn_ir_log', 'dnn_ir_exp']

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


# --- kernels ----------------------------------------------------------------------------------

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


# --- dnn: the edge network, four edges at once, no libm call ---------------------------------

#: Hidden widths of ``dnn`` (two layers): fixed, the kernel's code is generated unrolled for
#: it; :meth:`DnnSurrogate._prepare` refuses an artefact of other widths.
DNN_WIDTH = 16

_SHIFTER = 6755399441055744.0  # 1.5 * 2^52: x + _SHIFTER rounds x to an integer in the low bits
_SHIFTER_BITS = 0x4338000000000000
_LOG2E = 1.4426950408889634
_LN2_HI = 0.6931471803691238
_LN2_LO = 1.9082149292705877e-10
_SQRT2 = 1.4142135623730951


def _v4_ir(builder):
    """IR helpers on ``<4 x double>`` (one lane per metering edge) for :func:`_dnn_flows`."""
    dbl = llvm_ir.DoubleType()
    i64 = llvm_ir.IntType(64)
    i32 = llvm_ir.IntType(32)
    v4 = llvm_ir.VectorType(dbl, 4)
    vi4 = llvm_ir.VectorType(i64, 4)
    undef = llvm_ir.Constant(v4, llvm_ir.Undefined)
    mask0 = llvm_ir.Constant(llvm_ir.VectorType(i32, 4), [0, 0, 0, 0])
    module = builder.module
    fma_fn = cgutils.get_or_insert_function(module, llvm_ir.FunctionType(v4, [v4, v4, v4]),
                                            'llvm.fma.v4f64')

    def const(x):
        return llvm_ir.Constant(v4, [float(x)] * 4)

    def iconst(x):
        return llvm_ir.Constant(vi4, [int(x)] * 4)

    def splat(x):
        return builder.shuffle_vector(builder.insert_element(undef, x, llvm_ir.Constant(i32, 0)),
                                      undef, mask0)

    def pack(xs):
        v = undef
        for e, x in enumerate(xs):
            v = builder.insert_element(v, x, llvm_ir.Constant(i32, e))
        return v

    def fma(a, b, c):
        return builder.call(fma_fn, [a, b, c])

    def sel(cond, a, b):
        return builder.select(cond, a, b)

    def poly(x, coeffs):
        """Polynomial, coefficients highest power first, by Estrin's scheme (pairs
        ``c_2k + c_2k+1 x``, then powers ``x^2, x^4, ...``: a short dependency chain, the
        plant's next step waits for this one)."""
        terms = [const(c) for c in reversed(coeffs)]  # lowest power first
        xp = x
        while len(terms) > 1:
            nxt = [fma(terms[i + 1], xp, terms[i]) for i in range(0, len(terms) - 1, 2)]
            if len(terms) % 2:
                nxt.append(terms[-1])
            terms = nxt
            if len(terms) > 1:
                xp = builder.fmul(xp, xp)
        return terms[0]

    def total(vals):
        """Sum by a balanced tree (short dependency chain)."""
        while len(vals) > 1:
            nxt = [builder.fadd(vals[i], vals[i + 1]) for i in range(0, len(vals) - 1, 2)]
            if len(vals) % 2:
                nxt.append(vals[-1])
            vals = nxt
        return vals[0]

    def log(x):
        """``ln x`` (``x`` normal, > 0): the exponent from the bits, ``2 atanh(z)``,
        ``z = (m - 1) / (m + 1)``, of the mantissa ``m`` in [sqrt(1/2), sqrt(2)] (odd series to
        ``z^13``, ``|z| <= 0.172``).  Absolute error at most the series' truncation,
        ``2 z^15 / (15 (1 - z^2))`` < 4.6e-13 at the ends of the mantissa range, plus
        rounding; a few ulp where ``x`` is near 1 (``z`` small)."""
        bits = builder.bitcast(x, vi4)
        e = builder.sub(builder.and_(builder.lshr(bits, iconst(52)), iconst(0x7FF)),
                        iconst(1023))
        m = builder.bitcast(builder.or_(builder.and_(bits, iconst(0xFFFFFFFFFFFFF)),
                                        iconst(0x3FF0000000000000)), v4)
        big = builder.fcmp_ordered('>', m, const(_SQRT2))
        m = sel(big, builder.fmul(m, const(0.5)), m)
        e = builder.add(e, builder.zext(big, vi4))
        ef = builder.fsub(builder.bitcast(builder.add(e, iconst(_SHIFTER_BITS)), v4),
                          const(_SHIFTER))
        z = builder.fdiv(builder.fsub(m, const(1.0)), builder.fadd(m, const(1.0)))
        z2 = builder.fmul(z, z)
        s = poly(z2, [1.0 / 13.0, 1.0 / 11.0, 1.0 / 9.0, 1.0 / 7.0, 0.2, 1.0 / 3.0, 1.0])
        lm = builder.fmul(builder.fmul(const(2.0), z), s)
        return builder.fadd(builder.fmul(ef, const(_LN2_HI)),
                            builder.fadd(lm, builder.fmul(ef, const(_LN2_LO))))

    def exp(y):
        """``exp(y)`` for ``|y| < 700``: ``y = n ln2 + f`` (``n`` rounded by adding and
        subtracting 1.5 * 2^52), the Taylor polynomial of degree 11 of ``exp(f)``,
        ``|f| <= ln2 / 2``, and ``2^n`` written into the exponent bits.  Relative error at most
        the truncation, ``(ln2 / 2)^12 / 12!`` < 6.4e-15, plus rounding (up to 16 ulp)."""
        kd = builder.fadd(builder.fmul(y, const(_LOG2E)), const(_SHIFTER))
        n = builder.fsub(kd, const(_SHIFTER))
        f = builder.fsub(builder.fsub(y, builder.fmul(n, const(_LN2_HI))),
                         builder.fmul(n, const(_LN2_LO)))
        p = poly(f, [1.0 / math.factorial(i) for i in range(11, -1, -1)])
        scale = builder.shl(builder.add(builder.sub(builder.bitcast(kd, vi4),
                                                    iconst(_SHIFTER_BITS)), iconst(1023)),
                            iconst(52))
        return builder.fmul(p, builder.bitcast(scale, v4))

    def quintic_v(z):
        """The hidden activation: ``x (15 - 10 x^2 + 3 x^4) / 8``, ``x`` = ``z`` clipped to
        [-1, 1] (odd, twice continuously differentiable, saturating like tanh; the training's
        ``quintic``, :func:`eha_ros.training.networks.make_torch_mlp`)."""
        one, mone = const(1.0), const(-1.0)
        z = sel(builder.fcmp_ordered('<', z, mone), mone, z)
        x = sel(builder.fcmp_ordered('>', z, one), one, z)
        x2 = builder.fmul(x, x)
        return builder.fmul(x, fma(x2, fma(x2, const(0.375), const(-1.25)), const(1.875)))

    return {'const': const, 'splat': splat, 'pack': pack, 'fma': fma, 'sel': sel, 'log': log,
            'total': total,
            'exp': exp, 'quintic': quintic_v, 'v4': v4, 'i32': i32, 'i64': i64}


@intrinsic
def _dnn_flows(typingctx, w1, b1, w2, b2, w3, k, s4, dp4):
    """The four edges' flows [m^3/s] through the prepared network, computed on
    ``<4 x double>`` vectors (one lane per edge) written directly in LLVM IR: the features,
    both layers (unrolled for :data:`DNN_WIDTH`), the output and its exponential.  ``s4``,
    ``dp4``: the openings [m] and pressure drops [Pa] of the four edges.  The arithmetic of
    :func:`dnn_numpy` (fused multiply-adds; logarithm and exponential without libm, which
    does not vectorise here)."""
    ret = types.UniTuple(types.float64, 4)
    sig = ret(w1, b1, w2, b2, w3, k, s4, dp4)

    def codegen(context, builder, signature, args):
        v = _v4_ir(builder)
        const, splat, fma, sel = v['const'], v['splat'], v['fma'], v['sel']
        ptr = [context.make_array(ty)(context, builder, val).data
               for ty, val in zip(signature.args[:6], args[:6])]
        pw1, pb1, pw2, pb2, pw3, pk = ptr

        def ld(p, i):
            return builder.load(builder.gep(p, [llvm_ir.Constant(v['i64'], i)]))

        s = v['pack']([builder.extract_value(args[6], e) for e in range(4)])
        dp = v['pack']([builder.extract_value(args[7], e) for e in range(4)])
        r = builder.fmul(s, splat(ld(pk, 3)))
        is_open = builder.fcmp_ordered('>', s, const(0.0))
        lg = v['log'](sel(is_open, fma(r, r, const(1.0)), builder.fsub(const(1.0), r)))
        f_open = sel(is_open, builder.fmul(lg, const(0.5)), const(0.0))
        f_cov = sel(is_open, const(0.0), lg)
        adp = builder.bitcast(builder.and_(builder.bitcast(dp, llvm_ir.VectorType(v['i64'], 4)),
                                           llvm_ir.Constant(llvm_ir.VectorType(v['i64'], 4),
                                                            [0x7FFFFFFFFFFFFFFF] * 4)),
                              v['v4'])
        dpm = splat(ld(pk, 5))
        adp = sel(builder.fcmp_ordered('<', adp, dpm), adp, dpm)
        f_dp = v['log'](fma(adp, splat(ld(pk, 4)), const(1.0)))
        h = DNN_WIDTH
        h1 = []
        for j in range(h):
            z = fma(splat(ld(pw1, j)), f_open, splat(ld(pb1, j)))
            z = fma(splat(ld(pw1, h + j)), f_cov, z)
            h1.append(v['quintic'](fma(splat(ld(pw1, 2 * h + j)), f_dp, z)))
        y = fma(splat(ld(pk, 6)), f_open, splat(ld(pk, 2)))
        y = fma(splat(ld(pk, 7)), f_cov, y)
        y = fma(splat(ld(pk, 8)), f_dp, y)
        # each unit's sum in four partial chains, the output's by a tree: the plant's next
        # step waits for this one, so the dependency chains are kept short
        outs = [y]
        for j in range(h):
            part = []
            for i0 in range(4):
                a = splat(ld(pb2, j)) if i0 == 0 else None
                for i in range(i0, h, 4):
                    w = splat(ld(pw2, i * h + j))
                    a = builder.fmul(w, h1[i]) if a is None else fma(w, h1[i], a)
                part.append(a)
            outs.append(builder.fmul(splat(ld(pw3, j)), v['quintic'](v['total'](part))))
        y = v['total'](outs)
        q = builder.fmul(dp, v['exp'](y))
        out = [builder.extract_element(q, llvm_ir.Constant(v['i32'], e)) for e in range(4)]
        return context.make_tuple(builder, signature.return_type, out)

    return sig, codegen


def _v4_unary_intrinsic(name):
    """An intrinsic applying the helper ``name`` of :func:`_v4_ir` (``'log'`` or ``'exp'``) to
    a 4-tuple of float64, lane by lane: the helpers as the kernel uses them, for tests."""
    @intrinsic
    def _apply(typingctx, x4):
        sig = types.UniTuple(types.float64, 4)(x4)

        def codegen(context, builder, signature, args):
            v = _v4_ir(builder)
            x = v['pack']([builder.extract_value(args[0], e) for e in range(4)])
            y = v[name](x)
            out = [builder.extract_element(y, llvm_ir.Constant(v['i32'], e)) for e in range(4)]
            return context.make_tuple(builder, signature.return_type, out)

        return sig, codegen

    return _apply


_v4_log = _v4_unary_intrinsic('log')
_v4_exp = _v4_unary_intrinsic('exp')


@njit(cache=True)
def _v4_map(which, x, out):
    """``out = log(x)`` (``which == 0``) or ``exp(x)`` (1) by the kernel's IR helpers, four
    values at a time (``x.size`` a multiple of 4)."""
    for i in range(0, x.size, 4):
        t = (x[i], x[i + 1], x[i + 2], x[i + 3])
        y = _v4_log(t) if which == 0 else _v4_exp(t)
        out[i], out[i + 1], out[i + 2], out[i + 3] = y


def dnn_ir_log(x) -> np.ndarray:
    """``ln x`` by the kernel's own logarithm (:func:`_v4_ir`), for tests (``x`` normal, > 0)."""
    return _dnn_ir_map(0, x)


def dnn_ir_exp(y) -> np.ndarray:
    """``exp y`` by the kernel's own exponential (:func:`_v4_ir`), for tests (``|y| < 700``)."""
    return _dnn_ir_map(1, y)


def _dnn_ir_map(which, x):
    a = np.asarray(x, dtype=float).ravel()
    n = a.size
    buf = np.ones(-(-n // 4) * 4)
    buf[:n] = a
    out = np.empty_like(buf)
    _v4_map(which, buf, out)
    return out[:n].reshape(np.shape(x))


@njit(cache=True)
def dnn_kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m):
    """(Q1L, Q2L) [m^3/s], the four edges (1S, 1R, 2R, 2S) through the network ``ln G`` as
    one batch of four SIMD lanes (:func:`_dnn_flows`).

    ``data = (w1, b1, w2, b2, w3, consts)`` from :meth:`DnnSurrogate._prepare`: the first layer
    ``(3, DNN_WIDTH)`` on the per-step features of :func:`dnn_features` (the input
    normalisation and the clearance's feature folded into ``b1``), the second layer
    ``(DNN_WIDTH, DNN_WIDTH)``, the output row ``w3`` (output normalisation folded in),
    ``consts = [ps, pr, b3, 1/c, 1/dp0, dp_max, skip_open, skip_cov, skip_dp]`` (``b3`` and
    the linear skip term with the normalisations folded in).  No libm call.
    """
    k = data[5]
    ps = k[0]
    pr = k[1]
    q1s, q1r, q2r, q2s = _dnn_flows(
        data[0], data[1], data[2], data[3], data[4], k,
        (xs_m - lap_supply_m, -xs_m - lap_return_m, xs_m - lap_return_m, -xs_m - lap_supply_m),
        (ps - p1_pa, p1_pa - pr, p2_pa - pr, ps - p2_pa))
    return q1s - q1r, q2r - q2s


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


# The plant's loop and the loop over points with each kernel: the kernel a global of its forms,
# not an argument, so that they are cached on disk (:class:`.base.Forms`).

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


@njit(cache=True)
def _run_dnn(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, None, dnn_kernel, data, False)


@njit(cache=True)
def _run_split_dnn(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, None, dnn_kernel, data, True)


@njit(cache=True)
def _points_dnn(data, xs, p1, p2, lap_s, lap_r, out1, out2):
    for i in range(xs.size):
        out1[i], out2[i] = dnn_kernel(data, xs[i], p1[i], p2[i], lap_s[i], lap_r[i])


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


#: The compiled forms of :func:`dlut_kernel`, :func:`dnn_kernel` and :func:`dga_kernel`.
DLUT_FORMS = Forms(_run_dlut, _run_split_dlut, _points_dlut)


DNN_FORMS = Forms(_run_dnn, _run_split_dnn, _points_dnn)


DGA_FORMS = Forms(_run_dga, _run_split_dga, _points_dga)


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


# --- preparation per wear ---------------------------------------------------------------------

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


def dnn_features(s_m, dp_pa, clearance_m, dp_scale_pa: float) -> np.ndarray:
    """The network inputs of ``dnn`` ``(N, 4)`` (numpy; the kernel computes the same per
    step, :func:`_dnn_flows`): the opening in units of the clearance, ``r = s / c``, as
    ``ln(1 + r^2) / 2`` while open (``ln(h / c)``, ``h`` the gap of the truncated cone) and
    ``ln(1 - r)`` while covered (the laminar covered length), each 0 on the other side;
    ``ln(1 + min(|dp|, DP_MAX_PA) / dp_scale_pa)``; ``ln c``."""
    s, dp, c = np.broadcast_arrays(*(np.asarray(a, dtype=float).ravel()
                                     for a in (s_m, dp_pa, clearance_m)))
    r = s / c
    f_open = np.where(s > 0.0, 0.5 * np.log1p(np.maximum(r, 0.0) ** 2), 0.0)
    f_cov = np.where(s > 0.0, 0.0, np.log1p(np.maximum(-r, 0.0)))
    f_dp = np.log1p(np.minimum(np.abs(dp), DP_MAX_PA) / dp_scale_pa)
    return np.stack([f_open, f_cov, f_dp, np.log(c)], axis=1)


def dnn_numpy(data, s_m, dp_pa, clearance_m) -> np.ndarray:
    """Edge flow [m^3/s] of a ``dnn`` artefact's network evaluated as trained (numpy, float64,
    no folding; the reference the kernel is checked against)."""
    sizes = [int(v) for v in data[0]]
    mid, half = (np.asarray(v, dtype=float) for v in data[1])
    theta = np.asarray(data[3], dtype=float)
    z = (dnn_features(s_m, dp_pa, clearance_m, float(data[4][0])) - mid) / half
    h = mlp_forward(split_weights(theta[:-sizes[0]], sizes), z, 'quintic')
    y = float(data[2][0]) + float(data[2][1]) * (h[:, 0] + z @ theta[-sizes[0]:])
    dp = np.broadcast_arrays(np.asarray(dp_pa, dtype=float).ravel(), y)[0]
    return dp * np.exp(y)


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
        idx = len(data) - 1  # every kind keeps [ps, pr, ...] last
        data[idx] = data[idx].copy()
        s = np.ascontiguousarray(s_m, dtype=float).ravel()
        dp = np.ascontiguousarray(np.broadcast_to(np.asarray(dp_pa, dtype=float), s.shape))
        out = np.empty(s.size)
        _edge_loop(self.kernel, tuple(data), data[idx], s, dp, out)
        return out

    def p12(self, *args, **kwargs):
        raise SurrogateError(f'surrogate {self.name} is dynamic: it gives chamber flows '
                             '(chamber_flow), not an algebraic P12')


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


class DnnSurrogate(DynamicSurrogate):
    """``dnn``: the edge network, the clearance folded into its weights
    (:meth:`DnnSurrogate._prepare`)."""

    def _prepare(self, p: PlantParams) -> tuple:
        """Fold the input and output normalisations and the clearance's feature (constant within
        a run) into the weights: the kernel's first layer sees the opening and pressure-drop
        features only, its output is ``ln G`` directly.  ``data = (sizes, input_norm, output_norm,
        theta, [dp_scale_pa])`` (:func:`eha_ros.training.dynamic.build_dnn`)."""
        data, meta = self.data, self.meta
        sizes = [int(v) for v in data[0]]
        arch = meta.get('architecture', {})
        act = arch.get('activation')
        if act != 'quintic' or sizes != [4, DNN_WIDTH, DNN_WIDTH, 1] or not arch.get('skip'):
            raise SurrogateError(f'dnn artefact has layer widths {sizes}, activation {act!r}; the '
                                 f'kernel evaluates [4, {DNN_WIDTH}, {DNN_WIDTH}, 1], quintic, '
                                 'with the linear skip term: '
                                 f'rebuild it with python -m {self.rebuild}')
        mid, half = (np.asarray(v, dtype=float) for v in data[1])
        out_mid, out_half = (float(v) for v in data[2])
        theta = np.asarray(data[3], dtype=float)
        (w1, b1), (w2, b2), (w3, b3) = split_weights(theta[:-4], sizes)
        skip = theta[-4:]
        dp_scale = float(data[4][0])
        zc = (math.log(p.radial_clearance_m) - mid[3]) / half[3]
        w1f = w1[:3] / half[:3, None]
        b1f = b1 - (mid[:3] / half[:3]) @ w1[:3] + zc * w1[3]
        b3f = float(b3[0]) - float(skip[:3] @ (mid[:3] / half[:3])) + zc * float(skip[3])
        consts = np.array([p.supply_pressure_pa, p.return_pressure_pa,
                           out_mid + out_half * b3f, 1.0 / p.radial_clearance_m,
                           1.0 / dp_scale, DP_MAX_PA, *(out_half * skip[:3] / half[:3])])
        return (np.ascontiguousarray(w1f), np.ascontiguousarray(b1f), np.ascontiguousarray(w2),
                np.ascontiguousarray(b2), np.ascontiguousarray(out_half * w3[:, 0]), consts)


class DgaSurrogate(DynamicSurrogate):
    """``dga``: the designed edge formula with the clearance's terms evaluated once."""

    def _prepare(self, p: PlantParams) -> tuple:
        k_lam, n_lam, k_turb, k_rey = (float(v) for v in self.data[0])
        c = p.radial_clearance_m
        cf = np.array([c * c, k_lam / c ** n_lam, k_turb, k_rey])
        return (cf, np.array([p.supply_pressure_pa, p.return_pressure_pa]))


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
