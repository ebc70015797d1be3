"""What a sweep runs at a point: the base of every procedure.

A procedure declares its metrics (name, type), its signals and its dataset columns, checks a
spec whole before anything runs (:meth:`Procedure.check`: one ``ValueError`` line), and runs a
point into one row per case (:meth:`Procedure.run_point`).  The procedures themselves sit
beside the code they call: the closed-loop scenario in :mod:`eha_ros.sweep.procedures` (which
holds the one table of procedures), the pre-flight check and the valve test in
:mod:`eha_ros.health.procedures`.  A case that diverges is a row with status ``diverged``, one
that raises a row with status ``error``; both carry the message in ``error``.
"""

from __future__ import annotations

import numpy as np

from eha_ros.evaluation import CONTROLLER_PERIOD_S, model_integrator
from eha_ros.physics import Plant, SimulationDiverged, default_params
from eha_ros.physics.params import SPEC_BY_NAME
from eha_ros.physics.stability import EXPLICIT, check_dt, integrator_substeps
from eha_ros.surrogates.registry import load_surrogate

__all__ = ['Procedure', 'label', 'status_of']


def label(inputs: dict) -> str:
    """A case's swept inputs as ``name=value, ...`` (``nominal`` without any)."""
    return ', '.join(f'{k}={v:g}' if isinstance(v, float) else f'{k}={v}'
                     for k, v in inputs.items()) or 'nominal'


def status_of(exc: BaseException) -> tuple:
    """``(status, error)`` of a case that raised ``exc``: ``diverged`` or ``error``, and the
    message."""
    status = 'diverged' if isinstance(exc, SimulationDiverged) else 'error'
    return status, f'{type(exc).__name__}: {exc}'


class Procedure:
    """A procedure: its metrics (name, type), signals, checks and the run of one point."""

    SIGNALS: tuple = ()
    #: Interval [s] the signals are recorded at (``signal_dt_s`` a whole multiple of it).
    RECORD_DT_S = CONTROLLER_PERIOD_S
    #: Whether the procedure runs in ticks of ``RECORD_DT_S`` (a whole number of steps).
    TICKED = True
    #: Whether it runs the plant's loop, and so takes the spec's ``integrator``.
    INTEGRATES = True

    def __init__(self, spec):
        self.spec = spec
        self._models = {}

    @classmethod
    def metrics(cls, compare=None) -> tuple:
        return ()

    @classmethod
    def metric_names(cls, compare=None) -> tuple:
        return tuple(n for n, _ in cls.metrics(compare))

    def wanted(self) -> tuple:
        """``(name, type)`` of the metric columns of this spec."""
        allm = self.metrics(self.spec.compare)
        if self.spec.metrics is None:
            return allm
        return tuple(m for m in allm if m[0] in self.spec.metrics)

    def columns(self) -> tuple:
        """``(name, type)`` of the dataset columns of this spec's rows besides the sweep's own
        (:func:`eha_ros.sweep.dataset.schema`): the swept inputs (``string`` for a choice),
        the wanted metrics and the kept signals (``floats``)."""
        spec = self.spec
        out = tuple((n, 'string' if SPEC_BY_NAME[n].choices else 'float')
                    for n in spec.input_names)
        return out + self.wanted() + tuple((f'signal_{s}', 'floats') for s in spec.signals)

    def check(self, where: str) -> None:
        """Every point's parameters within the plant's ranges and every model's validity;
        raises ``ValueError`` with one line starting with ``where``."""
        spec = self.spec
        for _, dt in spec.case_models():
            n = self.RECORD_DT_S / dt
            if self.TICKED and abs(n - round(n)) > 1e-9 * n:
                raise ValueError(f'{where}: dt_s = {dt:g} s: the tick of {self.RECORD_DT_S:g} s '
                                 'must be a whole multiple of the step')
        every = spec.signal_dt_s / self.RECORD_DT_S
        if self.TICKED and spec.signals and abs(every - round(every)) > 1e-9 * every:
            raise ValueError(f'{where}: signal_dt_s = {spec.signal_dt_s:g} s must be a whole '
                             f'multiple of {self.RECORD_DT_S:g} s')
        models = {}
        for m in spec.models:
            try:
                models[m] = self.model(m)
            except (ValueError, OSError) as exc:
                raise ValueError(f'{where}: model {m}: {exc}') from None
        seen = set()
        for pt in spec.points():
            key = tuple(sorted(pt.inputs.items()))
            if key in seen:   # the same parameters at another seed or scenario: checked
                continue
            seen.add(key)
            try:
                p = pt.params(spec)
                for c in pt.cases:
                    name, integ = model_integrator(c.model)
                    s = models.get(name)
                    if s is not None:
                        s.check_params(p)
                    if self.INTEGRATES:
                        integ = spec.integrator if integ == EXPLICIT else integ
                        integrator_substeps(integ, c.dt_s)
                        check_dt(p, c.dt_s, s, integ)
            except ValueError as exc:
                raise ValueError(f'{where}: case {label(pt.inputs)}: {exc}') from None

    def model(self, name):
        """The fluid block of model ``name`` (``None`` for hf; ``<name>@split`` is ``name``'s),
        loaded once."""
        name = model_integrator(name)[0]
        if name == 'hf':
            return None
        if name not in self._models:
            self._models[name] = load_surrogate(name, default_params())
        return self._models[name]

    def _signals(self, arrays: dict) -> dict:
        every = int(round(self.spec.signal_dt_s / self.RECORD_DT_S))
        return {f'signal_{s}': np.array(arrays[s], dtype=float)[every - 1::every]
                for s in self.spec.signals}

    def run_point(self, point) -> list:
        raise NotImplementedError

    def warm_up(self) -> None:
        """Load every model and compile its kernels (a short run each)."""
        p = self.spec.point_params({})
        for m in self.spec.models:
            Plant(p, dt_s=self.spec.dt_s, fluid=self.model(m),
                  integrator=self.spec.integrator).advance(0.0, 100)
