"""Solve the steady table of the in-service estimator (:mod:`eha_ros.health.steady_table`) and
write ``steady_table.npz``.

Build: ``python -m eha_ros.training.steady_table`` (about 2 min on 2 cores).
"""

from __future__ import annotations

import time

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.health.steady_table import (CLEARANCE_STEP_M, N_Q, N_XS, OVERLAP_STEP_M,
                                         Q_MAX_M3_S, Q_SCALE_M3_S, TABLE_FILE, XS_MAX_M,
                                         XS_SCALE_M, SteadyTable, sinh_axis)
from eha_ros.physics import PlantParams, default_params
from eha_ros.physics.maps import WEAR_RANGES, fluid_hash, steady_map

__all__ = ['build_steady_table']


def build_steady_table(params: PlantParams | None = None, progress=print) -> SteadyTable:
    """Solve the steady state at every node (numba, all cores)."""
    p = params if params is not None else default_params()
    (l0, l1), (c0, c1) = WEAR_RANGES['overlap_m'], WEAR_RANGES['radial_clearance_m']
    laps = np.round(np.arange(l0, l1 + 1e-12, OVERLAP_STEP_M), 12)
    clrs = np.round(np.arange(c0, c1 + 1e-12, CLEARANCE_STEP_M), 12)
    xs = sinh_axis(XS_MAX_M, XS_SCALE_M, N_XS)
    q = sinh_axis(Q_MAX_M3_S, Q_SCALE_M3_S, N_Q)
    xg, qg = np.meshgrid(xs, q, indexing='ij')
    out = np.empty((laps.size, clrs.size, xs.size, q.size))
    t0 = time.perf_counter()
    for a, lap in enumerate(laps):
        for b, clr in enumerate(clrs):
            out[a, b] = steady_map(xg, qg, lap, clr, params=p)['p12_pa']
        progress(f'overlap {lap * 1e6:5.2f} um done ({time.perf_counter() - t0:.0f} s)')
    return SteadyTable(laps, clrs, xs, q, out)


def main():
    p = default_params()
    t0 = time.perf_counter()
    t = build_steady_table(p)
    save_artefact(models_dir('health') / TABLE_FILE, (t.overlap_m, t.clearance_m, t.xs_m, t.q_m3_s,
                                                      t.p12_pa.astype(np.float32)),
                  {'kind': 'steady_table', 'fluid_hash': fluid_hash(p),
                   'build_s': round(time.perf_counter() - t0, 1)})


if __name__ == '__main__':
    main()
