"""The LLVM IR of the ``dnn`` kernel (:mod:`.dnn`): :func:`dnn_flows` evaluates the prepared
network for the four metering edges of a step as the four lanes of ``<4 x double>`` vectors,
with its own logarithm and exponential (:func:`_v4_ir`), tested against numpy over their whole
input range (``test_dnn_ir_log_*``, ``test_dnn_ir_exp_*``) through :func:`dnn_ir_log` and
:func:`dnn_ir_exp`.

Why the kernel is hand-written IR: a plain ``@njit`` kernel of the same network (loops over the
four edges and the 16-unit layers, ``math.log1p``/``math.exp``, one scratch array per step) was
measured against this one in the same process and load (plant at dt = 1 us, controller at
1 kHz, best of 5 interleaved runs of 0.3 s of ``step_0p1`` and ``sine_0p1_10pi``, load average 2
on 2 cores): 640-910 ns per plant step against 170-220 ns (3.8-4.1x), and 330-480 ns
(1.9-2.2x) with ``fastmath`` and ``log`` for ``log1p``; hf 43-46 ns.  The bar for replacing it
was 1.5x.
"""

import math

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ['DNN_WIDTH', 'dnn_flows', 'dnn_ir_log', 'dnn_ir_exp']

#: Hidden widths of ``dnn`` (two layers): fixed, the kernel's code is generated unrolled for
#: it; :meth:`.dnn.DnnSurrogate._prepare` refuses an artefact of other widths.
DNN_WIDTH = 16

_SHIFTER = 6755399441055744.0  # 1.5 * 2^52: x + _SHIFTER rounds x to an integer in the low bits
_SHIFTER_BITS = 0x4338000000000000
_LOG2E = 1.4426950408889634
_LN2_HI = 0.6931471803691238
_LN2_LO = 1.9082149292705877e-10
_SQRT2 = 1.4142135623730951


def _v4_ir(builder):
    """IR helpers on ``<4 x double>`` (one lane per metering edge) for :func:`dnn_flows`."""
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
def dnn_flows(typingctx, w1, b1, w2, b2, w3, k, s4, dp4):
    """The four edges' flows [m^3/s] through the prepared network, computed on
    ``<4 x double>`` vectors (one lane per edge) written directly in LLVM IR: the features,
    both layers (unrolled for :data:`DNN_WIDTH`), the output and its exponential.  ``s4``,
    ``dp4``: the openings [m] and pressure drops [Pa] of the four edges.  The arithmetic of
    :func:`.dnn.dnn_numpy` (fused multiply-adds; logarithm and exponential without libm, which
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
