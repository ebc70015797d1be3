"""The pre-flight fault network under drift (:mod:`eha_ros.health.preflight`): the measured
conditions reach it, it refuses what it was not built for, its deviations hold on a drifted
held-out set, and its artefact records what it was built over."""

import math

import numpy as np
import pytest

from eha_ros.health.preflight import (CONDITION_READINGS, FAULT_NAMES, FAULTS, FaultEstimate,
                                      load_faults)
from eha_ros.physics import default_params
from eha_ros.physics.bench import (Conditions, load_bench, mean_conditions,
                                   measure_conditions)
from eha_ros.physics.maintenance import run_preflight
from eha_ros.physics.params import replace
from eha_ros.physics.tolerances import load_tolerances
from eha_ros.training.preflight import case_params, cases

P = default_params()
#: Streams no build or benchmark set uses (those: 21-24 and 41-45).
STREAM_TEST, STREAM_FLEET_TEST, STREAM_BEYOND_TEST = 51, 52, 53


@pytest.fixture(scope='module')
def model():
    return load_faults()


@pytest.fixture(scope='module')
def nominal_check():
    """A nominal valve's check and the conditions the bench measured for it."""
    seed = 7
    return run_preflight(P, seed=seed), mean_conditions(measure_conditions(
        P, seed, CONDITION_READINGS))


def _prior_std(f):
    return f.span / math.sqrt(12.0)


def test_measured_conditions_reach_the_estimator(model, nominal_check):
    """The same record read at other measured conditions (still in service) gives other
    estimates; conditions outside the service envelope set ``mismatch`` and widen every
    deviation to at least the uniform prior's."""
    rec, cond = nominal_check
    e = model.estimate(rec, cond)
    assert isinstance(e, FaultEstimate) and set(e.values) == set(FAULT_NAMES)
    assert e.mismatch == '' and e.note == '' and e.ood_score <= e.ood_limit
    lo, hi = load_bench().service['supply_pressure_pa']
    moved = model.estimate(rec, Conditions(hi, cond.return_pressure_pa,
                                           cond.fluid_temperature_k))
    assert max(abs(moved.values[n] - e.values[n]) / f.span
               for n, f in zip(FAULT_NAMES, FAULTS)) > 1e-3
    out = model.estimate(rec, Conditions(2.4e7, cond.return_pressure_pa,
                                         cond.fluid_temperature_k))
    assert 'supply_pressure_pa' in out.mismatch and 'service range' in out.mismatch
    for f in FAULTS:
        assert out.stds[f.name] >= _prior_std(f) * (1 - 1e-12)


def test_assumed_conditions_widen_the_deviations(model, nominal_check):
    """Conditions not measured (nominal assumed): a ``note`` says so, and no deviation is
    narrower than with the measured conditions."""
    rec, cond = nominal_check
    e = model.estimate(rec, cond)
    nominal = Conditions(P.supply_pressure_pa, P.return_pressure_pa,
                         cond.fluid_temperature_k, assumed=True)
    a = model.estimate(rec, nominal)
    assert a.note and 'not measured' in a.note
    for n in FAULT_NAMES:
        assert a.stds[n] >= e.stds[n]


def test_a_halved_bulk_modulus_is_refused(model):
    """Fluid with half the nominal bulk modulus (beyond the bench's drift envelope, and not
    measured): the OOD test flags the check as a mismatch and every deviation is widened."""
    p = replace(P, bulk_modulus_pa=0.5 * P.bulk_modulus_pa)
    seed = 11
    e = model.estimate(run_preflight(p, seed=seed),
                       mean_conditions(measure_conditions(p, seed, CONDITION_READINGS)))
    assert 'OOD score' in e.mismatch and e.ood_score > e.ood_limit
    for f in FAULTS:
        assert e.stds[f.name] >= _prior_std(f) * (1 - 1e-12)


def test_halved_bulk_moduli_are_refused_on_fresh_draws(model):
    """12 drifted cases of a stream used for nothing else, each with half the nominal bulk
    modulus: at least 10 are refused (the goal of 0.95 less two binomial standard errors of a
    12-case fraction, 0.82), and a case left unrefused holds every truth within 2 sigma."""
    refused = 0
    for wear, seed in cases(12, STREAM_BEYOND_TEST, inner=True):
        p = replace(case_params((wear, seed)), bulk_modulus_pa=0.5 * P.bulk_modulus_pa)
        e = model.estimate(run_preflight(p, seed=seed), mean_conditions(
            measure_conditions(p, seed, CONDITION_READINGS)))
        refused += bool(e.mismatch)
        if not e.mismatch:
            for k in FAULT_NAMES:
                assert abs(e.values[k] - wear[k]) <= 2 * e.stds[k], (seed, k)
    assert refused >= 10, refused


def test_the_ood_network_runs_as_it_was_trained(model):
    """The envelope network is in the artefact, and its numpy activation is torch's SiLU."""
    import torch
    from eha_ros.mlp import silu
    net = model.meta['ood']['net']
    assert net['activation'] == 'silu' and model.ood.net is not None
    assert [w.shape[1] for w, _ in model.ood.net.weights[:-1]] == net['hidden']
    z = np.linspace(-60.0, 60.0, 2001)
    np.testing.assert_allclose(silu(z), torch.nn.functional.silu(
        torch.as_tensor(z, dtype=torch.float64)).numpy(), rtol=1e-12, atol=1e-15)
    assert np.all(np.isfinite(model.ood.net.score(np.full((1, model.in_mean.size), 1e3))))


@pytest.mark.parametrize('fleet', [False, True], ids=['drift', 'fleet'])
def test_deviations_hold_on_a_drifted_held_out_set(model, fleet):
    """40 drifted cases of a stream used by no build step (faults as for training, every
    nuisance of the test bench and condition drawn; ``fleet``: and every nuisance of the
    tolerances, on another stream): per fault, the fraction within 2 sigma is at least
    0.9 - 2 sqrt(0.9 x 0.1 / 40) = 0.805 (the goal of 0.9 less two binomial standard errors of
    a 40-case fraction), and no more than 2 cases are flagged as mismatch."""
    n = 40
    est, std, truth, flagged = [], [], [], 0
    for case in cases(n, STREAM_FLEET_TEST if fleet else STREAM_TEST, fleet=fleet):
        p = case_params(case)
        e = model.estimate(run_preflight(p, seed=case[1]), mean_conditions(
            measure_conditions(p, case[1], CONDITION_READINGS)))
        flagged += bool(e.mismatch)
        est.append([e.values[k] for k in FAULT_NAMES])
        std.append([e.stds[k] for k in FAULT_NAMES])
        truth.append([case[0][k] for k in FAULT_NAMES])
    within = np.mean(np.abs(np.array(est) - truth) <= 2 * np.array(std), axis=0)
    floor = 0.9 - 2 * math.sqrt(0.9 * 0.1 / n)
    assert np.all(within >= floor), dict(zip(FAULT_NAMES, within))
    assert flagged <= 2


def test_the_artefact_records_what_it_was_built_over(model):
    """Sizes, separate streams, the nuisance ranges (those of ``config/test_bench.yaml``), the
    service envelope, calibration factors of at least 1 and a finite OOD limit."""
    m = model.meta
    b = load_bench()
    assert m['outputs'] == list(FAULT_NAMES)
    assert m['sizes']['train'] >= 2400 and min(m['sizes'].values()) >= 200
    assert len(set(m['streams'].values())) == len(m['streams']) == 4
    for name in b.nuisance:
        assert m['nuisance'][name] == pytest.approx(list(b.nuisance_range(name)))
    assert set(m['valve_nuisance']) == {'radial_clearance_m', 'overlap_supply_m'}
    # built over a fleet: every nuisance of the tolerances, the dynamic frictions as ratios
    tol = load_tolerances()
    assert set(m['fleet']) == {n for n, t in tol.items() if t.klass == 'nuisance'}
    assert m['friction_ratio'] == {n: [t.lo, t.hi] for n, t in tol.items() if t.ratio_of}
    assert set(m['ood']['parameters']) >= set(m['fleet']) - set(m['friction_ratio'])
    for name, rng in b.service.items():
        assert m['service'][name] == pytest.approx(list(rng))
    assert all(v >= 1.0 for v in m['calibration'].values())
    assert 0 < m['ood']['limit'] == model.ood.limit < math.inf
    assert set(m['held_out']) == {'val', 'cal', 'ood'}


def test_bad_input_is_refused_in_one_line(model, nominal_check):
    rec, cond = nominal_check
    with pytest.raises(TypeError, match='Conditions'):
        model.estimate(rec, None)
    short = {k: v[:100] for k, v in rec.items()}
    with pytest.raises(ValueError, match='samples'):
        model.estimate(short, cond)
    with pytest.raises(ValueError, match='no p12_pa'):
        model.estimate({k: v for k, v in rec.items() if k != 'p12_pa'}, cond)
    with pytest.raises(ValueError, match='not finite'):
        model.estimate(rec, Conditions(math.nan, 6e5, 313.0))


def test_the_sweep_procedure_reports_the_network_and_its_checks():
    """The ``preflight_check`` procedure's metrics follow the five faults and add the OOD
    score and the mismatch flag."""
    from eha_ros.health.procedures import PreflightProcedure
    names = dict(PreflightProcedure.metrics())
    assert {f'est_{n}' for n in FAULT_NAMES} <= set(names)
    assert names['ood_score'] == 'float' and names['mismatch'] == 'bool'
    assert not any('clearance' in n or 'overlap' in n for n in names)
