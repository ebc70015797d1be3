"""The maintenance test bench: the fluid's temperature law, the measured test conditions and
the envelopes of ``config/test_bench.yaml``.

A test bench measures the conditions of a test - supply and return pressure, fluid
temperature - and a diagnosis takes them as inputs; what no bench measures (the bulk modulus,
metering-edge silting, hysteresis, ...) is drift the diagnosis must see through.

Fluid law
    Kinematic viscosity by Walther's equation (ASTM D341),
    ``log10(log10(nu_cSt + 0.7)) = A - B log10(T)``, through the datasheet's viscosities at
    the reference and the hot temperature (``config/test_bench.yaml``); density
    ``rho(T) = rho_ref / (1 + alpha (T - T_ref))``.  The law is anchored once, at the
    datasheet: never at the parameters of a run, in any path (the nominal fluid of
    ``config/eha_params.yaml`` must be the datasheet's at the reference temperature, checked
    on load).  :func:`fluid_at` gives viscosity and density at a temperature,
    :func:`temperature_of` the temperature of a viscosity (the plant's fluid has the
    temperature its viscosity says by this law).

Measured conditions
    :func:`measure_conditions`: a reading is the true value plus a calibration error fixed
    for the test (uniform within the sensor's ``bias``) plus white noise, quantised to its
    resolution.  The estimators use the mean reading of a test (:class:`Conditions`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .params import ParameterError, PlantParams, config_dir, default_params, read_yaml, replace

__all__ = ['CONDITIONS', 'Conditions', 'ConditionSensors', 'outside_ranges', 'FluidLaw',
           'TestBench', 'load_bench', 'fluid_at', 'temperature_of', 'true_conditions',
           'measure_conditions', 'mean_conditions', 'with_conditions']

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
class FluidLaw:
    """Walther viscosity and linear-expansion density of the fluid (see the module)."""

    name: str
    a: float
    b: float
    reference_temperature_k: float
    reference_density_kg_m3: float
    expansion_coefficient_1_k: float

    def viscosity_m2_s(self, temperature_k: float) -> float:
        w = self.a - self.b * math.log10(temperature_k)
        return (10.0 ** (10.0 ** w) - 0.7) * 1e-6

    def density_kg_m3(self, temperature_k: float) -> float:
        return self.reference_density_kg_m3 / (
            1.0 + self.expansion_coefficient_1_k * (temperature_k - self.reference_temperature_k))

    def temperature_k(self, viscosity_m2_s: float) -> float:
        w = math.log10(math.log10(viscosity_m2_s * 1e6 + 0.7))
        return 10.0 ** ((self.a - w) / self.b)


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


def _num(doc, key, where):
    try:
        v = doc[key]
        return float(v['value'] if isinstance(v, dict) else v)
    except (KeyError, TypeError, ValueError):
        raise ParameterError(f'{where}: {key} must be a number') from None


def load_bench(path=None) -> TestBench:
    """Load ``config/test_bench.yaml`` (or ``path``).  The fluid law is the datasheet's
    (anchored in the file, never at a run's parameters); the nominal parameters'
    (``default_params()``) viscosity and density must be the law's at its reference
    temperature."""
    path = path or config_dir() / 'test_bench.yaml'
    return _load(str(path), default_params())


#: Relative agreement required between the nominal fluid of the parameters and the datasheet.
_ANCHOR_RTOL = 1e-9


@functools.lru_cache(maxsize=8)
def _load(path: str, p: PlantParams) -> TestBench:
    doc = read_yaml(path, 'test bench', 'section -> entries')
    unknown = sorted(set(doc) - {'fluid', 'sensors', 'service', 'nuisance', 'beyond'})
    if unknown:
        raise ParameterError(f'{path}: unknown section {unknown[0]}')
    try:
        f = doc['fluid']
        t_ref = _num(f, 'reference_temperature_k', f'{path}: fluid')
        t_hot = _num(f, 'hot_temperature_k', f'{path}: fluid')
        nu_hot = _num(f, 'hot_viscosity_m2_s', f'{path}: fluid')
        alpha = _num(f, 'expansion_coefficient_1_k', f'{path}: fluid')
        nu_ref = _num(f, 'reference_viscosity_m2_s', f'{path}: fluid')
        rho_ref = _num(f, 'reference_density_kg_m3', f'{path}: fluid')
        if not (t_hot > t_ref > 0 and 0 < nu_hot < nu_ref and alpha >= 0 and rho_ref > 0):
            raise ParameterError(f'{path}: fluid: need hot_temperature_k > reference > 0, '
                                 'a hot viscosity below the reference one and a positive '
                                 'density')
        for name, law_value in (('fluid_kinematic_viscosity_m2_s', nu_ref),
                                ('fluid_density_kg_m3', rho_ref)):
            if abs(getattr(p, name) / law_value - 1.0) > _ANCHOR_RTOL:
                raise ParameterError(
                    f'{path}: fluid: the nominal {name} = {getattr(p, name):.6g} is not the '
                    f'datasheet\'s {law_value:.6g} at {t_ref:g} K (one fluid: change both)')
        w = [math.log10(math.log10(nu * 1e6 + 0.7)) for nu in (nu_ref, nu_hot)]
        b = (w[0] - w[1]) / (math.log10(t_hot) - math.log10(t_ref))
        law = FluidLaw(str(f.get('name', 'fluid')), w[0] + b * math.log10(t_ref), b, t_ref,
                       rho_ref, alpha)
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


def fluid_at(temperature_k: float, bench: TestBench | None = None) -> dict:
    """Plant parameters of the fluid at ``temperature_k``: viscosity and density."""
    law = (bench or load_bench()).fluid
    return {'fluid_kinematic_viscosity_m2_s': law.viscosity_m2_s(temperature_k),
            'fluid_density_kg_m3': law.density_kg_m3(temperature_k)}


def temperature_of(params: PlantParams, bench: TestBench | None = None) -> float:
    """The fluid temperature [K] at which the fluid law gives ``params``' viscosity."""
    return (bench or load_bench()).fluid.temperature_k(params.fluid_kinematic_viscosity_m2_s)


def with_conditions(params: PlantParams, c: Conditions, bench: TestBench | None = None
                    ) -> PlantParams:
    """``params`` at the conditions ``c``: supply and return pressure, and the fluid at its
    temperature."""
    return replace(params, supply_pressure_pa=float(c.supply_pressure_pa),
                   return_pressure_pa=float(c.return_pressure_pa),
                   **fluid_at(float(c.fluid_temperature_k), bench))


def true_conditions(params: PlantParams, bench: TestBench | None = None) -> Conditions:
    """The plant's true test conditions."""
    return Conditions(params.supply_pressure_pa, params.return_pressure_pa,
                      temperature_of(params, bench))


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
