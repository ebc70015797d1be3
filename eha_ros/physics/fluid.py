"""The hydraulic fluid's datasheet law (``config/fluid.yaml``): viscosity and density at a
temperature.

The plant's fluid is set by its temperature ``fluid_temperature_k`` and its condition
``fluid_condition_factor`` (:mod:`eha_ros.physics.params`); its kinematic viscosity and its
density follow from this law, anchored once at the datasheet and never at a run's parameters:

* viscosity by Walther's equation (ASTM D341), ``log10(log10(nu_cSt + 0.7)) = A - B
  log10(T)``, through the datasheet's viscosities at the reference and the hot temperature,
  times the condition factor (1: new fluid of the datasheet; a polymer-thickened fluid sheared
  in service has less, another batch a few per cent either way; taken the same at every
  temperature);
* density ``rho(T) = rho_ref / (1 + alpha (T - T_ref))``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

__all__ = ['FluidLaw', 'load_fluid']


@dataclasses.dataclass(frozen=True)
class FluidLaw:
    """Walther viscosity and linear-expansion density of the fluid (see the module)."""

    name: str
    a: float
    b: float
    reference_temperature_k: float
    reference_density_kg_m3: float
    expansion_coefficient_1_k: float
    reference_viscosity_m2_s: float

    def viscosity_m2_s(self, temperature_k: float, condition_factor: float = 1.0) -> float:
        """Kinematic viscosity [m^2/s] at ``temperature_k``, times ``condition_factor``
        (at the reference temperature exactly the datasheet's figure)."""
        if temperature_k == self.reference_temperature_k:
            return self.reference_viscosity_m2_s * condition_factor
        w = self.a - self.b * math.log10(temperature_k)
        try:
            return (10.0 ** (10.0 ** w) - 0.7) * 1e-6 * condition_factor
        except OverflowError:   # far below any fluid's pour point
            return math.inf

    def density_kg_m3(self, temperature_k: float) -> float:
        return self.reference_density_kg_m3 / (
            1.0 + self.expansion_coefficient_1_k * (temperature_k - self.reference_temperature_k))

    def temperature_k(self, viscosity_m2_s: float, condition_factor: float = 1.0) -> float:
        """The temperature [K] at which a fluid of ``condition_factor`` has
        ``viscosity_m2_s``."""
        w = math.log10(math.log10(viscosity_m2_s / condition_factor * 1e6 + 0.7))
        return 10.0 ** ((self.a - w) / self.b)


def load_fluid(path) -> FluidLaw:
    """The law of the fluid file ``path`` (``config/fluid.yaml``:
    :func:`eha_ros.physics.params.fluid_law` finds it); a one-line :class:`ValueError` if it
    is missing or non-physical."""
    path = Path(path)
    try:
        mtime = path.stat().st_mtime_ns
    except OSError:
        mtime = None
    return _load(str(path), mtime)


def _num(doc, key, where):
    try:
        v = doc[key]
        value = float(v['value'] if isinstance(v, dict) else v)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f'{where}: {key} must be a number') from None
    if not math.isfinite(value):
        raise ValueError(f'{where}: {key} must be finite')
    return value


@functools.lru_cache(maxsize=8)
def _load(path: str, mtime) -> FluidLaw:
    import yaml
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f'cannot read fluid file {path}: {type(exc).__name__}') from None
    if not isinstance(doc, dict):
        raise ValueError(f'malformed fluid file {path}: expected a mapping')
    keys = ('reference_temperature_k', 'reference_viscosity_m2_s', 'reference_density_kg_m3',
            'hot_temperature_k', 'hot_viscosity_m2_s', 'expansion_coefficient_1_k')
    unknown = sorted(set(doc) - set(keys) - {'name'})
    if unknown:
        raise ValueError(f'{path}: unknown entry {unknown[0]}')
    t_ref, nu_ref, rho_ref, t_hot, nu_hot, alpha = (_num(doc, k, path) for k in keys)
    if not (t_hot > t_ref > 0 and 0 < nu_hot < nu_ref and alpha >= 0 and rho_ref > 0):
        raise ValueError(f'{path}: need hot_temperature_k > reference_temperature_k > 0, '
                         'a hot viscosity below the reference one, a positive density and '
                         'a non-negative expansion coefficient')
    w = [math.log10(math.log10(nu * 1e6 + 0.7)) for nu in (nu_ref, nu_hot)]
    b = (w[0] - w[1]) / (math.log10(t_hot) - math.log10(t_ref))
    return FluidLaw(str(doc.get('name', 'fluid')), w[0] + b * math.log10(t_ref), b, t_ref,
                    rho_ref, alpha, nu_ref)
