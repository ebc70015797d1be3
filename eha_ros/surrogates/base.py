"""What every surrogate of the fluid-dynamic block is: ``P12 = f(XS, Q, overlap, clearance)``.

A surrogate is a :class:`FluidSurrogate`: a name, a metadata dict (inputs and their units,
normalisation, training data, the fluid-parameter hash it was built for) and a pair
``(kernel, data)`` where ``kernel`` is a numba-jitted function
``kernel(data, xs_m, q_m3_s, overlap_m, clearance_m) -> p12_pa`` on scalars and ``data`` is a
tuple of numpy arrays (tables, coefficients, weights).  The plant calls ``kernel`` inside its own
jitted loop (the surrogate is a :class:`eha_ros.physics.loop.FluidBlock`), so a scalar call
costs no Python overhead; :meth:`FluidSurrogate.p12` is the vectorised numpy-facing convenience.

This module imports no other surrogate: :mod:`.registry` lists the kinds and loads artefacts
(:mod:`eha_ros.artefacts`).
"""

from __future__ import annotations

import dataclasses
import math
from collections import namedtuple
from typing import Callable

import numpy as np
from numba import njit

from eha_ros.artefacts import ArtefactError, check_hash
from eha_ros.physics import PlantParams
from eha_ros.physics.loop import P12
from eha_ros.physics.maps import fluid_hash, spool_grid

__all__ = ['Forms', 'FluidSurrogate', 'SurrogateError', 'relative_error']


class SurrogateError(ArtefactError):
    """A surrogate artefact is missing, corrupt, or was built for other physics parameters."""


@njit  # not cached: a kernel argument's type names the kernel object (see Forms)
def _vectorise(kernel, data, xs, q, lap, clr, out):
    for i in range(xs.size):
        out[i] = kernel(data, xs[i], q[i], lap[i], clr[i])


#: A kernel's compiled forms, each with the kernel a global (not an argument) so that numba
#: caches it on disk (:func:`eha_ros.physics.loop.run` says why): the plant's loop explicit
#: and split (``form(s, i_cmd, p, clock, loop, data)``) and the loop over points
#: (``points(data, xs, q, lap, clr, out)`` for P12, ``points(data, xs, p1, p2, lap_s, lap_r,
#: out1, out2)`` for chamber flows).
Forms = namedtuple('Forms', 'run run_split points')


@dataclasses.dataclass
class FluidSurrogate:
    """A surrogate of the fluid-dynamic block (see the module docstring)."""

    name: str
    kernel: Callable
    data: tuple
    meta: dict
    #: the module that rebuilds the artefact (``python -m <rebuild>``)
    rebuild: str = 'eha_ros.training.{lut,ga,nn,dynamic}'
    #: the kernel's disk-cached compiled forms (:data:`Forms`; ``None``: compiled per process)
    forms: Forms | None = None

    #: what the kernel gives: P12 (the reference's surrogates; :mod:`.edge`'s dynamic ones: flows)
    kernel_output = P12

    @property
    def loops(self) -> tuple | None:
        """The plant's loop with this kernel, explicit and split, cached on disk
        (:data:`Forms`, see :func:`eha_ros.physics.loop.fluid_kernels`); ``None`` without
        them: the loop is then compiled once per process."""
        return None if self.forms is None else (self.forms.run, self.forms.run_split)

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
        if self.forms is not None:
            self.forms.points(self.data, *flat, out)
        else:
            _vectorise(self.kernel, self.data, *flat, out)
        return out.reshape(arrs[0].shape) if arrs[0].ndim else float(out[0])

    def check_params(self, p: PlantParams) -> None:
        """Refuse parameters other than the fluid parameters the artefact was built for."""
        check_hash(self.meta, 'fluid_hash', fluid_hash(p), f'surrogate {self.name}',
                   self.rebuild, SurrogateError)


def relative_error(pred, true) -> float:
    """The reference's error metric: ``||pred - true||_2 / ||true||_2`` (Euclidean norms over
    all points; a map, a time history)."""
    pred = np.asarray(pred, dtype=float)
    true = np.asarray(true, dtype=float)
    return float(np.linalg.norm(pred - true) / np.linalg.norm(true))
