"""Steady-state valve table for the in-service health fit.

The in-service fit compares measured load pressure with the valve's steady state
``P12(XS, Q; overlap, clearance)`` (:func:`eha_ros.physics.maps.steady_map`).  Solved per
sample, a fit over a grid of wear values and a window of samples takes longer than the
monitor's update period.  This table holds the steady state once, at every node of a wear
grid (overlap x clearance) over a grid of (XS, Q) covering in-service operation; a fit then
interpolates bilinearly in (XS, Q) at each wear node.

Axes
    overlap -2..6 um every 0.5 um, radial clearance 1..6 um every 0.25 um (the swept wear
    ranges, :data:`eha_ros.physics.maps.WEAR_RANGES`); spool position +-40 um (asinh-spaced,
    dense near null where the pressure gain is steep); load flow +-15 cm^3/s (sinh-spaced),
    beyond what the reference's scenarios reach in service; samples outside the table are not
    used.

Build: ``python -m eha_ros.training.steady_table`` (about 2 min on 2 cores) writes
``models/steady_table.npz`` with the hash of the fluid parameters it was built for.
"""

from __future__ import annotations

import numpy as np

from eha_ros.artefacts import check_hash, load_artefact, models_dir
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import fluid_hash

__all__ = ['SteadyTable', 'load_steady_table', 'sinh_axis', 'TABLE_FILE']

TABLE_FILE = 'steady_table.npz'
#: ``python -m`` argument that rebuilds it
REBUILD = 'eha_ros.training.steady_table'

#: Grid steps of the wear axes [m].
OVERLAP_STEP_M = 0.5e-6
CLEARANCE_STEP_M = 0.25e-6
XS_MAX_M, XS_SCALE_M, N_XS = 4e-5, 2e-6, 81
Q_MAX_M3_S, Q_SCALE_M3_S, N_Q = 1.5e-5, 1e-6, 41


def sinh_axis(vmax, scale, n):
    """``n`` nodes on ``[-vmax, vmax]``, equally spaced in ``asinh(v / scale)``: dense within
    about ``scale`` of zero, where the curves bend, sparse beyond."""
    u = np.linspace(-np.arcsinh(vmax / scale), np.arcsinh(vmax / scale), n)
    return scale * np.sinh(u)


class SteadyTable:
    """P12 [Pa] at every (overlap, clearance, XS, Q) node; :meth:`p12_at_nodes` interpolates
    in (XS, Q) at every wear node at once."""

    def __init__(self, overlap_m, clearance_m, xs_m, q_m3_s, p12_pa, meta=None):
        self.overlap_m = np.asarray(overlap_m, dtype=float)
        self.clearance_m = np.asarray(clearance_m, dtype=float)
        self.xs_m = np.asarray(xs_m, dtype=float)
        self.q_m3_s = np.asarray(q_m3_s, dtype=float)
        self.p12_pa = np.asarray(p12_pa, dtype=float)   # (n_lap, n_clr, n_xs, n_q)
        self.meta = meta or {}

    def inside(self, xs, q):
        """Samples inside the (XS, Q) table."""
        return ((xs >= self.xs_m[0]) & (xs <= self.xs_m[-1]) & (q >= self.q_m3_s[0])
                & (q <= self.q_m3_s[-1]))

    def p12_at_nodes(self, xs, q):
        """``(n_lap, n_clr, n)`` model P12 [Pa] of the samples ``(xs, q)`` (inside the table)
        at every wear node: bilinear in (XS, Q)."""
        xs = np.asarray(xs, dtype=float)
        q = np.asarray(q, dtype=float)
        i = np.clip(np.searchsorted(self.xs_m, xs) - 1, 0, self.xs_m.size - 2)
        j = np.clip(np.searchsorted(self.q_m3_s, q) - 1, 0, self.q_m3_s.size - 2)
        u = (xs - self.xs_m[i]) / (self.xs_m[i + 1] - self.xs_m[i])
        v = (q - self.q_m3_s[j]) / (self.q_m3_s[j + 1] - self.q_m3_s[j])
        t = self.p12_pa
        return ((1 - u) * (1 - v) * t[:, :, i, j] + u * (1 - v) * t[:, :, i + 1, j]
                + (1 - u) * v * t[:, :, i, j + 1] + u * v * t[:, :, i + 1, j + 1])


def load_steady_table(params: PlantParams | None = None) -> SteadyTable:
    """The shipped table, checked against the fluid parameters of ``params``."""
    p = params if params is not None else default_params()
    path = models_dir('health') / TABLE_FILE
    data, meta = load_artefact(path, REBUILD)
    check_hash(meta, 'fluid_hash', fluid_hash(p), str(path), REBUILD)
    return SteadyTable(*data[:5], meta=meta)
