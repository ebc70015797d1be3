"""Physical parameters of the actuator: schema, YAML loading, validation and hashing.

Every parameter has one name, used unchanged in the YAML file, as ROS parameter and as
field of :class:`PlantParams` (the tuple the numba kernels take).  The schema below holds
its unit, its admissible range and what it means; the YAML file holds its value and the
reason that value was chosen.

The file format (``config/eha_params.yaml``) is a mapping ``name -> {value, unit, reason}``::

    supply_pressure_pa: {value: 2.06e+7, unit: Pa, reason: "3000 psi aircraft supply"}

Mode parameters (``cd_model``, ``torque_motor_model``) take a string from a fixed set and are
stored in :class:`PlantParams` as the index of that string.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
from collections import namedtuple
from pathlib import Path
from typing import Mapping

import yaml

from .fluid import FluidLaw, load_fluid

__all__ = [
    'ParamSpec', 'SPECS', 'PlantParams', 'ParameterError', 'load_params', 'params_from_mapping',
    'default_params', 'params_hash', 'params_to_dict', 'config_dir', 'CD_MODELS',
    'TORQUE_MOTOR_MODELS', 'DERIVED', 'SETTABLE',
]


class ParameterError(ValueError):
    """A parameter is missing, unknown, malformed or outside its physical range."""


CD_MODELS = ('reynolds', 'constant')
TORQUE_MOTOR_MODELS = ('fixed', 'magnetic')


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """Schema of one parameter.

    ``lo``/``hi`` bound the admissible value; ``lo_open``/``hi_open`` make a bound strict.
    ``choices`` turns the parameter into a mode selected by name.
    """

    name: str
    unit: str
    lo: float
    hi: float
    meaning: str
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple = ()

    def check(self, value: float) -> None:
        if not math.isfinite(value):
            raise ParameterError(f'parameter {self.name} = {value} is not finite')
        below = value <= self.lo if self.lo_open else value < self.lo
        above = value >= self.hi if self.hi_open else value > self.hi
        if below or above:
            lb = '(' if self.lo_open else '['
            rb = ')' if self.hi_open else ']'
            raise ParameterError(
                f'parameter {self.name} = {value:g} {self.unit} is non-physical: '
                f'must lie in {lb}{self.lo:g}, {self.hi:g}{rb} ({self.meaning})')


def _pos(name, unit, meaning, hi=math.inf):
    return ParamSpec(name, unit, 0.0, hi, meaning, lo_open=True)


def _nonneg(name, unit, meaning):
    return ParamSpec(name, unit, 0.0, math.inf, meaning)


def _frac(name, meaning, hi_open=False):
    return ParamSpec(name, '1', 0.0, 1.0, meaning, hi_open=hi_open)


SPECS: tuple[ParamSpec, ...] = (
    # --- hydraulic supply and fluid -------------------------------------------------------
    # Upper limits: what hydraulic servo systems reach, with margin (100 MPa: twice the
    # highest industrial supply; oils are 700-1100 kg/m^3, under 1e-2 m^2/s even cold, and
    # stiffer than 1e10 Pa only if the oil were steel), so a typo is refused up front.
    _pos('supply_pressure_pa', 'Pa', 'absolute supply pressure PS', hi=1e8),
    _pos('return_pressure_pa', 'Pa', 'absolute return pressure PR (must be below PS)', hi=1e8),
    _pos('nominal_supply_return_pa', 'Pa', 'PSR0, supply-return difference the first-stage '
         'gains were rated at', hi=1e8),
    _pos('vapour_pressure_pa', 'Pa', 'PVap, absolute pressure at which the oil cavitates',
         hi=1e6),
    # The fluid: its temperature and condition; its density and viscosity follow from the
    # fluid's datasheet law (config/fluid.yaml, eha_ros.physics.fluid) and are not set.
    _pos('fluid_temperature_k', 'K', 'fluid temperature; density and viscosity follow from '
         "the fluid's datasheet law", hi=600.0),
    _pos('fluid_condition_factor', '1', "the fluid's viscosity over its datasheet's at the "
         'same temperature (1: new fluid; service shear lowers it)', hi=10.0),
    _pos('fluid_density_kg_m3', 'kg/m^3', 'oil density rho (from fluid_temperature_k)',
         hi=2e3),
    _pos('fluid_kinematic_viscosity_m2_s', 'm^2/s', 'oil kinematic viscosity nu (from '
         'fluid_temperature_k and fluid_condition_factor)', hi=1e-2),
    _pos('bulk_modulus_pa', 'Pa', 'Bet, effective bulk modulus of oil, hoses and entrained air',
         hi=1e10),
    # --- controller -----------------------------------------------------------------------
    _nonneg('kp_a_m', 'A/m', 'proportional gain of the position controller'),
    _nonneg('ki_a_m_s', 'A/(m*s)', 'integral gain of the position controller'),
    _nonneg('kd_a_s_m', 'A*s/m', 'derivative gain of the position controller'),
    # --- torque motor ---------------------------------------------------------------------
    _pos('current_limit_a', 'A', 'CorM, coil current saturation (rated current)'),
    _nonneg('hysteresis_a', 'A', 'His, half-width of the magnetic hysteresis (play) band'),
    ParamSpec('offset_a', 'A', -1.0, 1.0, 'Ofs, current offset of the torque motor'),
    _nonneg('noise_std_a', 'A', 'standard deviation of the band-limited white current noise'),
    _pos('noise_sample_time_s', 's', 'hold time of each noise sample (its bandwidth is '
         '1/(2*hold))'),
    ParamSpec('torque_motor_model', '-', 0, 1, 'force from a fixed gain GM or from the '
              'magnetic circuit', choices=TORQUE_MOTOR_MODELS),
    _pos('torque_motor_gain_n_a', 'N/A', 'GM, force on the flapper per coil current'),
    _frac('demagnetisation', 'KGM, 0 nominal magnet .. 1 fully demagnetised'),
    _pos('magnet_mmf_a', 'A', 'Vp, magnetomotive force of the permanent magnets'),
    _pos('coil_turns', '1', 'n, coil turns'),
    _pos('air_gap_m', 'm', 'lg, length of each air gap at null'),
    _pos('air_gap_area_m2', 'm^2', 'Ag, pole face area of each air gap'),
    _pos('armature_length_m', 'm', 'La, armature length (pole to pole)'),
    _pos('flapper_arm_m', 'm', 'ls, pivot-to-nozzle distance of the flapper'),
    _pos('fringing_factor', '1', 'lambda + alpha*r, fringing correction of the gap reluctance'),
    # --- first stage ----------------------------------------------------------------------
    _pos('flapper_mass_kg', 'kg', 'MF, armature-flapper inertia referred to the nozzle'),
    _pos('flapper_stiffness_n_m', 'N/m', 'KF, flexure-tube (armature pivot) stiffness'),
    _pos('feedback_spring_stiffness_n_m', 'N/m', 'KSF, feedback spring stiffness'),
    _pos('flapper_damping_ratio', '1', 'ZF, damping ratio of the first stage', hi=10.0),
    _pos('flapper_stroke_m', 'm', 'XFM, flapper travel to the nozzle stop'),
    _nonneg('feedback_backlash_m', 'm', 'Kgioco, total play of the feedback-spring ball'),
    # --- second stage ---------------------------------------------------------------------
    _pos('spool_end_area_m2', 'm^2', 'ASV, spool end area driven by the first stage'),
    _pos('first_stage_pressure_gain_pa_m', 'Pa/m', 'GPF0, nozzle pressure gain per flapper '
         'displacement'),
    _pos('first_stage_flow_gain_m2_s', 'm^2/s', 'GQF0, nozzle flow gain per flapper '
         'displacement'),
    _nonneg('spool_damping_n_s_m', 'N*s/m', 'CS, viscous damping of the spool'),
    _nonneg('flow_force_coeff_n_s_m3', 'N*s/m^3', 'Kflow, steady flow force per load flow'),
    _nonneg('spool_static_friction_n', 'N', 'FSS, spool breakaway friction'),
    _nonneg('spool_dynamic_friction_n', 'N', 'FDS, spool sliding friction (<= FSS)'),
    _pos('spool_stroke_m', 'm', 'XSM, spool travel to its end stop'),
    _frac('filter_clogging', 'K_intas, 0 clean .. 1 fully clogged first-stage filter'),
    # --- fluid-dynamic valve (second-stage metering) ----------------------------------------
    _pos('port_width_m', 'm', 'w, circumferential width of each metering port'),
    ParamSpec('overlap_supply_m', 'm', -1e-3, 1e-3, 'OSSV, supply-edge overlap (<0 underlap)'),
    ParamSpec('overlap_return_m', 'm', -1e-3, 1e-3, 'ORSV, return-edge overlap (<0 underlap)'),
    _pos('radial_clearance_m', 'm', 'c, radial clearance between spool and sleeve', hi=1e-3),
    _frac('eccentricity_ratio', 'e/c, spool eccentricity relative to the clearance'),
    _pos('discharge_coefficient', '1', 'Cd, turbulent (asymptotic) discharge coefficient',
         hi=1.0),
    ParamSpec('cd_model', '-', 0, 1, 'Cd constant, or a function of the flow (Reynolds) '
              'number', choices=CD_MODELS),
    _pos('critical_flow_number', '1', 'lambda_crit, flow number of the laminar-turbulent '
         'transition'),
    _frac('valve_degradation', 'Khsv, 0 nominal .. 1 metering edges fully silted', True),
    _pos('chamber_volume_m3', 'm^3', 'Vol, oil volume of each jack chamber and its line'),
    _pos('map_volume_m3', 'm^3', 'Vol used when the valve alone is characterised (maps)'),
    _nonneg('leakage_coeff_m3_s_pa', 'm^3/(s*Pa)', 'Clk, cross-piston leakage of the jack'),
    # --- jack and load ----------------------------------------------------------------------
    _pos('jack_area_m2', 'm^2', 'AJ, jack piston area (equal-area jack)'),
    _pos('jack_mass_kg', 'kg', 'MJ, jack and surface mass referred to the rod'),
    _nonneg('jack_viscous_n_s_m', 'N*s/m', 'CJ, viscous friction of jack and surface'),
    _nonneg('aero_stiffness_n_m', 'N/m', 'Kaer, aerodynamic hinge-moment stiffness'),
    ParamSpec('external_force_n', 'N', -1e7, 1e7, 'external load opposing positive motion'),
    _nonneg('jack_static_friction_n', 'N', 'FSJ, jack breakaway friction'),
    _nonneg('jack_dynamic_friction_n', 'N', 'FDJ, jack sliding friction (<= FSJ)'),
    _pos('jack_stroke_m', 'm', 'XJM, jack travel to its end stop (either side of centre)'),
    _nonneg('surface_backlash_m', 'm', 'total play between jack and control surface'),
    _nonneg('sensor_resolution_m', 'm', 'quantum of the position sensor (0: ideal)'),
)

SPEC_BY_NAME = {s.name: s for s in SPECS}
#: Fields of :class:`PlantParams` that follow from others and are never set: the fluid's
#: density and viscosity, from its temperature and condition by the datasheet law.
DERIVED = ('fluid_density_kg_m3', 'fluid_kinematic_viscosity_m2_s')
#: The parameters one sets (a file, an override, a sweep): every field but :data:`DERIVED`.
SETTABLE = tuple(s.name for s in SPECS if s.name not in DERIVED)

#: The parameters as the kernels take them: one float64 per field, in schema order.
PlantParams = namedtuple('PlantParams', [s.name for s in SPECS])


def _coerce(spec: ParamSpec, raw, source: str) -> float:
    if spec.choices:
        if isinstance(raw, str) and raw in spec.choices:
            return float(spec.choices.index(raw))
        raise ParameterError(f'{source}: parameter {spec.name} = {raw!r} must be one of '
                             f'{", ".join(spec.choices)}')
    if isinstance(raw, bool) or raw is None:
        raise ParameterError(f'{source}: parameter {spec.name} = {raw!r} is not a number')
    try:
        return float(raw)
    except (TypeError, ValueError):
        raise ParameterError(f'{source}: parameter {spec.name} = {raw!r} is not a number'
                             ) from None


def _cross_check(p: PlantParams) -> None:
    """Relations between parameters that single ranges cannot express."""
    if p.return_pressure_pa >= p.supply_pressure_pa:
        raise ParameterError('parameter return_pressure_pa must be below supply_pressure_pa')
    if p.vapour_pressure_pa >= p.return_pressure_pa:
        raise ParameterError('parameter vapour_pressure_pa must be below return_pressure_pa')
    if p.spool_dynamic_friction_n > p.spool_static_friction_n:
        raise ParameterError('parameter spool_dynamic_friction_n must not exceed '
                             'spool_static_friction_n')
    if p.jack_dynamic_friction_n > p.jack_static_friction_n:
        raise ParameterError('parameter jack_dynamic_friction_n must not exceed '
                             'jack_static_friction_n')
    if p.offset_a and abs(p.offset_a) >= p.current_limit_a:
        raise ParameterError('parameter offset_a must be smaller than current_limit_a')
    if p.air_gap_m <= 0.5 * p.armature_length_m / p.flapper_arm_m * p.flapper_stroke_m:
        raise ParameterError('parameter air_gap_m must exceed the armature-tip travel at '
                             'full flapper stroke (flapper_stroke_m * La / (2 ls))')


def params_from_mapping(values: Mapping[str, object], source: str = 'parameters',
                        ) -> PlantParams:
    """Build and validate :class:`PlantParams` from ``name -> value`` (values or mode names).

    Raises :class:`ParameterError` naming the first missing, unknown or non-physical parameter.
    """
    unknown = sorted(set(values) - set(SPEC_BY_NAME))
    if unknown:
        raise ParameterError(f'{source}: unknown parameter {unknown[0]}')
    derived = [n for n in DERIVED if n in values]
    if derived:
        raise ParameterError(f'{source}: parameter {derived[0]} is not set: it follows from '
                             'fluid_temperature_k and fluid_condition_factor by the fluid '
                             'law (config/fluid.yaml)')
    out = {}
    for spec in (SPEC_BY_NAME[n] for n in SETTABLE):
        if spec.name not in values:
            raise ParameterError(f'{source}: missing parameter {spec.name} [{spec.unit}]')
        value = _coerce(spec, values[spec.name], source)
        try:
            spec.check(value)
        except ParameterError as exc:
            raise ParameterError(f'{source}: {exc}') from None
        out[spec.name] = value
    law = fluid_law()
    t, factor = out['fluid_temperature_k'], out['fluid_condition_factor']
    for name, value in (('fluid_density_kg_m3', law.density_kg_m3(t)),
                        ('fluid_kinematic_viscosity_m2_s', law.viscosity_m2_s(t, factor))):
        try:
            SPEC_BY_NAME[name].check(value)
        except ParameterError as exc:
            raise ParameterError(f'{source}: at fluid_temperature_k = {t:g} K: {exc}') from None
        out[name] = value
    p = PlantParams(**out)
    try:
        _cross_check(p)
    except ParameterError as exc:
        raise ParameterError(f'{source}: {exc}') from None
    return p


def replace(p: PlantParams, **changes) -> PlantParams:
    """Return ``p`` with some fields changed, validated again (mode names accepted)."""
    return params_from_mapping({**params_to_dict(p), **changes}, source='parameter override')


def params_to_dict(p: PlantParams, derived: bool = False) -> dict:
    """``name -> value`` of the settable parameters, mode parameters as their names (inverse
    of :func:`params_from_mapping`); ``derived``: the :data:`DERIVED` fields too."""
    return {spec.name: spec.choices[int(value)] if spec.choices else float(value)
            for spec, value in zip(SPECS, p) if derived or spec.name not in DERIVED}


def config_dir() -> Path:
    """The folder holding the YAML configuration.

    ``$EHA_ROS_CONFIG_DIR`` if set, else ``<prefix>/share/eha_ros/config`` of the installed
    package, else the ``config/`` folder of a source checkout.
    """
    env = os.environ.get('EHA_ROS_CONFIG_DIR')
    if env:
        return Path(env)
    import sys
    candidates = [Path(sys.prefix) / 'share' / 'eha_ros' / 'config',
                  Path(__file__).resolve().parents[2] / 'config']
    return next((c for c in candidates if (c / 'eha_params.yaml').is_file()), candidates[-1])


def fluid_law(path=None) -> FluidLaw:
    """The fluid's datasheet law (``config/fluid.yaml`` or ``path``)."""
    try:
        return load_fluid(path if path is not None else config_dir() / 'fluid.yaml')
    except ValueError as exc:
        raise ParameterError(str(exc)) from None


def read_yaml(path: Path | str, what: str, mapping: str = '') -> object:
    """Load a YAML file, turning every failure into a one-line :class:`ParameterError`; with
    ``mapping`` (what it maps, e.g. ``'name -> scenario'``) the document must be a mapping."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ParameterError(f'cannot read {what} file {path}: {exc.strerror}') from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = f' line {mark.line + 1}' if mark is not None else ''
        problem = getattr(exc, 'problem', None) or 'invalid YAML'
        raise ParameterError(f'malformed {what} file {path}{where}: {problem}') from None
    if mapping and not isinstance(doc, dict):
        raise ParameterError(f'malformed {what} file {path}: expected a mapping of {mapping}')
    return doc


def load_params(path: Path | str | None = None, **overrides) -> PlantParams:
    """Load ``config/eha_params.yaml`` (or ``path``) and apply ``overrides`` (name=value).

    Each entry must be ``{value, unit, reason}`` with the unit the schema expects.
    """
    path = Path(path) if path is not None else config_dir() / 'eha_params.yaml'
    doc = read_yaml(path, 'parameter', 'name -> {value, unit, reason}')
    values = {}
    for name, entry in doc.items():
        spec = SPEC_BY_NAME.get(name)
        if spec is None:
            raise ParameterError(f'{path}: unknown parameter {name}')
        if not isinstance(entry, dict) or 'value' not in entry:
            raise ParameterError(f'{path}: parameter {name} must be a mapping with a value, '
                                 'unit and reason')
        unit = str(entry.get('unit', ''))
        if unit != spec.unit:
            raise ParameterError(f'{path}: parameter {name} has unit {unit!r}, '
                                 f'expected {spec.unit!r}')
        if not str(entry.get('reason', '')).strip():
            raise ParameterError(f'{path}: parameter {name} has no reason')
        values[name] = entry['value']
    values.update(overrides)
    return params_from_mapping(values, source=str(path))


@functools.cache
def default_params() -> PlantParams:
    """The nominal parameters of ``config/eha_params.yaml`` (loaded once)."""
    return load_params()


def params_hash(p: PlantParams, names=None) -> str:
    """SHA-256 (hex, first 16 digits) of the parameter values, order- and format-stable.

    ``names`` restricts the hash to the parameters a derived artefact depends on.
    """
    d = params_to_dict(p, derived=True)
    if names is not None:
        d = {k: d[k] for k in names}
    blob = json.dumps({k: (repr(v) if isinstance(v, float) else v) for k, v in sorted(
        d.items())}, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
