"""The ``dnn`` dynamic surrogate (:mod:`.edge`): the edge network, its kernel
:func:`dnn_kernel`, the kernel's compiled forms :data:`DNN_FORMS` and :class:`DnnSurrogate`.

Inputs (:func:`dnn_features`, all logarithmic, the opening in units of the clearance):
``ln(1 + (s/c)^2) / 2`` while open (the gap of the truncated cone over the clearance),
``ln(1 - s/c)`` while covered (the laminar covered length), ``ln(1 + |dp| / dp0)`` and ``ln c``.
Two hidden layers of :data:`DNN_WIDTH` units with the activation ``x (15 - 10 x^2 + 3 x^4) / 8``
on ``x = clip(z, -1, 1)`` (a polynomial: no transcendental per unit), a linear output plus a
linear skip term of the inputs (the orifice law's log-log asymptotes are linear in these
inputs, the hidden layers learn the transitions).  Trained
(:func:`eha_ros.training.dynamic.build_dnn`) on the hf edge equations with most points where
the loop lives (openings within ~10 um of the edge, drops up to 1.1 x supply).
:meth:`DnnSurrogate._prepare` folds the clearance's input (constant within a run) and the
normalisations into the weights; the kernel evaluates the four edges of a step as the four
lanes of ``<4 x double>`` vectors, its LLVM IR generated for the fixed width
(:func:`.dnn_ir.dnn_flows`: logarithm and exponential from the floating-point bits and
polynomials, no libm call).  :func:`dnn_numpy` is the same network in numpy.
"""

import math

import numpy as np
from numba import njit

from eha_ros.mlp import mlp_forward, split_weights
from eha_ros.physics import PlantParams
from eha_ros.physics.loop import advance
from eha_ros.surrogates.base import Forms, SurrogateError
from eha_ros.surrogates.dnn_ir import DNN_WIDTH, dnn_flows
from eha_ros.surrogates.edge import DP_MAX_PA, DynamicSurrogate

__all__ = ['DNN_WIDTH', 'dnn_features', 'dnn_numpy', 'dnn_kernel', 'DNN_FORMS', 'DnnSurrogate']


def dnn_features(s_m, dp_pa, clearance_m, dp_scale_pa: float) -> np.ndarray:
    """The network inputs of ``dnn`` ``(N, 4)`` (numpy; the kernel computes the same per
    step, :func:`.dnn_ir.dnn_flows`): the opening in units of the clearance, ``r = s / c``, as
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


@njit(cache=True)
def dnn_kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m):
    """(Q1L, Q2L) [m^3/s], the four edges (1S, 1R, 2R, 2S) through the network ``ln G`` as
    one batch of four SIMD lanes (:func:`.dnn_ir.dnn_flows`).

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
    q1s, q1r, q2r, q2s = dnn_flows(
        data[0], data[1], data[2], data[3], data[4], k,
        (xs_m - lap_supply_m, -xs_m - lap_return_m, xs_m - lap_return_m, -xs_m - lap_supply_m),
        (ps - p1_pa, p1_pa - pr, p2_pa - pr, ps - p2_pa))
    return q1s - q1r, q2r - q2s


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


#: The compiled forms of :func:`dnn_kernel`, cached on disk (:class:`.base.Forms`).
DNN_FORMS = Forms(_run_dnn, _run_split_dnn, _points_dnn)


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
