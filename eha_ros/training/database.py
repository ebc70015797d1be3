"""Databases of characteristic maps (the reference's section 5.1.1) from the high-fidelity
map generator, and their file format.

A database is P12 [Pa] on a full grid of spool positions x flows x overlaps x clearances::

    DB1  133 x   5 x  5 x  5     lookup table and genetic algorithm
    DB2  133 x  15 x  9 x  9     4-input network
    DB3  133 x  15 x  9 x  9     as DB2, flows limited to a narrower range
    DB4  133 x  15 x 30 x 30     diagnostic network (900 maps)
    DB5  133 x 133 x  1 x  1     2-input network at nominal wear

Spool positions: :func:`eha_ros.physics.maps.spool_grid` (denser near null); overlaps and
clearances span :data:`eha_ros.physics.maps.WEAR_RANGES` (a single point: the nominal values).

File: ``<name>.npz`` holding ``xs_m``, ``q_m3_s``, ``overlap_m``, ``clearance_m`` (the grid),
``p12_pa`` (shape ``(n_xs, n_q, n_overlap, n_clearance)``) and ``meta`` (a JSON string: name,
units, generator settings, the hash of the physics parameters the maps depend on).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from eha_ros.artefacts import ArtefactError
from eha_ros.physics import PlantParams, default_params, params_hash
from eha_ros.surrogates.base import relative_error
from eha_ros.physics.maps import (FLOW_MAX_M3_S, WEAR_RANGES, fluid_hash, spool_grid,
                                  transient_map)

__all__ = ['DatabaseSpec', 'Database', 'DATABASES', 'build_database', 'load_database',
           'cache_dir', 'get_database', 'DatabaseError', 'random_wear', 'maps_at', 'heldout_maps',
           'map_errors']

#: Narrower flow range of DB3, around the flows of small commands.
FLOW_MAX_NARROW_M3_S = 1.5e-5


class DatabaseError(ArtefactError):
    """A database file is missing, corrupt, or was built for other physics parameters."""


@dataclasses.dataclass(frozen=True)
class DatabaseSpec:
    name: str
    n_xs: int
    n_q: int
    n_overlap: int
    n_clearance: int
    q_max_m3_s: float
    purpose: str

    def grid(self, p: PlantParams):
        xs = spool_grid(self.n_xs, p.spool_stroke_m)
        q = np.linspace(-self.q_max_m3_s, self.q_max_m3_s, self.n_q)
        lap = (np.array([p.overlap_supply_m]) if self.n_overlap == 1
               else np.linspace(*WEAR_RANGES['overlap_m'], self.n_overlap))
        clr = (np.array([p.radial_clearance_m]) if self.n_clearance == 1
               else np.linspace(*WEAR_RANGES['radial_clearance_m'], self.n_clearance))
        return xs, q, lap, clr


DATABASES = {s.name: s for s in (
    DatabaseSpec('DB1', 133, 5, 5, 5, FLOW_MAX_M3_S, 'lookup table, genetic algorithm'),
    DatabaseSpec('DB2', 133, 15, 9, 9, FLOW_MAX_M3_S, '4-input network'),
    DatabaseSpec('DB3', 133, 15, 9, 9, FLOW_MAX_NARROW_M3_S, '4-input network, low flows'),
    DatabaseSpec('DB4', 133, 15, 30, 30, FLOW_MAX_M3_S, 'diagnostic network'),
    DatabaseSpec('DB5', 133, 133, 1, 1, FLOW_MAX_M3_S, '2-input network at nominal wear'),
)}


@dataclasses.dataclass
class Database:
    """A loaded database: the grid, P12 on it and the metadata."""

    xs_m: np.ndarray
    q_m3_s: np.ndarray
    overlap_m: np.ndarray
    clearance_m: np.ndarray
    p12_pa: np.ndarray
    meta: dict

    @property
    def name(self) -> str:
        return self.meta['name']

    def check_params(self, p: PlantParams) -> None:
        """Refuse a database built for other fluid parameters."""
        if self.meta['fluid_hash'] != fluid_hash(p):
            raise DatabaseError(f'database {self.name} was built for fluid parameters '
                                f'{self.meta["fluid_hash"]}, these are {fluid_hash(p)}: '
                                'rebuild it (eha-build-db)')

    def save(self, path: Path) -> None:
        path = Path(path)
        tmp = path.with_name(path.name + '.partial.npz')
        np.savez(tmp, xs_m=self.xs_m, q_m3_s=self.q_m3_s, overlap_m=self.overlap_m,
                 clearance_m=self.clearance_m, p12_pa=self.p12_pa,
                 meta=np.array(json.dumps(self.meta)))
        os.replace(tmp, path)  # never leaves a half-written database under the real name


def build_database(name: str, params: PlantParams | None = None, progress: bool = True,
                   t_end_s: float = 1e-2, dt_s: float = 1e-6) -> Database:
    """Generate a database with the reference's map transient (one map per progress tick)."""
    if name not in DATABASES:
        raise DatabaseError(f'unknown database {name!r} (one of {", ".join(DATABASES)})')
    spec = DATABASES[name]
    p = params if params is not None else default_params()
    xs, q, lap, clr = spec.grid(p)
    p12 = np.empty((xs.size, q.size, lap.size, clr.size))
    n_maps = lap.size * clr.size
    # a few maps per call keeps both cores busy and the progress bar moving
    per_call = max(1, min(n_maps, 30))
    pairs = [(i, j) for i in range(lap.size) for j in range(clr.size)]
    t0 = time.perf_counter()
    for k in range(0, n_maps, per_call):
        chunk = pairs[k:k + per_call]
        li, cj = np.array(chunk).T
        r = transient_map(xs[:, None, None], q[None, :, None], lap[li][None, None, :],
                          clr[cj][None, None, :], params=p, t_end_s=t_end_s, dt_s=dt_s)
        for m, (i, j) in enumerate(chunk):
            p12[:, :, i, j] = r['p12_pa'][:, :, m]
        if progress:  # a bar of 30 characters and the time left
            done, elapsed = min(k + per_call, n_maps), time.perf_counter() - t0
            fill, eta = 30 * done // n_maps, elapsed / done * (n_maps - done)
            sys.stderr.write(f'\r{name} [{"#" * fill}{"." * (30 - fill)}] {done}/{n_maps} maps '
                             f'{elapsed:5.1f} s, eta {eta:5.1f} s')
            sys.stderr.flush()
    if progress:
        sys.stderr.write('\n')
    meta = {
        'name': name, 'purpose': spec.purpose, 'format': 1,
        'units': {'xs_m': 'm', 'q_m3_s': 'm^3/s', 'overlap_m': 'm', 'clearance_m': 'm',
                  'p12_pa': 'Pa'},
        'axes': ['xs_m', 'q_m3_s', 'overlap_m', 'clearance_m'],
        'generator': {'method': 'transient from zero pressure, spool fixed, flow imposed',
                      't_end_s': t_end_s, 'dt_s': dt_s},
        'fluid_hash': fluid_hash(p), 'params_hash': params_hash(p),
        'build_wall_s': round(time.perf_counter() - t0, 2),
    }
    return Database(xs, q, lap, clr, p12, meta)


_ARRAYS = ('xs_m', 'q_m3_s', 'overlap_m', 'clearance_m', 'p12_pa', 'meta')


def load_database(path: Path | str, params: PlantParams | None = None) -> Database:
    """Load and check a database file; with ``params``, refuse one built for others."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _ARRAYS if k not in z.files]
            if missing:
                raise DatabaseError(f'{path}: not a map database (missing {missing[0]})')
            arrays = {k: z[k] for k in _ARRAYS}
    except DatabaseError:
        raise
    except FileNotFoundError:
        raise DatabaseError(f'{path}: no such database file') from None
    except Exception as exc:  # zipfile/npy errors of a truncated or foreign file
        raise DatabaseError(f'{path}: corrupt or not a map database ({type(exc).__name__})'
                            ) from None
    try:
        meta = json.loads(str(arrays.pop('meta')))
    except ValueError:
        raise DatabaseError(f'{path}: corrupt metadata') from None
    db = Database(meta=meta, **arrays)
    shape = tuple(a.size for a in (db.xs_m, db.q_m3_s, db.overlap_m, db.clearance_m))
    if db.p12_pa.shape != shape or not np.all(np.isfinite(db.p12_pa)):
        raise DatabaseError(f'{path}: p12_pa does not match its grid or is not finite')
    if params is not None:
        db.check_params(params)
    return db


def cache_dir() -> Path:
    """Where built databases are kept: ``$EHA_ROS_DATA_DIR`` or ``~/.cache/eha_ros``."""
    return Path(os.environ.get('EHA_ROS_DATA_DIR', Path.home() / '.cache' / 'eha_ros'))


def get_database(name: str, params: PlantParams | None = None, progress: bool = False,
                 ) -> Database:
    """The database ``name`` for ``params``: from the cache if built for them, else built
    (and cached)."""
    p = params if params is not None else default_params()
    path = cache_dir() / f'{name}_{fluid_hash(p)}.npz'
    if path.is_file():
        try:
            return load_database(path, p)
        except DatabaseError:
            pass  # rebuilt below
    db = build_database(name, p, progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    db.save(path)
    return db


def main(argv=None) -> int:
    """``eha-build-db DB4 [-o FILE]``: build a database to a file, with a progress bar."""
    import argparse
    ap = argparse.ArgumentParser(prog='eha-build-db', description=main.__doc__)
    ap.add_argument('name', choices=sorted(DATABASES))
    ap.add_argument('-o', '--output', type=Path, default=None,
                    help='output file (default: <cache>/<name>_<hash>.npz)')
    ap.add_argument('--force', action='store_true', help='overwrite an existing file')
    args = ap.parse_args(argv)
    p = default_params()
    out = args.output or cache_dir() / f'{args.name}_{fluid_hash(p)}.npz'
    if out.exists() and not args.force:
        print(f'eha-build-db: error: {out} exists (use --force to overwrite)', file=sys.stderr)
        return 2
    db = build_database(args.name, p, progress=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    db.save(out)
    print(json.dumps({'database': args.name, 'file': str(out), 'points': int(db.p12_pa.size),
                      'shape': list(db.p12_pa.shape), 'build_wall_s': db.meta['build_wall_s'],
                      'fluid_hash': db.meta['fluid_hash']}))
    return 0


def random_wear(n_maps: int, rng: np.random.Generator, wear=None):
    """``(overlap_m, clearance_m)`` arrays: ``n_maps`` pairs drawn uniformly inside
    :data:`WEAR_RANGES` from ``rng`` (overlap first), or the given ``wear`` pairs."""
    if wear is not None:
        return tuple(np.array(v, dtype=float) for v in zip(*wear))
    return (rng.uniform(*WEAR_RANGES['overlap_m'], n_maps),
            rng.uniform(*WEAR_RANGES['radial_clearance_m'], n_maps))


def maps_at(xs_m, q_m3_s, overlap_m, clearance_m, params: PlantParams):
    """One map per wear pair, from the reference's transient: a list of ``(xs_m, q_m3_s,
    overlap_m, clearance_m, p12_pa)`` with ``p12_pa`` of shape ``(n_xs, n_q)``."""
    r = transient_map(xs_m[:, None, None], q_m3_s[None, :, None], overlap_m[None, None, :],
                      clearance_m[None, None, :], params=params)['p12_pa']
    return [(xs_m, q_m3_s, float(overlap_m[m]), float(clearance_m[m]), r[:, :, m])
            for m in range(overlap_m.size)]


def heldout_maps(n_maps: int = 1, *, seed: int = 0, params: PlantParams | None = None,
                 q_max_m3_s: float = FLOW_MAX_M3_S, n_q: int = 15, wear=None,
                 xs_midpoints: bool = False, random_flows: bool = False, xs_m=None,
                 q_m3_s=None):
    """Fresh maps for validation, from the reference's transient (:func:`maps_at`): the one
    generator of held-out maps of every surrogate.

    Wear: ``n_maps`` pairs drawn uniformly inside :data:`WEAR_RANGES` from
    ``numpy.random.default_rng(seed)``, or the given ``wear`` pairs.  Spool positions:
    ``spool_grid(133)``, its midpoints (``xs_midpoints``, off every table grid) or ``xs_m``.
    Flows: ``n_q`` over ``+-q_max_m3_s``, evenly spaced or (``random_flows``) drawn uniformly
    from the same generator and sorted, or ``q_m3_s``.

    Returns a list of ``(xs_m, q_m3_s, overlap_m, clearance_m, p12_pa)``, ``p12_pa`` of shape
    ``(n_xs, n_q)``.
    """
    p = params if params is not None else default_params()
    rng = np.random.default_rng(seed)
    lap, clr = random_wear(n_maps, rng, wear)
    if xs_m is None:
        xs_m = spool_grid(133, p.spool_stroke_m)
        if xs_midpoints:
            xs_m = 0.5 * (xs_m[1:] + xs_m[:-1])
    if q_m3_s is None:
        q_m3_s = (np.sort(rng.uniform(-q_max_m3_s, q_max_m3_s, n_q)) if random_flows
                  else np.linspace(-q_max_m3_s, q_max_m3_s, n_q))
    return maps_at(np.asarray(xs_m, dtype=float), np.asarray(q_m3_s, dtype=float), lap, clr, p)


def map_errors(model, maps) -> np.ndarray:
    """:func:`relative_error` of each map: ``model(xs, q, overlap, clearance)`` broadcasts
    (e.g. :meth:`FluidSurrogate.p12`); ``maps`` as :func:`.database.heldout_maps` returns."""
    return np.array([relative_error(model(xs[:, None], q[None, :], lap, clr), p12)
                     for xs, q, lap, clr, p12 in maps])


if __name__ == '__main__':
    sys.exit(main())
