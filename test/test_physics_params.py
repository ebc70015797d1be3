"""Parameters: the YAML file, validation with clear errors, hashing, layering."""

import subprocess
import sys

import numpy as np
import pytest
import yaml

from eha_ros.physics.maps import WEAR_RANGES
from eha_ros.physics.params import (DERIVED, SETTABLE, SPEC_BY_NAME, ParameterError,
                                    config_dir, default_params, load_params, params_hash,
                                    params_to_dict, replace)

P = default_params()
TEXT = (config_dir() / 'eha_params.yaml').read_text()


def test_every_parameter_has_value_unit_and_reason():
    doc = yaml.safe_load(TEXT)
    assert set(doc) == set(SETTABLE)
    for spec in (SPEC_BY_NAME[n] for n in SETTABLE):
        entry = doc[spec.name]
        assert entry['unit'] == spec.unit
        assert len(entry['reason'].split()) >= 3, spec.name


def test_nominal_wear_inside_swept_ranges():
    lo, hi = WEAR_RANGES['overlap_m']
    assert lo < P.overlap_supply_m < hi and lo < P.overlap_return_m < hi
    lo, hi = WEAR_RANGES['radial_clearance_m']
    assert lo < P.radial_clearance_m < hi


def test_blocked_load_plateau_is_the_supply_to_return_difference():
    """With the load blocked (Q = 0) and the spool half open, the chambers settle at the
    supply and return pressures: P12 = +-(Ps - Pr), the zero-flow plateau the reference's GA
    pins as c1.  Tolerance 0.5 %: the covered edges leak through the radial clearance (the
    laminar drop is about 0.1 % at nominal wear)."""
    from eha_ros.physics.maps import steady_map
    xs = 0.5 * P.spool_stroke_m * np.array([1.0, -1.0])
    p12 = steady_map(xs, np.zeros(2), P.overlap_supply_m, P.radial_clearance_m,
                     params=P)['p12_pa']
    dp = P.supply_pressure_pa - P.return_pressure_pa
    np.testing.assert_allclose(p12, [dp, -dp], rtol=5e-3)
    assert abs(p12[0]) < dp  # leakage lowers it, never raises it


def _write(tmp_path, text):
    f = tmp_path / 'p.yaml'
    f.write_text(text)
    return f


def _without(name):
    return '\n'.join(line for line in TEXT.splitlines() if not line.startswith(name + ':'))


def _with(name, value):
    doc = yaml.safe_load(TEXT)
    doc[name]['value'] = value
    return yaml.safe_dump(doc)


@pytest.mark.parametrize('text, message', [
    (_without('jack_mass_kg'), 'missing parameter jack_mass_kg'),
    (_with('jack_mass_kg', -20.0), 'jack_mass_kg = -20 kg is non-physical'),
    (_with('radial_clearance_m', 0.0), 'radial_clearance_m = 0 m is non-physical'),
    (_with('flapper_mass_kg', float('nan')), 'flapper_mass_kg = nan is not finite'),
    (_with('kp_a_m', 'fast'), 'kp_a_m = .fast. is not a number'),
    (_with('cd_model', 'magic'), 'cd_model = .magic. must be one of reynolds, constant'),
    (_with('return_pressure_pa', 3e7), 'return_pressure_pa must be below supply'),
    (_with('spool_dynamic_friction_n', 5.0), 'spool_dynamic_friction_n must not exceed'),
    (TEXT + '\nwarp_drive: {value: 1, unit: "1", reason: "x y z"}\n',
     'unknown parameter warp_drive'),
    (TEXT.replace('jack_area_m2: {value: 1.0e-3, unit: m^2',
                  'jack_area_m2: {value: 1.0e-3, unit: cm^2'), "unit 'cm\\^2'"),
    (TEXT.replace('reason: "new fluid, on its datasheet"', 'reason: ""'),
     'fluid_condition_factor has no reason'),
    (TEXT + '\nfluid_density_kg_m3: {value: 850.0, unit: kg/m^3, reason: "x y z"}\n',
     'fluid_density_kg_m3 is not set: it follows from fluid_temperature_k'),
    (_with('fluid_temperature_k', 20.0),
     'at fluid_temperature_k = 20 K: .*fluid_kinematic_viscosity_m2_s = inf is not finite'),
    ('supply_pressure_pa: {value: [1, 2\n', 'malformed parameter file .* line'),
    ('- just\n- a list\n', 'expected a mapping'),
])
def test_bad_parameter_files_are_refused_with_one_line(tmp_path, text, message):
    with pytest.raises(ParameterError, match=message) as exc:
        load_params(_write(tmp_path, text))
    assert '\n' not in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(ParameterError, match='cannot read parameter file'):
        load_params(tmp_path / 'nope.yaml')


def test_overrides_and_roundtrip():
    p = load_params(radial_clearance_m=4e-6, cd_model='constant')
    assert p.radial_clearance_m == 4e-6 and p.cd_model == 1.0
    assert params_to_dict(p)['cd_model'] == 'constant'
    assert replace(p, cd_model='reynolds').cd_model == 0.0


def test_hash_is_stable_and_sensitive():
    h = params_hash(P)
    assert h == params_hash(load_params()) and len(h) == 16
    assert params_hash(replace(P, radial_clearance_m=3e-6)) != h
    names = ['supply_pressure_pa', 'return_pressure_pa']
    assert params_hash(replace(P, jack_mass_kg=30.0), names) == params_hash(P, names)


def test_physics_layer_imports_neither_ros_nor_torch(tmp_path):
    code = ('import sys, eha_ros.physics, eha_ros.physics.maps; '
            'bad = [m for m in ("rclpy", "torch") if m in sys.modules]; print(bad); '
            'sys.exit(1 if bad else 0)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr


def test_simulate_cli_bad_input_one_line_and_exit_code(tmp_path):
    run = [sys.executable, '-m', 'eha_ros.tools.simulate']
    out = subprocess.run(run + ['--set', 'jack_mass_kg=-1'], capture_output=True, text=True,
                         cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.count('\n') == 1 and 'jack_mass_kg' in out.stderr
    existing = tmp_path / 'keep.png'
    existing.write_bytes(b'precious')
    out = subprocess.run(run + ['--plot', str(existing), '--duration', '0.001'],
                         capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 2 and 'refusing to overwrite' in out.stderr
    assert existing.read_bytes() == b'precious'


@pytest.mark.parametrize('name, value', [('supply_pressure_pa', 1e12),
                                         ('bulk_modulus_pa', 1e13),
                                         ('fluid_temperature_k', 1e4),
                                         ('fluid_condition_factor', 0.0)])
def test_non_physical_fluid_values_are_refused_up_front(name, value):
    """Values no hydraulic system has (a 1e12 Pa supply made the run diverge) are refused
    with a one-line error naming the parameter and its admissible range."""
    from eha_ros.physics.params import replace
    with pytest.raises(ParameterError, match=f'{name} .* non-physical'):
        replace(default_params(), **{name: value})


@pytest.mark.parametrize('name', DERIVED)
def test_the_fluids_density_and_viscosity_are_not_set_but_follow_its_temperature(name):
    """The fluid's density and viscosity follow from its temperature and condition by the
    datasheet law: an override of either is refused with the reason, and a changed temperature
    moves both (the dictionary of settable parameters round-trips)."""
    with pytest.raises(ParameterError, match=f'{name} is not set'):
        replace(P, **{name: getattr(P, name)})
    hot = replace(P, fluid_temperature_k=353.15)
    assert getattr(hot, name) < getattr(P, name)
    assert name not in params_to_dict(hot) and name in params_to_dict(hot, derived=True)
    assert replace(hot) == hot
