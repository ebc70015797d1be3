"""Training of the project's networks (torch, imported inside the functions only): the fluid
surrogates of :mod:`eha_ros.training.nn`, the dynamic edge network of :mod:`.dynamic` and the
wear-diagnosis network of :mod:`.valve_test` all train through :func:`fit_network`.

Model
    :func:`make_torch_mlp`: an MLP (float64, tanh hidden layers unless told otherwise, linear
    output) whose weights live in one flat parameter ``theta`` laid out as the numba kernel
    (:func:`eha_ros.surrogates.nn.mlp_kernel`) and the numpy forward pass
    (:func:`eha_ros.surrogates.nn.mlp_forward`) read them.  ``dnn`` (:mod:`.dnn`) uses the
    ``quintic`` activation (:data:`ACTIVATIONS`) and a linear skip term, which its own kernel
    and :func:`eha_ros.surrogates.dnn.dnn_numpy` read.

Algorithms
    :func:`train_lm`, Levenberg-Marquardt as MATLAB's ``trainlm`` (``(J'J + mu I) d = J'e``
    with the Jacobian formed by hand, batched, on a random subset of the training points; its
    damping and stops: :class:`LMSettings`); :func:`train_adam_lbfgs`, Adam on minibatches
    then full-batch L-BFGS.  Both minimise the (optionally weighted) mean squared
    error of the normalised outputs and keep the parameters of the best validation check.

Normalisation
    :func:`minmax`: per column ``(mid, half)`` mapping the training split to [-1, 1].

Splits
    :func:`map_split`: whole maps (wear pairs) held out from the interior of a wear grid.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

__all__ = ['ACTIVATIONS', 'make_torch_mlp', 'train_lm', 'train_adam_lbfgs', 'fit_network',
           'history_stops', 'minmax', 'map_split', 'ALGORITHMS', 'Split', 'LMSettings',
           'AdamLBFGSSettings']


@dataclasses.dataclass(frozen=True)
class Split:
    """The points a network trains on: inputs ``x`` ``(N, d_in)`` and outputs ``y`` ``(N,
    d_out)`` of the training split, the validation split's (``None``: none), and optional point
    weights of each (``None``: all 1); numpy arrays for :func:`fit_network`, float64 tensors
    inside the trainers."""

    x: object
    y: object
    x_val: object = None
    y_val: object = None
    w: object = None
    w_val: object = None


@dataclasses.dataclass(frozen=True)
class LMSettings:
    """Settings of :func:`train_lm`: at most ``epochs`` epochs; the damping ``mu`` [-] starts
    at ``mu``, is multiplied by ``mu_dec`` after a step that lowers the loss and by ``mu_inc``
    until one does, and the training stops above ``mu_max``; ``max_fail`` epochs without a
    better validation loss stop it; ``subsample`` training points per epoch, redrawn every
    ``resample_every`` epochs (never if 0); a gradient norm per residual below ``min_grad``
    and ``time_limit_s`` [s] of wall time stop it too."""

    epochs: int = 1000
    mu: float = 1e-3
    mu_dec: float = 0.1
    mu_inc: float = 10.0
    mu_max: float = 1e10
    max_fail: int = 50
    subsample: int = 20000
    resample_every: int = 0
    min_grad: float = 1e-12
    time_limit_s: float = float('inf')


@dataclasses.dataclass(frozen=True)
class AdamLBFGSSettings:
    """Settings of :func:`train_adam_lbfgs`: ``adam_steps`` Adam steps on minibatches of
    ``batch`` points, the learning rate decayed geometrically from ``lr`` to ``lr_final``; then
    at most ``lbfgs_iters`` full-batch L-BFGS iterations with ``lbfgs_history`` pairs; the
    validation check every ``val_every`` steps or iterations; ``time_limit_s`` [s] of wall
    time, split evenly between the two phases."""

    adam_steps: int = 3000
    batch: int = 4096
    lr: float = 1e-2
    lr_final: float = 1e-4
    lbfgs_iters: int = 1000
    lbfgs_history: int = 50
    val_every: int = 50
    time_limit_s: float = float('inf')


#: Training algorithms :func:`fit_network` knows, and their settings.
SETTINGS = {'lm': LMSettings, 'adam_lbfgs': AdamLBFGSSettings}
ALGORITHMS = tuple(SETTINGS)


#: Hidden-layer activations :func:`make_torch_mlp` knows: ``tanh``, and ``quintic``, the
#: odd polynomial ``x (15 - 10 x^2 + 3 x^4) / 8`` on [-1, 1] held at +-1 outside (twice
#: continuously differentiable, no transcendental: what :mod:`.dnn`'s ``dnn`` kernel
#: evaluates).
ACTIVATIONS = ('tanh', 'quintic')


def _activation(torch, name):
    """``(f(z), f'(z))`` of the hidden activation ``name``."""
    if name == 'tanh':
        f = torch.tanh

        def df(z, a):
            return 1.0 - a * a
    elif name == 'quintic':
        def f(z):
            x = torch.clamp(z, -1.0, 1.0)
            x2 = x * x
            return x * (1.875 + x2 * (-1.25 + 0.375 * x2))

        def df(z, a):
            x = torch.clamp(z, -1.0, 1.0)
            u = 1.0 - x * x
            return 1.875 * u * u
    else:
        raise ValueError(f'unknown activation {name!r} (known: {", ".join(ACTIVATIONS)})')
    return f, df


def make_torch_mlp(*, d_in: int, d_hidden: list, d_out: int = 1, seed: int = 0,
                   activation: str = 'tanh', skip: bool = False):
    """An MLP (hidden activation ``activation``, :data:`ACTIVATIONS`; linear output) as a
    torch module (float64) with its weights in one flat parameter ``theta`` laid out as the
    kernel reads them.  With ``skip`` the output also gets a linear term of the inputs, its
    weights ``(d_in, d_out)`` (row-major) after the last layer's in ``theta``.  Weights:
    Glorot-uniform from ``seed``, biases and skip weights zero."""
    import torch
    act, dact = _activation(torch, activation)

    class MLP(torch.nn.Module):
        def __init__(self, *, d_in, d_hidden, d_out):
            super().__init__()
            self.skip = bool(skip)
            self.sizes = [int(d_in), *(int(h) for h in d_hidden), int(d_out)]
            self.n_mlp = sum(do * di + do for di, do in zip(self.sizes[:-1], self.sizes[1:]))
            self.theta = torch.nn.Parameter(torch.zeros(
                self.n_mlp + (self.sizes[0] * self.sizes[-1] if self.skip else 0),
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
                    h = act(h)
            if self.skip:
                theta = self.theta if theta is None else theta
                h = h + x @ theta[self.n_mlp:].view(self.sizes[0], self.sizes[-1])
            return h

        @torch.no_grad()
        def jacobian(self, x):
            """``(N * d_out, P)`` derivative of the outputs (row ``n * d_out + o``) with
            respect to ``theta``, by hand: one batched backward sweep per output."""
            ws = self.layers()
            acts = [x]
            pre = [x]
            h = x
            for w, b in ws[:-1]:
                z = torch.addmm(b, h, w)
                h = act(z)
                pre.append(z)
                acts.append(h)
            n_pts = x.shape[0]
            d_out = self.sizes[-1]
            jac = torch.empty((n_pts, d_out, self.theta.numel()), dtype=x.dtype)
            for o in range(d_out):
                delta = torch.zeros((n_pts, d_out), dtype=x.dtype)
                delta[:, o] = 1.0
                k_end = self.n_mlp
                if self.skip:
                    jac[:, o, k_end:] = (x[:, :, None] * delta[:, None, :]).reshape(n_pts, -1)
                for n in range(len(ws) - 1, -1, -1):
                    w, _ = ws[n]
                    di, do = w.shape
                    jac[:, o, k_end - do:k_end] = delta
                    jac[:, o, k_end - do - do * di:k_end - do] = (
                        acts[n][:, :, None] * delta[:, None, :]).reshape(n_pts, di * do)
                    k_end -= do + do * di
                    if n > 0:
                        delta = (delta @ w.T) * dact(pre[n], acts[n])
            return jac.reshape(n_pts * d_out, -1)

    model = MLP(d_in=d_in, d_hidden=d_hidden, d_out=d_out)
    gen = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        for w, b in model.layers():
            lim = math.sqrt(6.0 / (w.shape[0] + w.shape[1]))  # Glorot
            w.copy_((torch.rand(w.shape, generator=gen, dtype=torch.float64) * 2 - 1) * lim)
            b.zero_()
    return model


# --- training --------------------------------------------------------------------------------

def _mse(model, x, y, w=None):
    """(Weighted) mean squared error; ``w`` one weight per row of ``x``."""
    import torch
    model.eval()
    with torch.no_grad():
        r2 = (model(x) - y) ** 2
        return float(torch.mean(r2 if w is None else r2 * w[:, None]))


def train_lm(model, data: Split, settings: LMSettings = LMSettings(), *, seed: int = 0,
             threads: int = 2) -> dict:
    """Levenberg-Marquardt on the (weighted) mean squared error of ``data`` (tensors), as
    MATLAB's ``trainlm``: each epoch solves ``(J'J + mu I) d = J'e`` on a subsample of the
    training points drawn from ``seed``, with the damping and stops of :class:`LMSettings`.
    The parameters of the best validation epoch (of the last epoch without validation data)
    are kept.

    Returns the history: ``loss``, ``val``, ``mu`` per epoch, ``epochs``, ``stop``, ``time_s``.
    """
    import torch
    torch.set_num_threads(threads)
    gen = np.random.default_rng(seed)
    x, y, x_val, y_val, w_val = data.x, data.y, data.x_val, data.y_val, data.w_val
    st, mu, subsample = settings, settings.mu, settings.subsample
    n = x.shape[0]

    w = torch.ones(n, dtype=x.dtype) if data.w is None else data.w

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
    for ep in range(st.epochs):
        if st.resample_every and ep and ep % st.resample_every == 0:
            xs, ys, ws = draw()
        with torch.no_grad():
            sw = torch.sqrt(ws).repeat_interleave(ys.shape[1])
            e = (model(xs) - ys).reshape(-1) * sw
            loss = float(torch.mean(e ** 2))
            jac = model.jacobian(xs) * sw[:, None]
            hess = jac.T @ jac
            grad = jac.T @ e
            if float(torch.linalg.vector_norm(grad)) / e.numel() < st.min_grad:
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
                        mu = max(mu * st.mu_dec, 1e-20)
                        loss = new
                        break
                mu *= st.mu_inc
                if mu > st.mu_max:
                    break
            if mu > st.mu_max:
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
                if fails >= st.max_fail:
                    stop = 'max_fail'
                    break
        if time.perf_counter() - t0 > st.time_limit_s:
            stop = 'time_limit'
            break
    if x_val is not None and best[0] < math.inf:
        with torch.no_grad():
            model.theta.copy_(best[1])
    hist.update(epochs=len(hist['loss']), stop=stop, time_s=time.perf_counter() - t0,
                final_mu=mu)
    return hist


def train_adam_lbfgs(model, data: Split, settings: AdamLBFGSSettings = AdamLBFGSSettings(),
                     *, seed: int = 0, threads: int = 2) -> dict:
    """Adam on minibatches (learning rate decayed geometrically from ``lr`` to ``lr_final``)
    then full-batch L-BFGS (strong Wolfe line search), on the (weighted) mean squared error of
    ``data`` (tensors).  The parameters of the best validation check (every ``val_every``
    steps/iterations) are kept.  ``time_limit_s`` is split evenly between the two phases
    (:class:`AdamLBFGSSettings`).

    Returns the history: ``loss``, ``val`` per check, ``adam_steps``, ``lbfgs_iters``,
    ``time_s``.
    """
    import torch
    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(int(seed))
    x, y, x_val, y_val, w_val = data.x, data.y, data.x_val, data.y_val, data.w_val
    st = settings
    t0 = time.perf_counter()
    hist = {'loss': [], 'val': []}
    best = [math.inf, model.theta.detach().clone()]

    w = torch.ones(x.shape[0], dtype=x.dtype) if data.w is None else data.w

    def check():
        v = _mse(model, x_val, y_val, w_val) if x_val is not None else _mse(model, x, y, w)
        hist['val'].append(v)
        if v < best[0]:
            best[0] = v
            best[1] = model.theta.detach().clone()

    opt = torch.optim.Adam(model.parameters(), lr=st.lr)
    gamma = (st.lr_final / st.lr) ** (1.0 / max(st.adam_steps, 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    n = x.shape[0]
    done_adam = 0
    for step in range(st.adam_steps):
        idx = torch.randint(0, n, (min(st.batch, n),), generator=gen)
        opt.zero_grad()
        loss = torch.mean((model(x[idx]) - y[idx]) ** 2 * w[idx, None])
        loss.backward()
        opt.step()
        sched.step()
        done_adam += 1
        if step % st.val_every == 0:
            hist['loss'].append(float(loss.detach()))
            check()
        if time.perf_counter() - t0 > 0.5 * st.time_limit_s:
            break
    check()
    t_adam = time.perf_counter() - t0
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=st.val_every,
                            history_size=st.lbfgs_history, line_search_fn='strong_wolfe',
                            tolerance_grad=1e-12, tolerance_change=1e-16)

    def closure():
        opt.zero_grad()
        loss = torch.mean((model(x) - y) ** 2 * w[:, None])
        loss.backward()
        return loss

    done_lbfgs = 0
    while done_lbfgs < st.lbfgs_iters:
        loss = opt.step(closure)
        it = opt.state[opt._params[0]]['n_iter']
        hist['loss'].append(float(loss.detach()))
        check()
        if it <= done_lbfgs:
            break
        done_lbfgs = it
        if time.perf_counter() - t0 > st.time_limit_s:
            break
    with torch.no_grad():
        model.theta.copy_(best[1])
    hist.update(adam_steps=done_adam, lbfgs_iters=done_lbfgs, adam_time_s=t_adam,
                time_s=time.perf_counter() - t0)
    return hist


def history_stops(hist: dict) -> dict:
    """How a training stopped, for an artefact's meta: ``stop``, ``epochs``, ``adam_steps``
    and ``lbfgs_iters`` of its history (``None`` where the algorithm has none)."""
    return {k: hist.get(k) for k in ('stop', 'epochs', 'adam_steps', 'lbfgs_iters')}


def minmax(a) -> np.ndarray:
    """``(2, n)`` per column of ``a`` (``(N, n)``, or ``(N,)`` giving ``(2,)``): ``mid``,
    ``half`` of the min-max normalisation to [-1, 1] (``half = 1`` for a constant column)."""
    a = np.asarray(a, dtype=float)
    lo, hi = a.min(axis=0), a.max(axis=0)
    return np.stack([0.5 * (hi + lo), np.where(hi > lo, 0.5 * (hi - lo), 1.0)])


def fit_network(data: Split, *, hidden, algorithm: str, seed: int, settings: dict,
                threads: int = 2, activation: str = 'tanh', skip: bool = False):
    """Build an MLP of hidden widths ``hidden`` and train it with ``algorithm`` (``'lm'``
    or ``'adam_lbfgs'``; ``settings``: the fields of its :data:`SETTINGS` class) on ``data``,
    already normalised numpy arrays (the point weights rescaled to mean 1 on the training
    split); ``activation``: the hidden layers' (:data:`ACTIVATIONS`); ``skip``: a linear
    input-output term besides the network (:func:`make_torch_mlp`).

    Returns ``(model, history, wall_s)``.
    """
    if algorithm not in ALGORITHMS:
        raise ValueError(f'unknown training algorithm {algorithm!r}')
    known = {f.name for f in dataclasses.fields(SETTINGS[algorithm])}
    bad = sorted(set(settings) - known)
    if bad:
        raise ValueError(f'training settings of {algorithm}: unknown {bad[0]!r} (one of '
                         f'{", ".join(sorted(known))})')
    import torch

    def column(a):
        if a is None:
            return None
        a = np.asarray(a, dtype=float)
        return a[:, None] if a.ndim == 1 else a
    w_tr, w_val = data.w, data.w_val
    if w_tr is not None:
        scale = 1.0 / np.mean(w_tr)
        w_tr = np.asarray(w_tr) * scale
        w_val = np.asarray(w_val) * scale if w_val is not None else None
    y_tr = column(data.y)
    model = make_torch_mlp(d_in=np.shape(data.x)[1], d_hidden=hidden, d_out=y_tr.shape[1],
                           seed=seed, activation=activation, skip=skip)
    train = train_lm if algorithm == 'lm' else train_adam_lbfgs
    tensors = Split(*(None if a is None else torch.as_tensor(np.ascontiguousarray(a),
                                                             dtype=torch.float64)
                      for a in (data.x, y_tr, data.x_val, column(data.y_val), w_tr, w_val)))
    t0 = time.perf_counter()
    hist = train(model, tensors, SETTINGS[algorithm](**settings), seed=seed, threads=threads)
    return model, hist, time.perf_counter() - t0


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
