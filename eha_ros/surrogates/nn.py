"""Neural-network surrogates of the fluid-dynamic block (the reference's sections 5.4.2 and
6.3.1): ``P12 = f(XS, Q, overlap, clearance)`` (``nn``) and, for the loop, ``P12 = f(XS, Q)``
at the nominal wear (``nn2``).

Network
    A fully connected multilayer perceptron, tanh hidden layers and a linear output.  Every
    input is first transformed - identity, or ``asinh(x / scale)`` for the spool position, whose
    map grid is ``x = stroke sinh(4 u) / sinh(4)``, so that the transformed grid is uniform - and
    then mapped to [-1, 1] by a min-max normalisation fitted on the training split; the output is
    normalised the same way.  The normalisation is saved with the weights.  Both shipped
    networks use the reference's hidden layers [21 15 3] and the identity transform: with the
    same training budget the asinh transform of XS gave held-out map errors about twice as
    large (it spends the network's resolution on the null region at the expense of the rest).

Data
    ``nn`` is trained on DB2 and DB3 together (same wear grid; DB3's flows are the narrow
    range): trained on DB2 alone it is as good on DB2's flows but twice as bad on DB3's.
    Whole maps (``(overlap, clearance)`` pairs inside the wear grid) are held out for
    validation and testing, the same pairs in both databases.  ``nn2`` is trained on DB5 with
    every 7th flow curve held out for testing (the next one for validation).

Training (torch, imported inside the training functions only)
    Levenberg-Marquardt as MATLAB's ``trainlm`` (damping ``mu`` multiplied by ``mu_dec`` after a
    step that lowers the loss and by ``mu_inc`` until one does; ``(J'J + mu I) d = J'e`` with the
    Jacobian formed by hand, batched, on a random subset of the training points redrawn every
    ``resample_every`` epochs), and Adam followed by L-BFGS.  Both minimise the mean squared
    error of the normalised output (a loss weighted by ``1 / ||map||^2``, the metric's own
    weighting, was measured and not kept: it trades DB2's accuracy for DB3's at a loss
    overall).  :func:`train_fluid_network` trains with both and keeps the one with the lower
    validation error; the metadata holds both results.

Inference (numpy and numba only)
    One generic numba kernel, ``mlp`` (:func:`mlp_kernel`), evaluates any artefact of this
    module; the data tuple packs the layout, the input transforms and normalisation, the output
    normalisation and the weights.  Which of the four kernel inputs the network reads is part of
    the data, so the 2-input network ignores the wear arguments.  The kernel works on a stack
    buffer and allocates nothing.

Error metric (the reference's): the relative error in Euclidean norm over a map,
``||P_pred - P_true||_2 / ||P_true||_2`` with the map all spool positions x flows of one wear
pair.

Build: ``python -m eha_ros.surrogates.nn`` (:func:`build_artefacts`; about an hour on two
cores).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import spool_grid, transient_map

from .base import SurrogateError, models_dir, register_kernel, save_artefact
from .database import Database, fluid_hash, get_database, maps_at, random_wear

__all__ = ['INPUT_NAMES', 'INPUT_UNITS', 'MAX_WIDTH', 'mlp_kernel', 'mlp_numpy', 'pack',
           'unpack', 'split_weights', 'fit_inputs', 'fit_output', 'make_torch_mlp',
           'torch_from_data', 'train_lm', 'train_adam_lbfgs', 'map_split', 'map_errors',
           'offgrid_maps',
           'train_fluid_network', 'build_artefacts', 'NN_SETTINGS', 'NN2_SETTINGS']

#: The kernel's inputs, in order, and their units.
INPUT_NAMES = ('xs_m', 'q_m3_s', 'overlap_m', 'clearance_m')
INPUT_UNITS = ('m', 'm^3/s', 'm', 'm')

#: Input transforms.
LINEAR, ASINH = 0, 1
_TRANSFORMS = {'linear': LINEAR, 'asinh': ASINH}

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


@register_kernel('mlp')
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
        if inputs[i, 1] == 1.0:
            g = math.asinh(g)
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


def unpack(data) -> dict:
    """The packed tuple as named arrays: ``sizes``, ``inputs``, ``output``, ``weights`` (a list
    of ``(W, b)``)."""
    layout, inputs, output, theta = (np.asarray(a, dtype=float) for a in data)
    n_layers = int(layout[1])
    sizes = [int(v) for v in layout[2:3 + n_layers]]
    return {'sizes': sizes, 'inputs': inputs, 'output': output,
            'weights': split_weights(theta, sizes)}


def split_weights(theta, sizes) -> list:
    """``[(W, b), ...]`` of a dense network with layer widths ``sizes`` from the flat
    ``theta``: layer by layer ``W`` (row-major, ``d_in x d_out``) then ``b``.  Raises
    :class:`SurrogateError` when the widths do not account for ``theta`` exactly."""
    theta = np.asarray(theta, dtype=float)
    weights = []
    k = 0
    for di, do in zip(sizes[:-1], sizes[1:]):
        w = theta[k:k + di * do].reshape(di, do)
        k += di * do
        weights.append((w, theta[k:k + do]))
        k += do
    if k != theta.size:
        raise SurrogateError(f'{theta.size} weights for layer widths {list(sizes)} '
                             f'(which need {k})')
    return weights


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


def _transform_inputs(inputs, raw):
    """Normalised network inputs ``(N, n_in)`` from raw ``(N, 4)`` kernel inputs (numpy)."""
    z = np.empty((raw.shape[0], inputs.shape[0]))
    for i, (src, kind, scale, mid, half) in enumerate(inputs):
        g = raw[:, int(src)] / scale
        if kind == ASINH:
            g = np.arcsinh(g)
        z[:, i] = (g - mid) / half
    return z


def mlp_numpy(data, xs_m, q_m3_s, overlap_m=0.0, clearance_m=0.0):
    """Vectorised numpy forward pass of a packed MLP, P12 [Pa] for broadcastable inputs."""
    arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float)
                                 for a in (xs_m, q_m3_s, overlap_m, clearance_m)))
    raw = np.stack([a.ravel() for a in arrs], axis=1)
    u = unpack(data)
    h = _transform_inputs(u['inputs'], raw)
    for n, (w, b) in enumerate(u['weights']):
        h = h @ w + b
        if n < len(u['weights']) - 1:
            h = np.tanh(h)
    out = u['output'][0] + u['output'][1] * h[:, 0]
    return out.reshape(arrs[0].shape)


@njit  # not cached: a kernel argument's type names the kernel object (see physics.plant)
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
        g = raw[:, src] / scale
        if kind == ASINH:
            g = np.arcsinh(g)
        lo, hi = float(g.min()), float(g.max())
        half = 0.5 * (hi - lo) if hi > lo else 1.0
        rows.append([src, kind, scale, 0.5 * (hi + lo), half])
    return np.array(rows, dtype=float)


def fit_output(y) -> np.ndarray:
    """Output normalisation ``[mid, half]`` (min-max to [-1, 1]) of the training targets."""
    lo, hi = float(np.min(y)), float(np.max(y))
    return np.array([0.5 * (hi + lo), 0.5 * (hi - lo) if hi > lo else 1.0])


# --- torch model (training only) -------------------------------------------------------------

def _torch():
    import torch
    return torch


def make_torch_mlp(*, d_in: int, d_hidden: list, d_out: int = 1, seed: int = 0):
    """A tanh MLP as a torch module (float64) with its weights in one flat parameter ``theta``
    laid out as the kernel reads them.  Weights: Glorot-uniform from ``seed``, biases zero."""
    torch = _torch()

    class MLP(torch.nn.Module):
        def __init__(self, *, d_in, d_hidden, d_out):
            super().__init__()
            self.config = {'d_in': int(d_in), 'd_hidden': [int(h) for h in d_hidden],
                           'd_out': int(d_out)}
            self.sizes = [self.config['d_in'], *self.config['d_hidden'], self.config['d_out']]
            self.theta = torch.nn.Parameter(torch.zeros(
                sum(do * di + do for di, do in zip(self.sizes[:-1], self.sizes[1:])),
                dtype=torch.float64))

        def layers(self, theta=None):
            theta = self.theta if theta is None else theta
            k = 0
            out = []
            for di, do in zip(self.sizes[:-1], self.sizes[1:]):
                w = theta[k:k + do * di].view(di, do)
                k += do * di
                out.append((w, theta[k:k + do]))
                k += do
            return out

        def forward(self, x, theta=None):
            ws = self.layers(theta)
            h = x
            for n, (w, b) in enumerate(ws):
                h = torch.addmm(b, h, w)
                if n < len(ws) - 1:
                    h = torch.tanh(h)
            return h

        @torch.no_grad()
        def jacobian(self, x):
            """``(N * d_out, P)`` derivative of the outputs (row ``n * d_out + o``) with
            respect to ``theta``, by hand: one batched backward sweep per output."""
            ws = self.layers()
            acts = [x]
            h = x
            for w, b in ws[:-1]:
                h = torch.tanh(torch.addmm(b, h, w))
                acts.append(h)
            n_pts = x.shape[0]
            d_out = self.sizes[-1]
            jac = torch.empty((n_pts, d_out, self.theta.numel()), dtype=x.dtype)
            for o in range(d_out):
                delta = torch.zeros((n_pts, d_out), dtype=x.dtype)
                delta[:, o] = 1.0
                k_end = self.theta.numel()
                for n in range(len(ws) - 1, -1, -1):
                    w, _ = ws[n]
                    di, do = w.shape
                    jac[:, o, k_end - do:k_end] = delta
                    jac[:, o, k_end - do - do * di:k_end - do] = (
                        acts[n][:, :, None] * delta[:, None, :]).reshape(n_pts, di * do)
                    k_end -= do + do * di
                    if n > 0:
                        delta = (delta @ w.T) * (1.0 - acts[n] ** 2)
            return jac.reshape(n_pts * d_out, -1)

    model = MLP(d_in=d_in, d_hidden=d_hidden, d_out=d_out)
    gen = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        for w, b in model.layers():
            lim = math.sqrt(6.0 / (w.shape[0] + w.shape[1]))  # Glorot
            w.copy_((torch.rand(w.shape, generator=gen, dtype=torch.float64) * 2 - 1) * lim)
            b.zero_()
    return model


def torch_from_data(data):
    """Rebuild the torch module of a packed MLP (for checks against the exported kernel)."""
    torch = _torch()
    u = unpack(data)
    model = make_torch_mlp(d_in=u['sizes'][0], d_hidden=u['sizes'][1:-1], d_out=u['sizes'][-1])
    with torch.no_grad():
        model.theta.copy_(torch.as_tensor(np.asarray(data[3], dtype=float)))
    return model.eval()


# --- training --------------------------------------------------------------------------------

def _mse(model, x, y, w=None):
    """(Weighted) mean squared error; ``w`` one weight per row of ``x``."""
    torch = _torch()
    model.eval()
    with torch.no_grad():
        r2 = (model(x) - y) ** 2
        return float(torch.mean(r2 if w is None else r2 * w[:, None]))


def train_lm(model, x, y, *, x_val=None, y_val=None, w=None, w_val=None,
             epochs: int = 1000, mu: float = 1e-3,
             mu_dec: float = 0.1, mu_inc: float = 10.0, mu_max: float = 1e10,
             max_fail: int = 50, subsample: int = 20000, resample_every: int = 0,
             min_grad: float = 1e-12, time_limit_s: float = float('inf'), seed: int = 0,
             threads: int = 2) -> dict:
    """Levenberg-Marquardt on the mean squared error (MATLAB's ``trainlm``).

    Each epoch solves ``(J'J + mu I) d = J'e`` on at most ``subsample`` training points (drawn
    from ``seed``; redrawn every ``resample_every`` epochs, never if 0), accepts the step if it
    lowers the loss (``mu *= mu_dec``) and otherwise retries with ``mu *= mu_inc``.  Stops at
    ``epochs``, ``mu > mu_max``, a gradient norm below ``min_grad``, ``max_fail`` epochs
    without a better validation loss, or ``time_limit_s``.  The parameters of the best
    validation epoch (of the last epoch without validation data) are kept.  ``w``, ``w_val``:
    optional weights of the training and validation points (weighted least squares).

    Returns the history: ``loss``, ``val``, ``mu`` per epoch, ``epochs``, ``stop``, ``time_s``.
    """
    torch = _torch()
    torch.set_num_threads(threads)
    gen = np.random.default_rng(seed)
    n = x.shape[0]

    w = torch.ones(n, dtype=x.dtype) if w is None else w

    def draw():
        if n <= subsample:
            return x, y, w
        idx = torch.as_tensor(np.sort(gen.choice(n, subsample, replace=False)))
        return x[idx], y[idx], w[idx]

    xs, ys, ws = draw()
    t0 = time.perf_counter()
    hist = {'loss': [], 'val': [], 'mu': []}
    best = (math.inf, model.theta.detach().clone())
    fails = 0
    stop = 'epochs'
    eye = torch.eye(model.theta.numel(), dtype=torch.float64)
    theta = model.theta
    for ep in range(epochs):
        if resample_every and ep and ep % resample_every == 0:
            xs, ys, ws = draw()
        with torch.no_grad():
            sw = torch.sqrt(ws).repeat_interleave(ys.shape[1])
            e = (model(xs) - ys).reshape(-1) * sw
            loss = float(torch.mean(e ** 2))
            jac = model.jacobian(xs) * sw[:, None]
            hess = jac.T @ jac
            grad = jac.T @ e
            if float(torch.linalg.vector_norm(grad)) / e.numel() < min_grad:
                stop = 'min_grad'
                break
            theta0 = theta.detach().clone()
            while True:
                lhs = hess + mu * eye
                chol, info = torch.linalg.cholesky_ex(lhs)
                if int(info) == 0:
                    step = torch.cholesky_solve(grad[:, None], chol)[:, 0]
                    theta.copy_(theta0 - step)
                    new = _mse(model, xs, ys, ws)
                    if new < loss:
                        mu = max(mu * mu_dec, 1e-20)
                        loss = new
                        break
                mu *= mu_inc
                if mu > mu_max:
                    break
            if mu > mu_max:
                theta.copy_(theta0)
                stop = 'mu_max'
                break
        hist['loss'].append(loss)
        hist['mu'].append(mu)
        if x_val is not None:
            v = _mse(model, x_val, y_val, w_val)
            hist['val'].append(v)
            if v < best[0]:
                best = (v, model.theta.detach().clone())
                fails = 0
            else:
                fails += 1
                if fails >= max_fail:
                    stop = 'max_fail'
                    break
        if time.perf_counter() - t0 > time_limit_s:
            stop = 'time_limit'
            break
    if x_val is not None and best[0] < math.inf:
        with torch.no_grad():
            model.theta.copy_(best[1])
    hist.update(epochs=len(hist['loss']), stop=stop, time_s=time.perf_counter() - t0,
                final_mu=mu)
    return hist


def train_adam_lbfgs(model, x, y, *, x_val=None, y_val=None, w=None, w_val=None,
                     adam_steps: int = 3000,
                     batch: int = 4096, lr: float = 1e-2, lr_final: float = 1e-4,
                     lbfgs_iters: int = 1000, lbfgs_history: int = 50, val_every: int = 50,
                     time_limit_s: float = float('inf'), seed: int = 0,
                     threads: int = 2) -> dict:
    """Adam on minibatches (learning rate decayed geometrically from ``lr`` to ``lr_final``)
    then full-batch L-BFGS (strong Wolfe line search), on the mean squared error.  The
    parameters of the best validation check (every ``val_every`` steps/iterations) are kept.
    ``time_limit_s`` is split evenly between the two phases.  ``w``, ``w_val``: optional
    weights of the training and validation points.

    Returns the history: ``loss``, ``val`` per check, ``adam_steps``, ``lbfgs_iters``,
    ``time_s``.
    """
    torch = _torch()
    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(int(seed))
    t0 = time.perf_counter()
    hist = {'loss': [], 'val': []}
    best = [math.inf, model.theta.detach().clone()]

    w = torch.ones(x.shape[0], dtype=x.dtype) if w is None else w

    def check():
        v = _mse(model, x_val, y_val, w_val) if x_val is not None else _mse(model, x, y, w)
        hist['val'].append(v)
        if v < best[0]:
            best[0] = v
            best[1] = model.theta.detach().clone()

    opt = torch.optim.Adam(model.parameters(), lr=lr)
    gamma = (lr_final / lr) ** (1.0 / max(adam_steps, 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    n = x.shape[0]
    done_adam = 0
    for step in range(adam_steps):
        idx = torch.randint(0, n, (min(batch, n),), generator=gen)
        opt.zero_grad()
        loss = torch.mean((model(x[idx]) - y[idx]) ** 2 * w[idx, None])
        loss.backward()
        opt.step()
        sched.step()
        done_adam += 1
        if step % val_every == 0:
            hist['loss'].append(float(loss.detach()))
            check()
        if time.perf_counter() - t0 > 0.5 * time_limit_s:
            break
    check()
    t_adam = time.perf_counter() - t0
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=val_every,
                            history_size=lbfgs_history, line_search_fn='strong_wolfe',
                            tolerance_grad=1e-12, tolerance_change=1e-16)

    def closure():
        opt.zero_grad()
        loss = torch.mean((model(x) - y) ** 2 * w[:, None])
        loss.backward()
        return loss

    done_lbfgs = 0
    while done_lbfgs < lbfgs_iters:
        loss = opt.step(closure)
        it = opt.state[opt._params[0]]['n_iter']
        hist['loss'].append(float(loss.detach()))
        check()
        if it <= done_lbfgs:
            break
        done_lbfgs = it
        if time.perf_counter() - t0 > time_limit_s:
            break
    with torch.no_grad():
        model.theta.copy_(best[1])
    hist.update(adam_steps=done_adam, lbfgs_iters=done_lbfgs, adam_time_s=t_adam,
                time_s=time.perf_counter() - t0)
    return hist


# --- data: splits by map, errors -------------------------------------------------------------

def map_split(n_overlap: int, n_clearance: int, *, n_test: int, n_val: int, seed: int):
    """Disjoint lists of ``(i_overlap, j_clearance)`` pairs: train, validation, test.  Test
    and validation maps are drawn from the interior of the wear grid (never its edges, so they
    are interpolation tests)."""
    rng = np.random.default_rng(seed)
    interior = [(i, j) for i in range(1, n_overlap - 1) for j in range(1, n_clearance - 1)]
    pick = rng.permutation(len(interior))
    test = sorted(interior[k] for k in pick[:n_test])
    val = sorted(interior[k] for k in pick[n_test:n_test + n_val])
    held = set(test) | set(val)
    train = [(i, j) for i in range(n_overlap) for j in range(n_clearance) if (i, j) not in held]
    return train, val, test


def _points(db: Database, pairs, weights: bool = False):
    """Raw inputs ``(N, 4)`` and P12 ``(N,)`` of the maps ``pairs`` of ``db``; with
    ``weights``, also ``1 / ||map||^2`` per point (so that a weighted squared error sums the
    squared relative errors of the maps, the reference's metric)."""
    xs, q = np.meshgrid(db.xs_m, db.q_m3_s, indexing='ij')
    xs, q = xs.ravel(), q.ravel()
    raws, ys, ws = [], [], []
    for i, j in pairs:
        raws.append(np.stack([xs, q, np.full_like(xs, db.overlap_m[i]),
                              np.full_like(xs, db.clearance_m[j])], axis=1))
        ys.append(db.p12_pa[:, :, i, j].ravel())
        ws.append(np.full(xs.size, 1.0 / np.sum(ys[-1] ** 2)))
    if weights:
        return np.concatenate(raws), np.concatenate(ys), np.concatenate(ws)
    return np.concatenate(raws), np.concatenate(ys)


def map_errors(data, maps) -> np.ndarray:
    """Relative error in Euclidean norm of each map: ``maps`` is an iterable of
    ``(xs, q, overlap, clearance, p12)`` with ``p12`` the true map on the ``xs x q`` grid."""
    errs = []
    for xs, q, lap, clr, p12 in maps:
        pred = mlp_numpy(data, xs[:, None], q[None, :], lap, clr)
        errs.append(float(np.linalg.norm(pred - p12) / np.linalg.norm(p12)))
    return np.array(errs)


def db_maps(db: Database, pairs):
    """The maps ``pairs`` of ``db`` in the form :func:`map_errors` takes."""
    return [(db.xs_m, db.q_m3_s, float(db.overlap_m[i]), float(db.clearance_m[j]),
             db.p12_pa[:, :, i, j]) for i, j in pairs]


def offgrid_maps(n_maps: int, *, q_max_m3_s: float = 6e-5, n_q: int = 15, seed: int = 0,
                 params: PlantParams | None = None, wear=None):
    """``n_maps`` fresh maps (the reference's transient) at wear drawn uniformly inside
    :data:`WEAR_RANGES` from ``seed`` (or at the given ``wear`` pairs), on the database spool
    grid and ``n_q`` flows over ``+-q_max_m3_s``."""
    p = params if params is not None else default_params()
    lap, clr = random_wear(n_maps, np.random.default_rng(seed), wear)
    xs = spool_grid(133, p.spool_stroke_m)
    return maps_at(xs, np.linspace(-q_max_m3_s, q_max_m3_s, n_q), lap, clr, p)


def _summary(errs) -> dict:
    errs = np.asarray(errs)
    return {'mean': float(errs.mean()), 'max': float(errs.max()), 'n_maps': int(errs.size)}


# --- training a fluid network end to end -----------------------------------------------------

#: Settings of the shipped 4-input network (the reference's architecture).  Stopping is by
#: epoch/iteration counts (the time limits are only a safeguard), so a build is reproducible.
NN_SETTINGS = {
    'hidden': [21, 15, 3], 'transforms': ['linear', 'linear', 'linear', 'linear'],
    'databases': ['DB2', 'DB3'], 'n_test': 10, 'n_val': 6, 'split_seed': 1, 'seed': 0,
    'map_weighting': False,
    'lm': {'epochs': 1000, 'subsample': 20000, 'resample_every': 100, 'max_fail': 200,
           'time_limit_s': 3600.0},
    'adam_lbfgs': {'adam_steps': 20000, 'batch': 4096, 'lr': 1e-2, 'lr_final': 1e-4,
                   'lbfgs_iters': 1500, 'time_limit_s': 3600.0},
}

#: Settings of the shipped 2-input network (nominal wear, DB5).
NN2_SETTINGS = {
    'hidden': [21, 15, 3], 'transforms': ['linear', 'linear'], 'databases': ['DB5'],
    'seed': 0, 'q_test_every': 7, 'map_weighting': False,
    'lm': {'epochs': 1000, 'subsample': 20000, 'resample_every': 0, 'max_fail': 200,
           'time_limit_s': 3600.0},
    'adam_lbfgs': {'adam_steps': 20000, 'batch': 4096, 'lr': 1e-2, 'lr_final': 1e-4,
                   'lbfgs_iters': 1500, 'time_limit_s': 3600.0},
}


def _fit_model(raw_tr, y_tr, raw_val, y_val, *, sources, transforms, scales, hidden, algorithm,
               seed, settings, threads, w_tr=None, w_val=None):
    """Normalise on the training split, build and train one network; returns
    ``(data, history, wall_s)``."""
    torch = _torch()
    inputs = fit_inputs(raw_tr, sources, transforms, scales)
    output = fit_output(y_tr)
    to_t = (lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64))
    x_tr = to_t(_transform_inputs(inputs, raw_tr))
    t_tr = to_t(((y_tr - output[0]) / output[1])[:, None])
    x_va = to_t(_transform_inputs(inputs, raw_val)) if raw_val is not None else None
    t_va = to_t(((y_val - output[0]) / output[1])[:, None]) if raw_val is not None else None
    if w_tr is not None:  # weights of mean 1 on the training split
        scale = 1.0 / np.mean(w_tr)
        w_tr = to_t(w_tr * scale)
        w_val = to_t(w_val * scale) if w_val is not None else None
    model = make_torch_mlp(d_in=len(sources), d_hidden=hidden, seed=seed)
    t0 = time.perf_counter()
    if algorithm == 'lm':
        hist = train_lm(model, x_tr, t_tr, x_val=x_va, y_val=t_va, w=w_tr, w_val=w_val,
                        seed=seed, threads=threads, **settings)
    elif algorithm == 'adam_lbfgs':
        hist = train_adam_lbfgs(model, x_tr, t_tr, x_val=x_va, y_val=t_va, w=w_tr,
                                w_val=w_val, seed=seed, threads=threads, **settings)
    else:
        raise ValueError(f'unknown training algorithm {algorithm!r}')
    wall = time.perf_counter() - t0
    data = pack(model.sizes, inputs, output, model.theta.detach().numpy())
    return data, hist, wall, model


def train_fluid_network(*, n_inputs: int = 4, settings: dict | None = None,
                        algorithms=('lm', 'adam_lbfgs'), params: PlantParams | None = None,
                        threads: int = 2, n_offgrid: int = 8, verbose: bool = False):
    """Train the 4-input (``n_inputs=4``, DB2/DB3 settings :data:`NN_SETTINGS`) or 2-input
    (``n_inputs=2``, DB5, :data:`NN2_SETTINGS`) network with each algorithm, keep the one with
    the lower validation error and return ``(data, meta)``.

    4 inputs: whole maps are held out (test and validation pairs of the wear grid, the same in
    every database used); errors are reported on the held-out maps of each database and on
    ``n_offgrid`` fresh maps at random wear.  2 inputs: every ``q_test_every``-th flow curve
    of DB5 is held out for testing (the ones next to them for validation); errors on the
    held-out curves and on a fresh nominal map at flows between the database's.
    """
    p = params if params is not None else default_params()
    st = dict(NN_SETTINGS if n_inputs == 4 else NN2_SETTINGS)
    st.update(settings or {})
    dbs = {name: get_database(name, p) for name in st['databases']}
    scales = [p.spool_stroke_m / math.sinh(SPOOL_GRID_DENSITY), None, None, None][:n_inputs]
    if n_inputs == 4:
        first = next(iter(dbs.values()))
        train, val, test = map_split(first.overlap_m.size, first.clearance_m.size,
                                     n_test=st['n_test'], n_val=st['n_val'],
                                     seed=st['split_seed'])
        raw_tr, y_tr, w_tr = (np.concatenate(a) for a in zip(
            *(_points(db, train, weights=True) for db in dbs.values())))
        raw_val, y_val, w_val = (np.concatenate(a) for a in zip(
            *(_points(db, val, weights=True) for db in dbs.values())))
        split = {'train_maps': len(train), 'val_pairs': val, 'test_pairs': test}
        eval_sets = {f'{name}_test': db_maps(db, test) for name, db in dbs.items()}
        for name, db in dbs.items():
            q_max = float(np.max(np.abs(db.q_m3_s)))
            eval_sets[f'offgrid_q{q_max:.1e}'] = offgrid_maps(
                n_offgrid, q_max_m3_s=q_max, n_q=db.q_m3_s.size, seed=100, params=p)
    else:
        db = dbs['DB5']
        n_q = db.q_m3_s.size
        every = st['q_test_every']
        test_q = np.arange(every // 2, n_q, every)
        val_q = np.clip(test_q + 1, 0, n_q - 1)
        train_q = np.setdiff1d(np.arange(n_q), np.concatenate([test_q, val_q]))
        sub = (lambda cols: Database(db.xs_m, db.q_m3_s[cols], db.overlap_m, db.clearance_m,
                                     db.p12_pa[:, cols], db.meta))
        raw_tr, y_tr, w_tr = _points(sub(train_q), [(0, 0)], weights=True)
        raw_val, y_val, w_val = _points(sub(val_q), [(0, 0)], weights=True)
        split = {'train_flows': int(train_q.size), 'val_flows': val_q.tolist(),
                 'test_flows': test_q.tolist()}
        eval_sets = {'DB5_test': db_maps(sub(test_q), [(0, 0)])}
        q_mid = 0.5 * (db.q_m3_s[1:] + db.q_m3_s[:-1])[::4]
        fresh = transient_map(db.xs_m[:, None], q_mid[None, :], params=p)['p12_pa']
        eval_sets['offgrid_flows'] = [(db.xs_m, q_mid, p.overlap_supply_m,
                                       p.radial_clearance_m, fresh)]
    if n_inputs == 4:
        val_maps = [m for db in dbs.values() for m in db_maps(db, val)]
    else:
        val_maps = db_maps(sub(val_q), [(0, 0)])
    sources = list(range(n_inputs))
    results = {}
    for alg in algorithms:
        data, hist, wall, _ = _fit_model(
            raw_tr, y_tr, raw_val, y_val, sources=sources, transforms=st['transforms'],
            scales=scales, hidden=st['hidden'], algorithm=alg, seed=st['seed'],
            settings=st[alg], threads=threads,
            w_tr=w_tr if st['map_weighting'] else None,
            w_val=w_val if st['map_weighting'] else None)
        errs = {k: _summary(map_errors(data, v)) for k, v in eval_sets.items()}
        val_err = _summary(map_errors(data, val_maps))
        results[alg] = {'data': data, 'hist': hist, 'wall_s': wall, 'errors': errs,
                        'val': val_err}
        if verbose:
            print(json.dumps({'algorithm': alg, 'wall_s': round(wall, 1), 'val': val_err,
                              'errors': errs, 'stop': hist.get('stop')}), flush=True)
    winner = min(results, key=lambda a: results[a]['val']['mean'])
    res = results[winner]
    inputs = res['data'][1]
    meta = {
        'kind': 'mlp', 'format': 1,
        'inputs': [{'name': INPUT_NAMES[int(r[0])], 'unit': INPUT_UNITS[int(r[0])],
                    'transform': 'asinh(x/scale)' if r[1] == ASINH else 'x/scale',
                    'scale': r[2], 'mid': r[3], 'half': r[4]} for r in inputs],
        'inputs_used': [INPUT_NAMES[s] for s in sources],
        'normalisation': 'z = (transform(x) - mid) / half, min-max to [-1, 1] on the '
                         'training split; P12 = mid + half * y',
        'output': {'name': 'p12_pa', 'unit': 'Pa', 'mid': float(res['data'][2][0]),
                   'half': float(res['data'][2][1])},
        'architecture': {'d_in': n_inputs, 'd_hidden': st['hidden'], 'd_out': 1,
                         'activation': 'tanh', 'output_activation': 'linear',
                         'n_weights': int(res['data'][3].size)},
        'training': {'algorithm': winner, 'settings': st[winner], 'seed': st['seed'],
                     'loss': ('squared error of the normalised output weighted by '
                              '1/||map||^2 (sum of squared relative map errors)'
                              if st['map_weighting'] else
                              'mean squared error of the normalised output'),
                     'time_s': round(res['wall_s'], 1), 'threads': threads,
                     'stop': res['hist'].get('stop'),
                     'epochs': res['hist'].get('epochs'),
                     'adam_steps': res['hist'].get('adam_steps'),
                     'lbfgs_iters': res['hist'].get('lbfgs_iters'),
                     'databases': st['databases'],
                     'database_hashes': {k: db.meta['fluid_hash'] for k, db in dbs.items()},
                     'split': split},
        'comparison': {alg: {'time_s': round(r['wall_s'], 1), 'val': r['val'],
                             'errors': r['errors'], 'stop': r['hist'].get('stop'),
                             'epochs': r['hist'].get('epochs'),
                             'adam_steps': r['hist'].get('adam_steps'),
                             'lbfgs_iters': r['hist'].get('lbfgs_iters'),
                             'settings': st[alg]}
                       for alg, r in results.items()},
        'winner_rule': 'lower mean relative map error on the validation maps',
        'errors': res['errors'],
        'metric': '||P_pred - P_true||_2 / ||P_true||_2 per map (all XS x Q of one wear pair)',
        'valid_range': {'xs_m': [float(raw_tr[:, 0].min()), float(raw_tr[:, 0].max())],
                        'q_m3_s': [float(raw_tr[:, 1].min()), float(raw_tr[:, 1].max())]},
        'fluid_hash': fluid_hash(p),
    }
    if n_inputs == 2:
        meta['nominal_wear'] = {'overlap_m': p.overlap_supply_m,
                                'clearance_m': p.radial_clearance_m}
        meta['note'] = 'ignores the overlap and clearance arguments (nominal wear)'
    return res['data'], meta


def build_artefacts(params: PlantParams | None = None, out_dir: Path | None = None,
                    threads: int = 2, verbose: bool = False) -> list[Path]:
    """Train and save ``nn.npz`` (4 inputs) and ``nn2.npz`` (2 inputs) in
    :func:`models_dir` (or ``out_dir``); returns their paths."""
    out = Path(out_dir) if out_dir is not None else models_dir()
    paths = []
    for name, n_in in (('nn', 4), ('nn2', 2)):
        data, meta = train_fluid_network(n_inputs=n_in, params=params, threads=threads,
                                         verbose=verbose)
        path = out / f'{name}.npz'
        save_artefact(path, data, meta)
        paths.append(path)
    return paths


if __name__ == '__main__':
    for _p in build_artefacts(verbose=True):
        print(_p)
