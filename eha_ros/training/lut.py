"""Build the lookup table of the fluid-dynamic block (:mod:`eha_ros.surrogates.lut`) and write
``lut.npz``.

Build: ``python -m eha_ros.training.lut``.

The table: 133 spool positions (``spool_grid``) x 61 flows over ``+-FLOW_MAX_M3_S`` (sinh
spacing, densest at zero flow) x 5 overlaps x 5 clearances (uniform over ``WEAR_RANGES``, the
reference's DB1 wear points), generated with the databases' map transient (spool fixed, flow
imposed, pressures from zero, 1e-2 s at 1e-6 s), stored as float32 (interpolation in float64).
Why this grid, measured in the reference's metric (relative Euclidean-norm error over a map)
by ``bench/surrogates_lut_ga.py``:

* along the wear axes the maps are smooth: 5 x 5 wear points interpolate about as well as
  the spool and flow axes allow, and interpolating in log(clearance), clearance^2,
  clearance^3 or 1/clearance instead of clearance is worse;
* along the spool axis 133 points suffice;
* the flow axis carries the error: P12 is nearly linear in Q across the water-hammer peaks
  near null but bends like ``Q |Q|`` where the valve is open, so the table spends its points
  on flow rather than on wear;
* the map-wide metric is dominated by the large peaks at large flows, while the closed loop
  of the shipped scenarios stays near null and at small flows: the sinh-spaced flow axis
  puts its points there with the map-wide error unchanged.

``source='DB1'``/``'DB2'`` builds the table from a database instead, for comparison.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.physics import PlantParams, default_params, params_hash
from eha_ros.physics.maps import (FLOW_MAX_M3_S, WEAR_RANGES, fluid_hash, spool_grid,
                                  transient_map)
from eha_ros.surrogates.base import SurrogateError
from eha_ros.surrogates.lut import AXES, make_lut
from eha_ros.training.database import get_database, map_errors
from eha_ros.training.database import heldout_maps as _heldout_maps

__all__ = ['GRID', 'build_table', 'heldout_maps', 'build_artefact']

#: Shipped grid: points per axis (spool positions, flows, overlaps, clearances) and the
#: density of the flow axis (``spool_grid``'s sinh spacing over the flow range; 0: uniform).
GRID = {'n_xs': 133, 'n_q': 61, 'n_overlap': 5, 'n_clearance': 5, 'q_density': 2.5}


def build_table(params: PlantParams | None = None, n_xs: int = GRID['n_xs'],
                n_q: int = GRID['n_q'], n_overlap: int = GRID['n_overlap'],
                n_clearance: int = GRID['n_clearance'], q_density: float = GRID['q_density'],
                t_end_s: float = 1e-2, dt_s: float = 1e-6):
    """Grid and P12 [Pa] from the map transient of the databases.

    Returns
    -------
    xs_m, q_m3_s, overlap_m, clearance_m, p12_pa : ndarray
        Spool positions (``spool_grid(n_xs)``), flows over ``+-FLOW_MAX_M3_S``
        (``FLOW_MAX_M3_S sinh(q_density u) / sinh(q_density)`` for ``u`` uniform in [-1, 1],
        uniform for ``q_density = 0``), wear (uniform over ``WEAR_RANGES``) and P12 of shape
        ``(n_xs, n_q, n_overlap, n_clearance)``.
    """
    p = params if params is not None else default_params()
    for label, n in (('n_xs', n_xs), ('n_q', n_q), ('n_overlap', n_overlap),
                     ('n_clearance', n_clearance)):
        if int(n) != n or n < 2:
            raise SurrogateError(f'{label} = {n} must be an integer >= 2')
    if not (q_density >= 0 and np.isfinite(q_density)):
        raise SurrogateError(f'q_density = {q_density} must be a finite number >= 0')
    xs = spool_grid(int(n_xs), p.spool_stroke_m)
    if q_density > 0:  # the spool grid's antisymmetric sinh spacing, over the flow range
        q = spool_grid(int(n_q), FLOW_MAX_M3_S, density=float(q_density))
    else:
        q = np.linspace(-FLOW_MAX_M3_S, FLOW_MAX_M3_S, int(n_q))
    lap = np.linspace(*WEAR_RANGES['overlap_m'], int(n_overlap))
    clr = np.linspace(*WEAR_RANGES['radial_clearance_m'], int(n_clearance))
    r = transient_map(xs[:, None, None, None], q[None, :, None, None],
                      lap[None, None, :, None], clr[None, None, None, :], params=p,
                      t_end_s=t_end_s, dt_s=dt_s)
    return xs, q, lap, clr, r['p12_pa']


def heldout_maps(n_maps: int, seed: int = 0, params: PlantParams | None = None,
                 n_q: int = 30, wear=None):
    """Maps off every table grid (:func:`.database.heldout_maps`): ``n_maps`` wear pairs drawn
    inside ``WEAR_RANGES`` from ``seed`` (or the given ``wear`` pairs), each on the midpoints
    of ``spool_grid(133)`` x ``n_q`` sorted flows drawn uniformly over ``+-FLOW_MAX_M3_S``."""
    return _heldout_maps(n_maps, seed=seed, params=params, n_q=n_q, wear=wear,
                         xs_midpoints=True, random_flows=True)


def build_artefact(params: PlantParams | None = None, path: Path | None = None,
                   source: str = 'grid', grid: dict | None = None,
                   n_validation_maps: int = 5) -> Path:
    """Build the lookup table and write it to ``path`` (default ``models/lut.npz``).

    Parameters
    ----------
    params : PlantParams, optional
        Physics parameters (default: the nominal ones); their fluid hash goes into the meta.
    path : Path, optional
        Output file.
    source : {'grid', 'DB1', 'DB2', 'DB3', 'DB4'}
        ``'grid'``: the table of :data:`GRID` (or ``grid``), generated here (about 15 s on two
        cores); a database name: that database's grid and values (built and cached if
        missing).
    grid : dict, optional
        Overrides of :data:`GRID` for ``source='grid'``.
    n_validation_maps : int
        Maps at random wear (:func:`heldout_maps`, seed 0) whose errors go into the meta.

    Returns
    -------
    Path
        The artefact written.
    """
    p = params if params is not None else default_params()
    path = Path(path) if path is not None else models_dir('surrogates') / 'lut.npz'
    t0 = time.perf_counter()
    if source == 'grid':
        g = {**GRID, **(grid or {})}
        unknown = set(g) - set(GRID)
        if unknown:
            raise SurrogateError(f'unknown lookup-table grid keys {sorted(unknown)} '
                                 f'(known: {", ".join(GRID)})')
        xs, q, lap, clr, p12 = build_table(p, **g)
        origin = {'source': 'grid', **g,
                  'generator': {'method': 'transient from zero pressure, spool fixed, flow '
                                          'imposed', 't_end_s': 1e-2, 'dt_s': 1e-6}}
        fh = fluid_hash(p)
    elif source in ('DB1', 'DB2', 'DB3', 'DB4'):
        db = get_database(source, p)
        xs, q, lap, clr, p12 = db.xs_m, db.q_m3_s, db.overlap_m, db.clearance_m, db.p12_pa
        origin = {'source': source, 'n_xs': xs.size, 'n_q': q.size, 'n_overlap': lap.size,
                  'n_clearance': clr.size, 'generator': db.meta.get('generator')}
        fh = db.meta['fluid_hash']
    else:
        raise SurrogateError(f"unknown lookup-table source {source!r} (one of 'grid', 'DB1', "
                             "'DB2', 'DB3', 'DB4')")
    t_table = time.perf_counter() - t0
    meta = {
        'kind': 'lut', 'format': 1,
        'inputs': [{'name': n, 'unit': u} for n, u in AXES],
        'output': {'name': 'p12_pa', 'unit': 'Pa'},
        'interpolation': 'multilinear in (xs, q, overlap, clearance), float64; inputs '
                         'clamped to the axes',
        'table_dtype': 'float32',
        'ranges': {n: [float(a[0]), float(a[-1])] for (n, _), a in zip(AXES, (xs, q, lap, clr))},
        'data': origin,
        'fluid_hash': fh, 'params_hash': params_hash(p),
        'table_wall_s': round(t_table, 2),
    }
    s = make_lut(xs, q, lap, clr, p12, meta)
    if n_validation_maps > 0:
        maps = heldout_maps(n_validation_maps, seed=0, params=p)
        e = map_errors(s.p12, maps)
        meta['validation'] = {
            'maps': 'heldout_maps(seed=0): random wear, spool-grid midpoints x 30 random flows',
            'n_maps': int(e.size), 'mean_error': float(e.mean()), 'max_error': float(e.max())}
    meta['build_wall_s'] = round(time.perf_counter() - t0, 2)
    save_artefact(path, s.data, meta)
    return path


if __name__ == '__main__':
    sys.exit(print(build_artefact()))
