"""Lookup table of the fluid-dynamic block (the reference's section 5.2): ``P12(XS, Q, overlap,
clearance)`` on a 4-D grid, multilinear interpolation between the grid points.

Kernel
------
:func:`lut_kernel` locates each input on its axis through a bucket index (equal buckets
narrower than half the finest breakpoint spacing, see :func:`axis_tables`): one lookup and at
most one step, both branch-free, so the axes need not be uniform (the spool axis is
:func:`eha_ros.physics.maps.spool_grid`, 27x denser near null) and random inputs cost no
mispredicted branches.  Inputs outside an axis are clamped to its end (the table is held
constant beyond its edges, it does not extrapolate); the 16 surrounding table values are
blended with the product of the four linear weights.  The kernel is allocation-free and runs
in float64 whatever the table's storage type (about 0.07 us per call from a jitted loop); a
NaN input gives a NaN output.

Table (what :func:`build_artefact` ships)
-----------------------------------------
133 spool positions (``spool_grid``) x 61 flows over ``+-FLOW_MAX_M3_S`` (sinh spacing,
0.83e-6 m^3/s at zero flow to 4.9e-6 at the ends) x 5 overlaps x 5 clearances (uniform over
``WEAR_RANGES``, the reference's DB1 wear points), generated with the databases' map
transient (spool fixed, flow imposed, pressures from zero, 1e-2 s at 1e-6 s), stored as
float32 (0.84 MB; interpolation in float64).  The choice comes
from measuring where the interpolation error comes from, in the reference's metric (relative
Euclidean-norm error over a map), on 12 maps at random wear, on the midpoints of the spool
grid x 30 random flows (mean / max over the maps):

* along the wear axes the maps are smooth: on 20 maps at random wear on the databases' own
  spool and flow points (so that only the wear interpolation counts), 5 x 5 wear points
  interpolate to 0.08 % / 0.2 %, 9 x 9 (DB2) to 0.03 % / 0.06 %; interpolating in
  log(clearance), clearance^2, clearance^3 or 1/clearance instead of clearance is worse in
  every case (0.17 %, 0.10 %, 0.19 %, 0.27 % mean at 5 x 5);
* along the spool axis 133 points suffice: 199 or 265 change the error by < 0.02 %;
* the flow axis carries the error: P12 is nearly linear in Q across the water-hammer peaks
  near null but bends like ``Q |Q|`` where the valve is open.  5 flows (the DB1 table) leave
  2.9 % / 3.1 %, 15 flows (the DB2 table) 0.79 % / 0.86 %; with 5 x 5 wear points, 41
  uniform flows 0.25 % / 0.35 %, 61 flows 0.15 % / 0.29 %, 81 flows 0.14 % / 0.23 %;
* the map-wide metric is dominated by the large peaks at large flows, while the closed loop
  of the shipped scenarios stays within ``|XS| < 25 um``, ``|Q| < 1e-5 m^3/s``.  There,
  61 uniform flows (spacing 2e-6 m^3/s) leave up to 0.9 % for ``|Q| < 1e-5`` and 2.3 % for
  ``|Q| < 1e-6``; the sinh-spaced flow axis (density 2.5) brings these to 0.6 % and 1.1 %
  with the map-wide error unchanged (density 3.5: 0.95 % at ``|Q| < 1e-6``, map-wide
  0.17 % mean).

So the table spends its points on flow rather than on wear.  What error remains sits at the
water-hammer peaks: 45 % of the squared error at ``|XS| < 5 um``, 23 % at 5-20 um, 30 % at
20-100 um.  ``source='DB1'``/``'DB2'`` builds the table from a database instead (for
comparison: in the small-signal region above they err by up to 17 % and 6 %).
``bench/surrogates_lut_ga.py`` reports the figures.

Inputs outside the table (``|Q| > FLOW_MAX_M3_S``, wear outside ``WEAR_RANGES``) are clamped:
the surrogate is only meant for the ranges it was built on.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from numba import njit

from eha_ros.physics import PlantParams, default_params, params_hash
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, transient_map

from .base import FluidSurrogate, SurrogateError, models_dir, register_kernel, save_artefact
from .base import map_errors
from .database import FLOW_MAX_M3_S, fluid_hash, get_database
from .database import heldout_maps as _heldout_maps

__all__ = ['lut_kernel', 'axis_tables', 'make_lut', 'build_table', 'heldout_maps', 'map_errors',
           'build_artefact', 'GRID', 'AXES']

#: Shipped grid: points per axis (spool positions, flows, overlaps, clearances) and the
#: density of the flow axis (``spool_grid``'s sinh spacing over the flow range; 0: uniform).
GRID = {'n_xs': 133, 'n_q': 61, 'n_overlap': 5, 'n_clearance': 5, 'q_density': 2.5}
#: Input names, in the kernel's order, and their units.
AXES = (('xs_m', 'm'), ('q_m3_s', 'm^3/s'), ('overlap_m', 'm'), ('clearance_m', 'm'))


#: Buckets of an axis index per finest breakpoint spacing, and the most an axis may need.
_BUCKETS_PER_SPACING = 2
_MAX_BUCKETS = 1 << 16


def axis_tables(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two arrays :func:`_locate` needs besides the breakpoints of an axis.

    The axis span is cut into ``nb`` equal buckets narrower than half the finest breakpoint
    spacing, so that a bucket holds at most one breakpoint.

    Returns
    -------
    aux : ndarray of float64
        ``[axis[0], nb / span, nb - 1, 1 / (axis[1] - axis[0]), ..., 1 / (axis[n-1] -
        axis[n-2])]``.
    index : ndarray of int64
        ``index[b]``: the interval ``i`` (``axis[i] <= x < axis[i + 1]``, ``i <= n - 2``)
        holding the start of bucket ``b``; a point of bucket ``b`` lies in interval
        ``index[b]`` or the next one.

    Raises
    ------
    SurrogateError
        When the axis is so non-uniform that it would need more than 65536 buckets.
    """
    axis = np.asarray(axis, dtype=np.float64)
    span = axis[-1] - axis[0]
    dx = np.diff(axis)
    nb = int(np.ceil(_BUCKETS_PER_SPACING * span / dx.min()))
    if nb > _MAX_BUCKETS:
        raise SurrogateError(f'lookup-table axis too non-uniform: finest spacing {dx.min():g} '
                             f'over a span of {span:g} needs {nb} index buckets '
                             f'(at most {_MAX_BUCKETS})')
    starts = axis[0] + span * np.arange(nb) / nb
    index = np.minimum(np.searchsorted(axis, starts, side='right') - 1, axis.size - 2)
    aux = np.concatenate([[axis[0], nb / span, nb - 1.0], 1.0 / dx])
    return aux, index.astype(np.int64)


@njit(cache=True, inline='always')
def _locate(axis, aux, index, x):
    """``(i, t)`` with ``x = (1 - t) axis[i] + t axis[i + 1]``, ``t`` clamped to [0, 1].

    The bucket of ``x`` gives its interval to within one step (see :func:`axis_tables`):
    no search loop, and the step is a conditional move, so random inputs cost no
    mispredicted branches.  A NaN ``x`` gives a NaN ``t``.
    """
    u = (x - aux[0]) * aux[1]
    if not u > 0.0:  # also NaN
        u = 0.0
    if u > aux[2]:
        u = aux[2]
    i = index[int(u)]
    i = min(i + (axis[i + 1] <= x), axis.size - 2)
    t = (x - axis[i]) * aux[3 + i]
    if t < 0.0:
        t = 0.0
    elif t > 1.0:
        t = 1.0
    return i, t


@register_kernel('lut')
@njit(cache=True)
def lut_kernel(data, xs_m, q_m3_s, overlap_m, clearance_m):
    """P12 [Pa] by multilinear interpolation; inputs [m, m^3/s, m, m] clamped to the axes.

    ``data = (xs_axis, q_axis, overlap_axis, clearance_axis, table, xs_aux, q_aux,
    overlap_aux, clearance_aux, xs_index, q_index, overlap_index, clearance_index)``, the
    ``aux``/``index`` arrays from :func:`axis_tables`.
    """
    table = data[4]
    i, a = _locate(data[0], data[5], data[9], xs_m)
    j, b = _locate(data[1], data[6], data[10], q_m3_s)
    k, c = _locate(data[2], data[7], data[11], overlap_m)
    m, d = _locate(data[3], data[8], data[12], clearance_m)
    acc = 0.0
    for di in range(2):
        wi = a if di else 1.0 - a
        for dj in range(2):
            wj = wi * (b if dj else 1.0 - b)
            for dk in range(2):
                wk = wj * (c if dk else 1.0 - c)
                v0 = np.float64(table[i + di, j + dj, k + dk, m])
                v1 = np.float64(table[i + di, j + dj, k + dk, m + 1])
                acc += wk * (v0 + d * (v1 - v0))
    return acc


def make_lut(xs_m, q_m3_s, overlap_m, clearance_m, p12_pa, meta: dict | None = None,
             dtype=np.float32, name: str = 'lut') -> FluidSurrogate:
    """A lookup-table surrogate from a grid and P12 on it.

    Parameters
    ----------
    xs_m, q_m3_s, overlap_m, clearance_m : array_like
        Strictly increasing breakpoints [m, m^3/s, m, m], at least 2 each.
    p12_pa : array_like
        P12 [Pa], shape ``(n_xs, n_q, n_overlap, n_clearance)``, finite.
    meta : dict, optional
        Metadata to carry (``kind`` and ``inputs`` are filled in).
    dtype : numpy dtype
        Storage type of the table (interpolation runs in float64 regardless).

    Raises
    ------
    SurrogateError
        On a malformed grid or table.
    """
    axes = []
    for (label, _), a in zip(AXES, (xs_m, q_m3_s, overlap_m, clearance_m)):
        a = np.ascontiguousarray(a, dtype=np.float64)
        if a.ndim != 1 or a.size < 2 or not np.all(np.isfinite(a)) or np.any(np.diff(a) <= 0):
            raise SurrogateError(f'lookup table axis {label} must be a finite, strictly '
                                 'increasing 1-D array of at least 2 breakpoints')
        axes.append(a)
    table = np.ascontiguousarray(p12_pa, dtype=dtype)
    shape = tuple(a.size for a in axes)
    if table.shape != shape:
        raise SurrogateError(f'lookup table of shape {table.shape} does not match its axes '
                             f'{shape}')
    if not np.all(np.isfinite(table)):
        raise SurrogateError('lookup table holds non-finite values')
    meta = dict(meta or {})
    meta.setdefault('kind', 'lut')
    meta.setdefault('inputs', [{'name': n, 'unit': u} for n, u in AXES])
    meta.setdefault('output', {'name': 'p12_pa', 'unit': 'Pa'})
    extra = [axis_tables(a) for a in axes]
    data = (*axes, table, *(e[0] for e in extra), *(e[1] for e in extra))
    return FluidSurrogate(name=name, kernel=lut_kernel, data=data, meta=meta)


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
    path = Path(path) if path is not None else models_dir() / 'lut.npz'
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
        'ranges': {'xs_m': [float(xs[0]), float(xs[-1])], 'q_m3_s': [float(q[0]), float(q[-1])],
                   'overlap_m': [float(lap[0]), float(lap[-1])],
                   'clearance_m': [float(clr[0]), float(clr[-1])]},
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
