"""The surrogate kinds, listed: each artefact's ``meta['kind']`` names the kernel that evaluates
it, the class that holds it and the module that rebuilds it.

A kind is added here, explicitly: no import side effect fills this table.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

from eha_ros.artefacts import load_artefact, models_dir
from eha_ros.physics import PlantParams, default_params
from eha_ros.surrogates import dga, dlut, dnn, ga, lut, nn
from eha_ros.surrogates.base import FluidSurrogate, Forms, SurrogateError

__all__ = ['Kind', 'KINDS', 'load_surrogate', 'shipped_surrogates']


@dataclasses.dataclass(frozen=True)
class Kind:
    """How artefacts of one kind are evaluated and rebuilt."""

    kernel: Callable
    cls: type
    #: ``python -m`` argument that rebuilds the artefact
    rebuild: str
    #: the kernel's disk-cached compiled forms (:data:`.base.Forms`)
    forms: Forms


KINDS = {
    'lut': Kind(lut.lut_kernel, FluidSurrogate, 'eha_ros.training.lut', lut.LUT_FORMS),
    'ga': Kind(ga.ga_kernel, FluidSurrogate, 'eha_ros.training.ga', ga.GA_FORMS),
    'mlp': Kind(nn.mlp_kernel, FluidSurrogate, 'eha_ros.training.nn', nn.MLP_FORMS),
    'dlut': Kind(dlut.dlut_kernel, dlut.DlutSurrogate, 'eha_ros.training.dynamic dlut',
                 dlut.DLUT_FORMS),
    'dnn': Kind(dnn.dnn_kernel, dnn.DnnSurrogate, 'eha_ros.training.dynamic dnn', dnn.DNN_FORMS),
    'dga': Kind(dga.dga_kernel, dga.DgaSurrogate, 'eha_ros.training.dynamic dga', dga.DGA_FORMS),
}


#: Shipped artefacts whose kind is not their name.
_SHIPPED_KINDS = {'nn': 'mlp', 'nn2': 'mlp'}


def shipped_surrogates() -> list[str]:
    """Names of the surrogate artefacts in :func:`eha_ros.artefacts.models_dir`."""
    return sorted(f.stem for f in models_dir('surrogates').glob('*.npz'))


def load_surrogate(name: str, params: PlantParams | None = None,
                   path: Path | None = None) -> FluidSurrogate:
    """Load the shipped surrogate ``name`` (``lut``, ``ga``, ``nn``, ``nn2``, ``dlut``...) and
    check it was built for ``params`` (default: the nominal parameters)."""
    p = params if params is not None else default_params()
    path = Path(path) if path is not None else models_dir('surrogates') / f'{name}.npz'
    if not path.is_file():
        raise SurrogateError(f'unknown surrogate {name!r} (shipped: '
                             f'{", ".join(shipped_surrogates())})')
    known = KINDS.get(_SHIPPED_KINDS.get(name, name))  # what rebuilds it, should it not load
    data, meta = load_artefact(path, known.rebuild if known else FluidSurrogate.rebuild,
                               SurrogateError)
    kind = KINDS.get(meta.get('kind'))
    if kind is None:
        raise SurrogateError(f'{path}: unknown surrogate kind {meta.get("kind")!r} (one of '
                             f'{", ".join(KINDS)})')
    s = kind.cls(name=name, kernel=kind.kernel, data=data, meta=meta, rebuild=kind.rebuild,
                 forms=kind.forms)
    s.check_params(p)
    return s
