"""The in-loop comparison's bookkeeping (:mod:`eha_ros.evaluation`): the step ladder,
the seeds' statistics and the larger-step runs."""

import math

import numpy as np
import pytest

from eha_ros.physics import default_params
from eha_ros.physics.params import replace
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.evaluation import (DT_S, SETTLED_FRACTION, WEAR_POINTS, converged_summary,
                                largest_steps, noise_free, run, with_noise)
from eha_ros.surrogates.base import relative_error


def _row(meeting, cases=3, cost=1.0):
    return {'cases': cases, 'cases_meeting_bounds': meeting, 'median_cost_vs_hf': cost}


def test_largest_steps_stops_at_the_first_step_that_misses_a_case():
    summary = {'dlut': _row(3, cost=1.5), 'dlut@dt=2e-06': _row(3, cost=0.8),
               'dlut@dt=5e-06': _row(2, cost=0.3), 'dlut@dt=1e-05': _row(3, cost=0.2),
               'dnn': _row(2), 'dnn@dt=2e-06': _row(3),
               'hf@dt=2e-06': _row(3, cost=0.5), 'hf@dt=5e-06': _row(3, cost=0.2),
               'lut': _row(0)}
    out = largest_steps(summary)
    # 10 us meets again, but 5 us did not: the ladder is not monotonic, so it stops at 2 us
    assert out['dlut']['largest_step_s'] == 2e-6
    assert out['dlut']['median_cost_vs_hf_at_it'] == 0.8
    assert out['dlut']['steps_tried_s'] == [1e-6, 2e-6, 5e-6, 1e-5]
    assert out['dnn']['largest_step_s'] is None  # misses at 1 us already
    assert out['hf']['largest_step_s'] == 5e-6 and out['hf']['steps_tried_s'][0] == DT_S
    assert 'lut' not in out  # run at one step only


@pytest.fixture(scope='module')
def dga():
    return load_surrogate('dga')


def test_with_noise_reports_each_seed_and_the_standard_error(dga):
    p = default_params()
    assert p.noise_std_a > 0
    r = with_noise(p, 'step_0p1', {'dga': dga}, seeds=3)
    assert r['seeds'] == 3
    for e in (r['hf_seed_to_seed'], r['hf_cd_plus_0.1%_same_seed'], r['models']['dga']):
        for q in ('jack', 'p12'):
            v = np.array(e[f'{q}_per_seed'])
            assert v.size == 3 and np.all(np.isfinite(v))
            assert e[q] == pytest.approx(v.mean(), rel=1e-12)
            assert e[f'{q}_sem'] == pytest.approx(v.std(ddof=1) / math.sqrt(3), rel=1e-12)
    # another seed is another trajectory: the spread is not zero
    assert r['hf_seed_to_seed']['jack'] > 0 and r['hf_seed_to_seed']['p12'] > 0
    m = r['models']['dga']
    assert m['meets'] == (m['jack'] <= 1.5 * r['hf_seed_to_seed']['jack']
                          and m['p12'] <= 1.5 * r['hf_seed_to_seed']['p12'])


def test_noise_free_runs_hf_and_the_dynamic_surrogates_at_the_larger_steps(dga):
    p = replace(default_params(), noise_std_a=0.0)
    r = noise_free(p, 'step_0p1', {'dga': dga, 'lut': load_surrogate('lut')},
                   large_dts=(2e-6,))
    assert set(r['models']) == {'hf@dt=2e-06', 'dga', 'dga@dt=2e-06', 'lut'}
    # hf at twice the step stays within the bounds on a 0.1 mm step (the noise-free loop is
    # well conditioned there: the yardstick is under 0.5 %)
    assert r['models']['hf@dt=2e-06']['meets']
    assert r['models']['hf@dt=2e-06']['jack'] > 0  # a different run, not hf itself


@pytest.mark.parametrize('scenario,wear', [('step_0p3mm', 'worn_b'), ('step_0p01', 'rand_1')])
def test_dynamic_surrogates_meet_the_bounds_on_widened_cases(scenario, wear):
    """Two of bench/inloop.py's widened cases, noise off, each a failure of an earlier build:
    a 0.3 mm step on an underlapped valve of small clearance (dga's GA-only coefficients: P12
    1.12 against a bound of 0.15) and a 0.01 mm step on an underlapped valve of large
    clearance (dlut with 8 clearance nodes: jack 0.059 against 0.021).  Every dynamic surrogate
    within the bounds the evaluation computes from hf's own yardstick."""
    lap, clr = WEAR_POINTS[wear]
    p = replace(default_params(), noise_std_a=0.0, overlap_supply_m=lap, overlap_return_m=lap,
                radial_clearance_m=clr)
    models = {m: load_surrogate(m, p) for m in ('dlut', 'dnn', 'dga')}
    case = noise_free(p, scenario, models)
    for m in models:
        got = case['models'][m]
        assert got['meets'], (m, got['jack'], got['p12'], case['bound'])


def test_the_converged_reference_judges_every_run_and_checks_itself(dga):
    """With ``converged_dt`` every run (hf at 1 us too) is compared with hf at that step under
    the case's bounds, and the reference with hf at twice its step; the summary counts the
    cases in the rows the step ladder reads."""
    p = replace(default_params(), noise_std_a=0.0)
    r = noise_free(p, 'step_0p01', {'dga': dga}, large_dts=(5e-6,), split_dts=(1e-5,),
                   converged_dt=2.5e-7, keep_runs=True)
    conv = run(p, 'step_0p01', dt=2.5e-7)
    check = run(p, 'step_0p01', dt=5e-7)
    b = r['bound']
    c = r['converged']
    assert c['dt_s'] == 2.5e-7
    assert c['check']['jack'] == relative_error(check['jack_position_m'], conv['jack_position_m'])
    assert c['settled'] == (c['check']['jack'] <= SETTLED_FRACTION * b['jack']
                            and c['check']['p12'] <= SETTLED_FRACTION * b['p12'])
    for key, res in [('hf', c['hf'])] + [(k, m['converged']) for k, m in r['models'].items()]:
        run_ = r['runs'][key]
        assert res['jack'] == relative_error(run_['jack_position_m'], conv['jack_position_m'])
        assert res['p12'] == relative_error(run_['p12_pa'], conv['p12_pa'])
        assert res['meets'] == (res['jack'] <= b['jack'] and res['p12'] <= b['p12'])
    assert 0 < c['hf']['jack'] < b['jack']  # another step, another run; within the bounds here
    s = converged_summary({'noise_free': {'step_0p01/nominal': r}})
    assert set(s) == {'hf', 'hf@dt=5e-06', 'hf@split@dt=1e-05', 'dga', 'dga@dt=5e-06',
                      'dga@split@dt=1e-05'}
    assert s['hf']['median_cost_vs_hf'] == 1.0
    for key, row in s.items():
        res = c['hf'] if key == 'hf' else r['models'][key]['converged']
        assert row['cases'] == 1 and row['cases_meeting_bounds'] == int(res['meets'])
    assert converged_summary({'noise_free': {'x': {k: v for k, v in r.items()
                                                   if k != 'converged'}}}) is None


def test_the_converged_summary_lists_failures_and_unsettled_references():
    def case(settled, hf_meets, m_meets):
        res = {'jack': 0.5, 'p12': 0.5}
        return {'bound': {'jack': 1.0, 'p12': 1.0}, 'hf_cost_s_per_s': 2.0,
                'converged': {'settled': settled, 'hf': {**res, 'meets': hf_meets}},
                'models': {'m@split@dt=1e-05': {'cost_s_per_s': 0.5,
                                                'converged': {**res, 'meets': m_meets}},
                           'm@split@dt=2e-05': {'error': 'SimulationDiverged: boom'}}}
    s = converged_summary({'noise_free': {'a': case(True, False, True),
                                          'b': case(False, True, False)}})
    assert s['hf']['cases_failing'] == ['a'] and s['hf']['cases_unsettled'] == ['b']
    assert s['m@split@dt=1e-05']['cases_failing'] == ['b']
    assert s['m@split@dt=1e-05']['median_cost_vs_hf'] == 0.25
    # a run that failed is a failed case, never a missing one
    assert s['m@split@dt=2e-05']['cases_failing'] == ['a', 'b']
    assert s['m@split@dt=2e-05']['cases'] == 2
    steps = largest_steps(s)
    assert steps['m@split']['largest_step_s'] is None
    assert steps['hf']['largest_step_s'] is None  # hf at 1 us itself misses case a


def test_the_sweep_gives_the_converged_comparison_the_evaluation_gives(tmp_path):
    """Through the sweep (``converged_dt`` in the spec, one row per case, read back): the same
    errors, verdicts and check as :func:`noise_free` computes in one process."""
    from eha_ros.sweep.comparison import run_comparison
    p = replace(default_params(), noise_std_a=0.0)
    direct = noise_free(p, 'step_0p01', {}, split_dts=(1e-5,), converged_dt=2.5e-7)
    done = run_comparison(tmp_path / 'cmp', ['step_0p01'], {'nominal': None}, ['dga'],
                          split_dts=(1e-5,), converged_dt=2.5e-7, in_process=True,
                          progress=False)
    swept = done['noise_free']['step_0p01/nominal']
    assert swept['converged'] == {k: direct['converged'][k] for k in ('hf', 'settled', 'check')}
    got = swept['models']['hf@split@dt=1e-05']['converged']
    assert got == direct['models']['hf@split@dt=1e-05']['converged']
    assert swept['models']['dga']['converged']['jack'] > 0
