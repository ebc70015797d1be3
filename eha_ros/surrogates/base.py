"""One interface for every surrogate of the fluid-dynamic block:
``P12 = f(XS, Q, overlap, clearance)``.

A surrogate is a :class:`FluidSurrogate`: a name, a metadata dict (inputs and their units,
normalisation, training data, the fluid-parameter hash it was built for) and a pair
``(kernel, data)`` where ``kernel`` is a numba-jitted function
``kernel(data, xs_m, q_m3_s, overlap_m, clearance_m) -> p12_pa`` on scalars and ``data`` is a
tuple of numpy arrays (tables, coefficients, weights).  The plant calls ``kernel`` inside its own
jitted loop, so a scalar call costs no Python overhead; :meth:`FluidSurrogate.p12` is the
vectorised numpy-facing convenience.

Artefacts are ``.npz`` files in ``eha_ros/surrogates/models/`` holding the arrays of ``data``
(``data_0``, ``data_1``, ...) and ``meta`` (JSON).  :func:`load_surrogate` refuses one built for
other fluid parameters.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Callable

import numpy as np
from numba import njit

from eha_ros.physics import PlantParams, default_params

from .database import DatabaseError, fluid_hash

__all__ = ['FluidSurrogate', 'SurrogateError', 'models_dir', 'save_artefact', 'load_artefact',
           'register_kernel', 'load_surrogate', 'KERNELS', 'relative_error', 'map_errors']


class SurrogateError(DatabaseError):
    """A surrogate artefact is missing, corrupt, or was built for other physics parameters."""


#: kind (the artefact's ``meta['kind']``) -> numba kernel
KERNELS: dict[str, Callable] = {}


def register_kernel(kind: str):
    """Decorator: register the numba kernel that evaluates artefacts of ``kind``."""
    def deco(fn):
        KERNELS[kind] = fn
        return fn
    return deco


@njit  # not cached: a kernel argument's type names the kernel object (see physics.plant)
def _vectorise(kernel, data, xs, q, lap, clr, out):
    for i in range(xs.size):
        out[i] = kernel(data, xs[i], q[i], lap[i], clr[i])


@dataclasses.dataclass
class FluidSurrogate:
    """A surrogate of the fluid-dynamic block (see the module docstring)."""

    name: str
    kernel: Callable
    data: tuple
    meta: dict

    #: ``'algebraic'``: the kernel gives P12 (the reference's surrogates); ``'dynamic'``: it
    #: gives chamber flows (:mod:`.dynamic`).
    family = 'algebraic'

    def prepare(self, p: PlantParams) -> tuple:
        """The kernel's data for the parameters ``p`` (the artefact's arrays: an algebraic
        surrogate reads the wear as kernel arguments)."""
        return self.data

    def stability_limit(self, p: PlantParams) -> tuple[float, str]:
        """Largest stable step [s] of the jack under this surrogate's feedback.

        The plant imposes ``Q = AJ dXJ/dt`` and the jack feels ``AJ P12(XS, Q)``: to first
        order a damper ``AJ^2 |dP12/dQ|`` on the jack's mass, stable under the explicit step
        for ``dt < 2 MJ / (AJ^2 |dP12/dQ|)``.  The slope is measured on the surrogate itself,
        over the spool grid and the flows the loop reaches (twice the table's range).
        """
        from eha_ros.physics.maps import spool_grid
        xs = spool_grid(67, p.spool_stroke_m)
        q_max = 2.0 * float(self.meta.get('valid_range', {}).get('q_m3_s', [0, 6e-5])[1])
        q = np.concatenate([np.linspace(-q_max, q_max, 81), np.linspace(-1e-7, 1e-7, 21)])
        q = np.unique(q)
        pr = self.p12(xs[:, None], q[None, :], p.overlap_supply_m, p.radial_clearance_m)
        slope = float(np.max(np.abs(np.diff(pr, axis=1)) / np.diff(q)[None, :]))
        aj = p.jack_area_m2
        if not slope > 0:
            return math.inf, f'surrogate {self.name} P12(Q) feedback (flat)'
        return (2.0 * p.jack_mass_kg / (aj * aj * slope),
                f'surrogate {self.name} P12(Q) feedback on the jack (|dP12/dQ| up to '
                f'{slope:.3g} Pa s/m^3)')

    def p12(self, xs_m, q_m3_s, overlap_m, clearance_m):
        """P12 [Pa] for broadcastable inputs [m, m^3/s, m, m]."""
        arrs = np.broadcast_arrays(*(np.asarray(a, dtype=float)
                                     for a in (xs_m, q_m3_s, overlap_m, clearance_m)))
        flat = [np.ascontiguousarray(a.ravel()) for a in arrs]
        out = np.empty(flat[0].size)
        _vectorise(self.kernel, self.data, *flat, out)
        return out.reshape(arrs[0].shape) if arrs[0].ndim else float(out[0])

    def check_params(self, p: PlantParams) -> None:
        if self.meta.get('fluid_hash') != fluid_hash(p):
            raise SurrogateError(
                f'surrogate {self.name} was built for fluid parameters '
                f'{self.meta.get("fluid_hash")}, these are {fluid_hash(p)}: retrain it '
                '(python -m eha_ros.surrogates.<module>, see the module docstring) or use the '
                'parameters it was built for')


def relative_error(pred, true) -> float:
    """The reference's error metric: ``||pred - true||_2 / ||true||_2`` (Euclidean norms over
    all points; a map, a time history)."""
    pred = np.asarray(pred, dtype=float)
    true = np.asarray(true, dtype=float)
    return float(np.linalg.norm(pred - true) / np.linalg.norm(true))


def map_errors(model, maps) -> np.ndarray:
    """:func:`relative_error` of each map: ``model(xs, q, overlap, clearance)`` broadcasts
    (e.g. :meth:`FluidSurrogate.p12`); ``maps`` as :func:`.database.heldout_maps` returns."""
    return np.array([relative_error(model(xs[:, None], q[None, :], lap, clr), p12)
                     for xs, q, lap, clr, p12 in maps])


def models_dir() -> Path:
    """Folder of the shipped artefacts (``$EHA_ROS_MODELS_DIR`` overrides it)."""
    env = os.environ.get('EHA_ROS_MODELS_DIR')
    return Path(env) if env else Path(__file__).resolve().parent / 'models'


def save_artefact(path: Path, data: tuple, meta: dict) -> None:
    """Write ``data`` arrays and ``meta`` to ``path`` (atomically)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + '.partial.npz')
    arrays = {f'data_{i}': np.asarray(a) for i, a in enumerate(data)}
    np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
    os.replace(tmp, path)


def load_artefact(path: Path) -> tuple[tuple, dict]:
    """Read an artefact; one-line :class:`SurrogateError` when missing or corrupt."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z['meta']))
            n = len([k for k in z.files if k.startswith('data_')])
            data = tuple(np.ascontiguousarray(z[f'data_{i}']) for i in range(n))
    except FileNotFoundError:
        raise SurrogateError(f'{path}: no such surrogate artefact') from None
    except Exception as exc:
        raise SurrogateError(f'{path}: corrupt surrogate artefact ({type(exc).__name__})'
                             ) from None
    return data, meta


def load_surrogate(name: str, params: PlantParams | None = None,
                   path: Path | None = None) -> FluidSurrogate:
    """Load the shipped surrogate ``name`` (``lut``, ``ga``, ``nn``, ``nn2``...) and check it
    was built for ``params`` (default: the nominal parameters)."""
    p = params if params is not None else default_params()
    path = Path(path) if path is not None else models_dir() / f'{name}.npz'
    if path is None or not path.is_file():
        known = sorted(f.stem for f in models_dir().glob('*.npz'))
        raise SurrogateError(f'unknown surrogate {name!r} (shipped: {", ".join(known)})')
    data, meta = load_artefact(path)
    kind = meta.get('kind')
    _import_kernels()
    if kind not in KERNELS:
        raise SurrogateError(f'{path}: unknown surrogate kind {kind!r}')
    cls = FluidSurrogate
    if meta.get('family') == 'dynamic':
        from .dynamic import DynamicSurrogate as cls
    s = cls(name=name, kernel=KERNELS[kind], data=data, meta=meta)
    s.check_params(p)
    return s


def _import_kernels():
    """Import the modules that register kernels (kept lazy to keep imports light)."""
    from . import dynamic, ga, lut, nn  # noqa: F401
