"""Multilayer perceptrons in numpy, as inference runs them: the forward pass and the flat
weight layout every network artefact stores (the fluid networks, the valve-test and pre-flight
estimators).  Training (torch) is :mod:`eha_ros.training.networks`.
"""

from __future__ import annotations

import numpy as np

from eha_ros.artefacts import ArtefactError

__all__ = ['split_weights', 'flatten_weights', 'quintic', 'silu', 'NUMPY_ACTIVATIONS',
           'mlp_forward']


def split_weights(theta, sizes) -> list:
    """``[(W, b), ...]`` of a dense network with layer widths ``sizes`` from the flat
    ``theta``: layer by layer ``W`` (row-major, ``d_in x d_out``) then ``b``.  Raises
    :class:`~eha_ros.artefacts.ArtefactError` when the widths do not account for ``theta``
    exactly."""
    theta = np.asarray(theta, dtype=float)
    weights = []
    k = 0
    for di, do in zip(sizes[:-1], sizes[1:]):
        w = theta[k:k + di * do].reshape(di, do)
        k += di * do
        weights.append((w, theta[k:k + do]))
        k += do
    if k != theta.size:
        raise ArtefactError(f'{theta.size} weights for layer widths {list(sizes)} '
                            f'(which need {k})')
    return weights


def quintic(z):
    """The ``quintic`` hidden activation (:data:`eha_ros.training.networks.ACTIVATIONS`):
    ``x (15 - 10 x^2 + 3 x^4) / 8`` on ``x = clip(z, -1, 1)`` (numpy)."""
    x = np.clip(z, -1.0, 1.0)
    return x * (1.875 + x * x * (-1.25 + 0.375 * x * x))


def flatten_weights(weights) -> np.ndarray:
    """The flat ``theta`` of ``[(W, b), ...]``: the inverse of :func:`split_weights`."""
    return np.concatenate([np.concatenate([w.ravel(), b]) for w, b in weights])


def silu(z):
    """The ``silu`` hidden activation ``z / (1 + exp(-z))`` (torch's ``SiLU``), the logistic
    written from ``exp(-|z|)`` so that it neither overflows nor cancels: unbounded, so a
    network of it extrapolates about linearly beyond its training data."""
    z = np.asarray(z, dtype=float)
    e = np.exp(-np.abs(z))
    return z * np.where(z >= 0.0, 1.0 / (1.0 + e), e / (1.0 + e))


#: Hidden activations of :func:`mlp_forward` by name.
NUMPY_ACTIVATIONS = {'tanh': np.tanh, 'quintic': quintic, 'silu': silu}


def mlp_forward(weights, h, activation: str = 'tanh'):
    """Numpy forward pass of an MLP on normalised inputs ``h`` ``(N, d_0)``: ``weights`` a
    list of ``(W (d_in, d_out), b)``, the hidden ``activation`` (:data:`NUMPY_ACTIVATIONS`)
    on every layer but the last (linear)."""
    act = NUMPY_ACTIVATIONS[activation]
    for n, (w, b) in enumerate(weights):
        h = h @ w + b
        if n < len(weights) - 1:
            h = act(h)
    return h
