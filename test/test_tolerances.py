"""config/tolerances.yaml: every plant parameter classified, ranges physical, refusals in one
line; the shipped screening (docs/screening/screening.json) covers every drawn parameter and
holds every ``negligible`` one to its rule."""

import json
from pathlib import Path

from hypothesis import given, settings, strategies as st
import pytest
import yaml

from eha_ros.physics import default_params
from eha_ros.physics.bench import load_bench
from eha_ros.physics.params import SETTABLE, ParameterError, config_dir, replace
from eha_ros.physics.tolerances import CLASSES, DRAWN, NEGLIGIBLE_SIGMA, draw_unit, load_tolerances

ROOT = Path(__file__).resolve().parents[1]
SCREENING = ROOT / 'docs' / 'screening' / 'screening.json'
DOC = yaml.safe_load((config_dir() / 'tolerances.yaml').read_text())


def test_every_plant_parameter_has_one_class_and_a_reason():
    tol = load_tolerances()
    assert list(tol) == list(SETTABLE)
    assert {t.klass for t in tol.values()} <= set(CLASSES)
    assert all(t.reason for t in tol.values())
    # the ones a test reads are the items the two tests estimate
    est = {n for n, t in tol.items() if t.klass == 'estimated'}
    assert {'radial_clearance_m', 'overlap_supply_m', 'valve_degradation', 'demagnetisation',
            'filter_clogging', 'spool_static_friction_n', 'jack_static_friction_n',
            'offset_a', 'leakage_coeff_m3_s_pa'} <= est


def test_drawn_ranges_are_physical_and_bracket_nominal():
    p0 = default_params()
    for name, t in load_tolerances().items():
        if t.klass not in DRAWN:
            continue
        lo, hi = t.bounds(p0)
        assert lo <= hi
        for v in (lo, hi, 0.5 * (lo + hi)):
            replace(p0, **{name: v})   # refused if non-physical
        if not t.ratio_of:
            assert lo <= getattr(p0, name) <= hi, name


def test_the_bench_nuisances_are_the_trained_tolerances():
    """test_bench.yaml's nuisance list (what the shipped networks and the valve fit's
    calibration were drawn over) is the ``trained`` entries of tolerances.yaml, plus the two
    valve-fit items the pre-flight training draws as nuisance, with the same ranges."""
    b, tol = load_bench(), load_tolerances()
    trained = {n for n, t in tol.items() if t.trained}
    assert trained <= set(b.nuisance)
    for name, (lo, hi, rel) in b.nuisance.items():
        t = tol[name]
        if name in trained:
            assert (t.klass, t.lo, t.hi, t.relative) == ('nuisance', lo, hi, rel), name
        else:
            assert t.klass == 'estimated', name


def _write(tmp_path, doc) -> Path:
    path = tmp_path / 'tolerances.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


_names = st.sampled_from(sorted(DOC))
_drawn = st.sampled_from(sorted(n for n, e in DOC.items() if e['class'] in DRAWN))
_fixed = st.sampled_from(sorted(n for n, e in DOC.items() if e['class'] not in DRAWN))


@st.composite
def _broken(draw):
    """A copy of the shipped file with one defect, and a word the refusal must name."""
    doc = {k: dict(v) for k, v in DOC.items()}
    kind = draw(st.sampled_from(('missing', 'unknown', 'class', 'reason', 'swap', 'fixed_range',
                                 'no_range', 'ratio')))
    if kind == 'missing':
        name = draw(_names)
        del doc[name]
        return doc, name
    if kind == 'unknown':
        name = draw(st.from_regex(r'[a-z]{3,12}_[a-z]{2,6}', fullmatch=True).filter(
            lambda n: n not in DOC))
        doc[name] = {'class': 'setting', 'reason': 'x'}
        return doc, name
    if kind == 'class':
        name = draw(_names)
        doc[name]['class'] = draw(st.text('abcdefgxyz_', min_size=1, max_size=8).filter(
            lambda c: c not in CLASSES))
        return doc, name
    if kind == 'reason':
        name = draw(_names)
        doc[name]['reason'] = draw(st.sampled_from(('', '  ', None)))
        return doc, name
    if kind == 'swap':
        name = draw(_drawn.filter(lambda n: DOC[n]['lo'] < DOC[n]['hi']))
        doc[name]['lo'], doc[name]['hi'] = DOC[name]['hi'], DOC[name]['lo']
        return doc, name
    if kind == 'fixed_range':
        name = draw(_fixed)
        doc[name].update(lo=0.0, hi=1.0)
        return doc, name
    if kind == 'no_range':
        name = draw(_drawn)
        doc[name].pop(draw(st.sampled_from(('lo', 'hi'))))
        return doc, name
    name = draw(_drawn)
    doc[name]['ratio_of'] = 'not_a_parameter'
    return doc, name


@settings(max_examples=40, deadline=None)
@given(_broken())
def test_a_broken_tolerances_file_is_refused_in_one_line_naming_the_entry(
        tmp_path_factory, case):
    doc, word = case
    path = _write(tmp_path_factory.mktemp('tol'), doc)
    with pytest.raises(ParameterError) as e:
        load_tolerances(path)
    msg = str(e.value)
    assert '\n' not in msg and word in msg and str(path) in msg


def test_a_range_that_leaves_the_physical_limits_is_refused(tmp_path):
    doc = {k: dict(v) for k, v in DOC.items()}
    doc['discharge_coefficient'].update(lo=0.5, hi=1.5)   # Cd above 1
    with pytest.raises(ParameterError, match='discharge_coefficient.*range end 1.5'):
        load_tolerances(_write(tmp_path, doc))


# --- the shipped screening -----------------------------------------------------------------

@pytest.fixture(scope='module')
def screening():
    assert SCREENING.is_file(), f'{SCREENING} missing: run python bench/sensitivity.py'
    return json.loads(SCREENING.read_text())


def test_the_shipped_screening_covers_every_drawn_parameter_in_both_tests(screening):
    drawn = {n for n, t in load_tolerances().items() if t.klass in DRAWN}
    assert set(screening['tests']) == {'valve_test', 'preflight'}
    assert screening['smoke'] is False
    for name, r in screening['tests'].items():
        assert drawn <= set(r['largest_effect_sigma']), name
        assert r['trajectories_complete'] >= 4, name
        assert 'noise_seed' in r['largest_effect_sigma']   # the yardstick


def test_every_negligible_parameter_is_negligible_by_the_shipped_screening(screening):
    tol = load_tolerances()
    for name, t in tol.items():
        if t.klass != 'negligible':
            continue
        for test, r in screening['tests'].items():
            eff = r['largest_effect_sigma'][name]
            assert eff < NEGLIGIBLE_SIGMA, f'{name} moves a {test} estimate by {eff} sigma'


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), static=st.floats(0.0, 20.0))
def test_a_drawn_unit_is_a_valid_valve_inside_every_range(seed, static):
    """The fleet's one sampler: every nuisance inside its range about nominal, a dynamic
    friction inside its ratio of the breakaway friction it is given, the caller's changes kept
    as given, the same unit from the same stream, and always a valve the schema accepts."""
    import numpy as np
    tol, p = load_tolerances(), default_params()
    given_changes = {'spool_static_friction_n': static, 'radial_clearance_m': 4e-6}
    u = draw_unit(np.random.default_rng(seed), given_changes)
    assert u == draw_unit(np.random.default_rng(seed), given_changes)
    assert {n for n, t in tol.items() if t.klass == 'nuisance'} <= set(u)
    for name, t in tol.items():
        if t.klass != 'nuisance':
            continue
        if t.ratio_of:
            ref = u.get(t.ratio_of, getattr(p, t.ratio_of))
            assert t.lo * ref - 1e-12 <= u[name] <= t.hi * ref + 1e-12, name
        else:
            lo, hi = t.bounds(p)
            assert lo <= u[name] <= hi, name
    assert u['spool_static_friction_n'] == static and u['radial_clearance_m'] == 4e-6
    replace(p, **u)   # raises if the unit is not a valid valve
    left = draw_unit(np.random.default_rng(seed), exclude=('noise_std_a',))
    assert 'noise_std_a' not in left


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), gain=st.floats(0.5, 3.0), noise=st.floats(0.0, 1.0))
def test_error_shares_recover_a_known_linear_error(seed, gain, noise):
    """On drawn units, an error made of one parameter's standardised value, a bias and noise
    is shared in the proportions it was made of (closed form: gain**2, bias**2, noise**2 over
    their sum), within four sampling deviations of the fitted gain on 400 units (the noise's
    chance correlation with the parameter: sd(share) = 2 gain noise / sqrt(400) / mean(e**2))."""
    import numpy as np
    from eha_ros.physics.tolerances import error_shares
    rng = np.random.default_rng([seed, 0x5A7E])
    units = [draw_unit(rng, {'spool_static_friction_n': float(rng.uniform(0.5, 6.0))})
             for _ in range(400)]
    v = np.array([u['discharge_coefficient'] for u in units])
    z = (v - v.mean()) / v.std()
    e = gain * z + 0.5 + noise * rng.standard_normal(len(units))
    s = error_shares(np.column_stack([e, np.zeros(len(e))]), units)
    ms = float(np.mean(e ** 2))
    top = next(iter(s[0]['parameters']))
    assert top == 'discharge_coefficient'
    tol = 4 * 2 * gain * noise / np.sqrt(len(units)) / ms + 0.005
    assert s[0]['parameters'][top] == pytest.approx(gain ** 2 / ms, abs=tol)
    assert s[0]['bias'] == pytest.approx(np.mean(e) ** 2 / ms, abs=1e-3)
    parts = (sum(s[0]['parameters'].values()) + s[0]['other_parameters'] + s[0]['bias']
             + s[0]['rest'])
    assert parts == pytest.approx(1.0, abs=0.05)   # the sample's chance correlations
    assert s[1] == {'bias': 0.0, 'parameters': {}, 'other_parameters': 0.0, 'rest': 0.0}
    # dynamic frictions enter as their ratio; too few units for the parameters is refused
    assert 'spool_dynamic_friction_n' in {k for u in units for k in u}
    with pytest.raises(ValueError, match='more units than parameters'):
        error_shares(e[:10], units[:10])
