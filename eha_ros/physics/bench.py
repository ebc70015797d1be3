"""The maintenance test bench: the measured test conditions and the envelopes of
``config/test_bench.yaml``.

A test bench measures the conditions of a test - supply and return pressure, fluid
temperature - and a diagnosis takes them as inputs; what no bench measures (the bulk modulus,
metering-edge silting, hysteresis, ...) is drift the diagnosis must see through.

Fluid
    The plant's fluid is its temperature and its condition (``fluid_temperature_k``,
    ``fluid_condition_factor``); the viscosity and density follow from the datasheet law of
    :mod:`eha_ros.physics.fluid` (``config/fluid.yaml``).  The bench's sensor measures the
    temperature; the condition (a sheared or another batch of fluid) no bench measures.

Measured conditions
    :func:`measure_conditions`: a reading is the true value plus a calibration error fixed
    for the test (uniform within the sensor's ``bias``) plus white noise, quantised to its
    resolution.  The estimators use the mean reading of a test (:class:`Conditions`).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .fluid import FluidLaw
from .params import (ParameterError, PlantParams, config_dir, default_params, fluid_law,
                     read_yaml, replace)

__all__ = ['CONDITIONS', 'Conditions', 'ConditionSensors', 'outside_ranges', 'FluidLaw',
           'TestBench', 'load_bench', 'true_conditions', 'measure_conditions',
           'mean_conditions', 'with_conditions']

#: The measured test conditions, in order.
CONDITIONS = ('supply_pressure_pa', 'return_pressure_pa', 'fluid_temperature_k')


@dataclasses.dataclass(frozen=True)
class Conditions:
    """Conditions of one test [Pa, Pa, K]; ``assumed``: not measured, nominal values taken."""

    supply_pressure_pa: float
    return_pressure_pa: float
    fluid_temperature_k: float
    assumed: bool = False

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in CONDITIONS + ('assumed',)}

    def array(self) -> np.ndarray:
        return np.array([getattr(self, k) for k in CONDITIONS])


@dataclasses.dataclass(frozen=True)
class Sensor:
    noise_std: float
    resolution: float
    bias: float
    unit: str


@dataclasses.dataclass(frozen=True)
class TestBench:
    """``config/test_bench.yaml``: fluid law, sensors, service envelope, nuisance drift."""

    fluid: FluidLaw
    sensors: dict          # name -> Sensor
    service: dict          # name -> (lo, hi)
    nuisance: dict         # name -> (lo, hi, relative)
    beyond: dict           # name -> {'factors': [...]} or {'values': [...]}
    reasons: dict

    def nuisance_range(self, name: str, params: PlantParams | None = None) -> tuple:
        """Absolute ``(lo, hi)`` of a nuisance parameter."""
        lo, hi, rel = self.nuisance[name]
        if rel:
            nominal = getattr(params or default_params(), name)
            return lo * nominal, hi * nominal
        return lo, hi

    def outside_service(self, c: Conditions) -> list:
        """One phrase per measured condition outside the service envelope."""
        return outside_ranges(self.service, c)


def outside_ranges(service: dict, c: Conditions) -> list:
    """One phrase per condition of ``c`` outside ``service`` (``name -> (lo, hi)``)."""
    out = []
    for name in CONDITIONS:
        v = getattr(c, name)
        lo, hi = service[name]
        if not lo <= v <= hi:
            out.append(f'measured {name} = {v:.4g} outside the service range '
                       f'[{lo:.4g}, {hi:.4g}]')
    return out


def load_bench(path=None) -> TestBench:
    """Load ``config/test_bench.yaml`` (or ``path``); the fluid law is the datasheet's
    (:func:`eha_ros.physics.fluid.load_fluid`)."""
    path = path or config_dir() / 'test_bench.yaml'
    return _load(str(path), default_params(), fluid_law())


@functools.lru_cache(maxsize=8)
def _load(path: str, p: PlantParams, law: FluidLaw) -> TestBench:
    doc = read_yaml(path, 'test bench', 'section -> entries')
    unknown = sorted(set(doc) - {'sensors', 'service', 'nuisance', 'beyond'})
    if unknown:
        raise ParameterError(f'{path}: unknown section {unknown[0]}')
    try:
        sensors, service, nuisance, reasons = {}, {}, {}, {}
        for name in CONDITIONS:
            s = doc['sensors'][name]
            sensors[name] = Sensor(float(s['noise_std']), float(s['resolution']),
                                   float(s['bias']), str(s.get('unit', '')))
            if not (sensors[name].resolution > 0 and sensors[name].noise_std >= 0
                    and sensors[name].bias >= 0):
                raise ParameterError(f'{path}: sensors: {name} needs a positive resolution '
                                     'and non-negative noise_std and bias')
            e = doc['service'][name]
            service[name] = (float(e['lo']), float(e['hi']))
            reasons[f'service.{name}'] = str(e.get('reason', ''))
            if not service[name][0] < service[name][1]:
                raise ParameterError(f'{path}: service: {name} needs lo < hi')
        for name, e in (doc.get('nuisance') or {}).items():
            if not hasattr(p, name):
                raise ParameterError(f'{path}: nuisance: unknown plant parameter {name}')
            nuisance[name] = (float(e['lo']), float(e['hi']), bool(e.get('relative', False)))
            reasons[f'nuisance.{name}'] = str(e.get('reason', ''))
            if not nuisance[name][0] <= nuisance[name][1]:
                raise ParameterError(f'{path}: nuisance: {name} needs lo <= hi')
        beyond = {str(k): dict(v) for k, v in (doc.get('beyond') or {}).items()}
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, ParameterError):
            raise
        raise ParameterError(f'{path}: missing or malformed entry {exc}') from None
    return TestBench(law, sensors, service, nuisance, beyond, reasons)


def with_conditions(params: PlantParams, c: Conditions, bench: TestBench | None = None
                    ) -> PlantParams:
    """``params`` at the conditions ``c``: supply and return pressure, and the fluid (of
    ``params``' condition) at its temperature.  ``bench``: unused, kept for the callers that
    pass it."""
    return replace(params, supply_pressure_pa=float(c.supply_pressure_pa),
                   return_pressure_pa=float(c.return_pressure_pa),
                   fluid_temperature_k=float(c.fluid_temperature_k))


def true_conditions(params: PlantParams, bench: TestBench | None = None) -> Conditions:
    """The plant's true test conditions."""
    return Conditions(params.supply_pressure_pa, params.return_pressure_pa,
                      params.fluid_temperature_k)


class ConditionSensors:
    """The bench's transducers of :data:`CONDITIONS` for one test: a calibration error drawn
    once from ``seed`` (uniform within each sensor's bias), then at every :meth:`read` the
    true value of the parameters it is given, plus white noise, quantised.  Deterministic in
    ``seed`` and the number of readings taken."""

    def __init__(self, seed: int, bench: TestBench | None = None):
        self.bench = bench or load_bench()
        self._rng = np.random.default_rng([int(seed), 0xBE7C])
        sens = [self.bench.sensors[k] for k in CONDITIONS]
        self._bias = np.array([self._rng.uniform(-s.bias, s.bias) for s in sens])
        self._noise = np.array([s.noise_std for s in sens])
        self._step = np.array([s.resolution for s in sens])
        self._params = self._offset = None

    def read(self, params: PlantParams, n: int = 1) -> np.ndarray:
        """``(n, 3)`` readings of the conditions of ``params`` (the plant calls it every
        tick: the true values plus bias are kept while ``params`` is the same object)."""
        if params is not self._params:
            self._params = params
            self._offset = true_conditions(params, self.bench).array() + self._bias
        out = self._offset + self._rng.standard_normal((n, 3)) * self._noise
        return np.round(out / self._step) * self._step


def measure_conditions(params: PlantParams, seed: int, n: int = 1,
                       bench: TestBench | None = None) -> np.ndarray:
    """The first ``n`` readings ``(n, 3)`` of :class:`ConditionSensors` (``seed``) on
    ``params``: what the plant reports over the first ``n`` ticks of a run."""
    return ConditionSensors(seed, bench).read(params, n)


def mean_conditions(readings, assumed: bool = False) -> Conditions:
    """The conditions of a test: the mean of its readings ``(n, 3)``."""
    r = np.asarray(readings, dtype=float).reshape(-1, 3)
    if r.shape[0] == 0 or not np.all(np.isfinite(r)):
        raise ParameterError('measured test conditions: no finite reading')
    m = r.mean(axis=0)
    return Conditions(float(m[0]), float(m[1]), float(m[2]), assumed)
