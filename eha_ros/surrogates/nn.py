"""Neural-network surrogates of the fluid-dynamic block (the reference's sections 5.4.2 and
6.3.1): ``P12 = f(XS, Q, overlap, clearance)`` (``nn``) and, for the loop, ``P12 = f(XS, Q)``
at the nominal wear (``nn2``).

Network
    A fully connected multilayer perceptron, tanh hidden layers and a linear output.  Every
    input is first transformed - identity, or ``asinh(x / scale)`` for the spool position, whose
    map grid is ``x = stroke sinh(4 u) / sinh(4)``, so that the transformed grid is uniform - and
    then mapped to [-1, 1] by a min-max normalisation fitted on the training split; the output is
    normalised the same way.  The normalisation is saved with the weights.  Both shipped
    networks use the reference's hidden layers [21 15 3] and the identity transform: the asinh
    transform of XS spends the network's resolution on the null region at the expense of the
    rest (the artefacts' meta ``comparison`` records both).

Inference (numpy and numba only)
    One generic numba kernel, ``mlp`` (:func:`mlp_kernel`), evaluates any artefact of this
    module; the data tuple packs the layout, the input transforms and normalisation, the output
    normalisation and the weights.  Which of the four kernel inputs the network reads is part of
    the data, so the 2-input network ignores the wear arguments.  The kernel works on a stack
    buffer and allocates nothing.

Error metric, data (which databases, which maps are held out), training and the build of the
shipped artefacts: :mod:`eha_ros.training.nn` (``python -m eha_ros.training.nn``, about an
hour on two cores), on the shared trainer of :mod:`eha_ros.training.networks`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from eha_ros.mlp import mlp_forward, split_weights
from eha_ros.physics.loop import advance
from eha_ros.surrogates.base import Forms, SurrogateError

__all__ = ['INPUT_NAMES', 'INPUT_UNITS', 'MAX_WIDTH', 'LINEAR', 'ASINH', 'mlp_kernel',
           'mlp_numpy', 'pack', 'unpack', 'transform_inputs', 'fit_inputs', 'fit_output']

#: The kernel's inputs, in order, and their units.
INPUT_NAMES = ('xs_m', 'q_m3_s', 'overlap_m', 'clearance_m')
INPUT_UNITS = ('m', 'm^3/s', 'm', 'm')

#: Input transforms: ``x/scale``, ``asinh(x/scale)``, and ``asinh`` of the positive or the
#: negative part of ``x/scale`` (two inputs that let a network represent a kink at x = 0).
LINEAR, ASINH, ASINH_POS, ASINH_NEG = 0, 1, 2, 3
_TRANSFORMS = {'linear': LINEAR, 'asinh': ASINH, 'asinh_pos': ASINH_POS,
               'asinh_neg': ASINH_NEG}

#: Widest layer the kernel evaluates (its stack buffer holds two layers).
MAX_WIDTH = 128

#: Density of the spool grid (:func:`eha_ros.physics.maps.spool_grid`); the asinh transform of
#: XS uses ``scale = stroke / sinh(density)`` so that the map grid becomes uniform.
SPOOL_GRID_DENSITY = 4.0


# --- inference: numba kernel and numpy reference --------------------------------------------

@intrinsic
def _stack_buffer_ptr(typingctx):
    """Pointer to ``2 * MAX_WIDTH`` float64 on the caller's stack (an entry-block alloca)."""
    def codegen(context, builder, signature, args):
        ty = context.get_value_type(types.float64)
        return cgutils.alloca_once(builder, ty,
                                   size=context.get_constant(types.intp, 2 * MAX_WIDTH))
    return types.CPointer(types.float64)(), codegen


@njit(cache=True, inline='always')
def _stack_buffer():
    return carray(_stack_buffer_ptr(), (2 * MAX_WIDTH,))


@njit(cache=True)
def mlp_kernel(data, xs_m, q_m3_s, overlap_m, clearance_m):
    """P12 [Pa] of a packed MLP (see :func:`pack`) at one point; allocation-free.

    ``data = (layout, inputs, output, theta)``: ``layout = [n_in, n_layers, d_0, ..., d_L]``;
    ``inputs[i] = [source, transform, scale, mid, half]`` (source 0..3 = XS, Q, overlap,
    clearance); ``output = [mid, half]``; ``theta`` the weights, layer by layer ``W`` (row-major,
    ``d_in x d_out``: the layer computes ``h @ W + b``) then ``b``.
    """
    layout = data[0]
    inputs = data[1]
    output = data[2]
    theta = data[3]
    buf = _stack_buffer()
    n_in = int(layout[0])
    n_layers = int(layout[1])
    for i in range(n_in):
        src = int(inputs[i, 0])
        if src == 0:
            x = xs_m
        elif src == 1:
            x = q_m3_s
        elif src == 2:
            x = overlap_m
        else:
            x = clearance_m
        g = x / inputs[i, 2]
        kind = inputs[i, 1]
        if kind == 1.0:
            g = math.asinh(g)
        elif kind == 2.0:
            g = math.asinh(max(g, 0.0))
        elif kind == 3.0:
            g = math.asinh(max(-g, 0.0))
        buf[i] = (g - inputs[i, 3]) / inputs[i, 4]
    a = 0
    b = MAX_WIDTH
    k = 0
    d_prev = n_in
    for lay in range(n_layers):
        d = int(layout[3 + lay])
        kb = k + d * d_prev
        for j in range(d):
            buf[b + j] = theta[kb + j]
        # input-major order: the inner loop over the layer's units carries no dependency
        for i in range(d_prev):
            h = buf[a + i]
            row = k + i * d
            for j in range(d):
                buf[b + j] += theta[row + j] * h
        if lay < n_layers - 1:
            for j in range(d):
                # tanh through exp: a third of libm tanh's cost, within 1e-16 of it
                buf[b + j] = 1.0 - 2.0 / (math.exp(2.0 * buf[b + j]) + 1.0)
        k = kb + d
        a, b = b, a
        d_prev = d
    return output[0] + output[1] * buf[a]


@njit(cache=True)
def _run_mlp(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, mlp_kernel, None, data, False)


@njit(cache=True)
def _run_split_mlp(s, i_cmd, p, clock, loop, data):
    return advance(s, i_cmd, p, clock, loop, mlp_kernel, None, data, True)


@njit(cache=True)
def _points_mlp(data, xs, q, lap, clr, out):
    for i in range(xs.size):
        out[i] = mlp_kernel(data, xs[i], q[i], lap[i], clr[i])


#: The compiled forms of :func:`mlp_kernel`, cached on disk (:class:`.base.Forms`).
MLP_FORMS = Forms(_run_mlp, _run_split_mlp, _points_mlp)


def unpack(data) -> dict:
    """The packed tuple as named arrays: ``sizes``, ``inputs``, ``output``, ``weights`` (a list
    of ``(W, b)``)."""
    layout, inputs, output, theta = (np.asarray(a, dtype=float) for a in data)
    n_layers = int(layout[1])
    sizes = [int(v) for v in layout[2:3 + n_layers]]
    return {'sizes': sizes, 'inputs': inputs, 'output': output,
            'weights': split_weights(theta, sizes)}


def pack(sizes, inputs, output, theta) -> tuple:
    """The kernel's data tuple from layer sizes ``[d_0, ..., d_L]`` (``d_L = 1``), the input
    table ``(d_0, 5)``, the output normalisation ``[mid, half]`` and the flat weights."""
    sizes = [int(s) for s in sizes]
    if sizes[-1] != 1 or max(sizes) > MAX_WIDTH or sizes[0] > 4:
        raise SurrogateError(f'MLP sizes {sizes}: at most 4 inputs, one output, layers of at '
                             f'most {MAX_WIDTH}')
    n_theta = sum(do * di + do for di, do in zip(sizes[:-1], sizes[1:]))
    theta = np.ascontiguousarray(theta, dtype=float).ravel()
    if theta.size != n_theta:
        raise SurrogateError(f'MLP sizes {sizes} need {n_theta} weights, got {theta.size}')
    layout = np.array([sizes[0], len(sizes) - 1] + sizes, dtype=float)
    return (layout, np.ascontiguousarray(inputs, dtype=float),
            np.ascontiguousarray(output, dtype=float), theta)


def _transform(g, kind):
    if kind == ASINH:
        return np.arcsinh(g)
    if kind == ASINH_POS:
        return np.arcsinh(np.maximum(g, 0.0))
    if kind == ASINH_NEG:
        return np.arcsinh(np.maximum(-g, 0.0))
    return g


def transform_inputs(inputs, raw):
    """Normalised network inputs ``(N, n_in)`` from raw ``(N, 4)`` kernel inputs (numpy)."""
    z = np.empty((raw.shape[0], inputs.shape[0]))
    for i, (src, kind, scale, mid, half) in enumerate(inputs):
        z[:, i] = (_transform(raw[:, int(src)] / scale, kind) - mid) / half
    return z


def mlp_numpy(data, xs_m, q_m3_s, overlap_m=0.0, clearance_m=0.0):
    """Vectorised numpy forward pass of a packed MLP, P12 [Pa] for broadcastable inputs."""
    arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float)
                                 for a in (xs_m, q_m3_s, overlap_m, clearance_m)))
    raw = np.stack([a.ravel() for a in arrs], axis=1)
    u = unpack(data)
    h = mlp_forward(u['weights'], transform_inputs(u['inputs'], raw))
    out = u['output'][0] + u['output'][1] * h[:, 0]
    return out.reshape(arrs[0].shape)


@njit  # not cached: a kernel argument's type names the kernel object (see .base.Forms)
def _kernel_loop(kernel, data, xs, q, lap, clr):
    """Sum of ``kernel`` over the points, called as the plant calls it (used for timing)."""
    s = 0.0
    for i in range(xs.size):
        s += kernel(data, xs[i], q[i], lap[i], clr[i])
    return s


# --- normalisation ---------------------------------------------------------------------------

def fit_inputs(raw, sources, transforms, scales=None) -> np.ndarray:
    """Input table ``(n_in, 5)``: per used input ``[source, transform, scale, mid, half]`` with
    ``mid, half`` the min-max normalisation to [-1, 1] of the transformed ``raw[:, source]``
    (``raw`` the training split, ``(N, 4)``)."""
    rows = []
    for n, (src, tr) in enumerate(zip(sources, transforms)):
        kind = _TRANSFORMS[tr] if isinstance(tr, str) else int(tr)
        scale = 1.0 if scales is None or scales[n] is None else float(scales[n])
        g = _transform(raw[:, src] / scale, kind)
        lo, hi = float(g.min()), float(g.max())
        half = 0.5 * (hi - lo) if hi > lo else 1.0
        rows.append([src, kind, scale, 0.5 * (hi + lo), half])
    return np.array(rows, dtype=float)


def fit_output(y) -> np.ndarray:
    """Output normalisation ``[mid, half]`` (min-max to [-1, 1]) of the training targets."""
    lo, hi = float(np.min(y)), float(np.max(y))
    return np.array([0.5 * (hi + lo), 0.5 * (hi - lo) if hi > lo else 1.0])
