"""The settled valve test and its fit at measured conditions (eha_ros.health.valve_fit):
the conditions reach the estimate, a test the valve model does not explain is refused with its
reason, unmeasured conditions are said and widen the deviations, and the stated deviations
cover the truth on a small drifted set."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from eha_ros.graph import LEVEL_CANNOT_ASSESS
from eha_ros.health.monitor import MonitorCore
from eha_ros.health.thresholds import HealthThresholds
from eha_ros.health.valve_fit import ValveFitEstimator
from eha_ros.physics import default_params
from eha_ros.physics.bench import (Conditions, ConditionSensors, load_bench, mean_conditions,
                                   measure_conditions, true_conditions)
from eha_ros.physics.params import fluid_law as load_fluid
from eha_ros.physics.maintenance import ValveTest, valve_test_schedule
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, steady_map, stepped_trace
from eha_ros.physics.params import replace

P = replace(default_params(), noise_std_a=0.0)
VALVE = replace(P, radial_clearance_m=3.3e-6, overlap_supply_m=1.7e-6,
                overlap_return_m=1.7e-6)


def curves_of(params):
    s = valve_test_schedule('settled')
    xs = spool_grid(s['n_points'], params.spool_stroke_m)
    n = int(round(s['hold_s'] / 1e-3))
    out = []
    for q in s['flows_m3_s']:
        p1, p2 = stepped_trace(xs, q, n, 1000, params, first=n - 1)
        out.append((q, xs, p1[-1] - p2[-1]))
    return out


@pytest.fixture(scope='module')
def est():
    return ValveFitEstimator(P)


def test_fluid_law_gives_the_nominal_fluid_at_its_reference_temperature():
    """The nominal fluid is the datasheet's at 40 degC, exactly; Walther's law is thinner hot,
    5 cSt at 100 degC by construction; the density follows the temperature; the condition
    factor scales the viscosity alone; the plant's true temperature is its parameter."""
    assert P.fluid_kinematic_viscosity_m2_s == 1.4e-5 and P.fluid_density_kg_m3 == 850.0
    hot = replace(P, fluid_temperature_k=373.15)
    assert hot.fluid_kinematic_viscosity_m2_s == pytest.approx(5e-6, rel=1e-9)
    assert hot.fluid_density_kg_m3 == pytest.approx(850.0 / (1 + 8.5e-4 * 60.0), rel=1e-12)
    sheared = replace(hot, fluid_condition_factor=0.85)
    assert sheared.fluid_kinematic_viscosity_m2_s == pytest.approx(0.85 * 5e-6, rel=1e-9)
    assert sheared.fluid_density_kg_m3 == hot.fluid_density_kg_m3
    assert true_conditions(sheared).fluid_temperature_k == 373.15


def test_condition_sensors_read_one_tick_at_a_time_as_measure_conditions():
    s = ConditionSensors(7)
    rows = np.array([s.read(VALVE)[0] for _ in range(5)])
    np.testing.assert_array_equal(rows, measure_conditions(VALVE, 7, 5))
    # the calibration error is within the sensors' bias, and fixed for the test
    b = load_bench()
    err = measure_conditions(VALVE, 7, 2000).mean(axis=0) - true_conditions(VALVE).array()
    assert np.all(np.abs(err) <= [b.sensors[k].bias + 3 * b.sensors[k].resolution for k in (
        'supply_pressure_pa', 'return_pressure_pa', 'fluid_temperature_k')])


def test_settled_samples_are_the_stepped_curve_and_settle():
    """The plant's samples of a settled test are the stepped curve's
    (:func:`stepped_trace`) bit for bit, whether the plant runs the points in order or enters
    the test midway; every point ends within 2 kPa + 0.1 % of the steady map (the tightest
    valve of the wear range, with a leaky piston: the case that took seconds from zero)."""
    vt = ValveTest.of('settled', 1_000_000, 1e-6)
    assert vt.duration_s == pytest.approx(16.4)
    tight = replace(VALVE, radial_clearance_m=WEAR_RANGES['radial_clearance_m'][0],
                    leakage_coeff_m3_s_pa=10 * VALVE.leakage_coeff_m3_s_pa,
                    critical_flow_number=1000.0)
    grid = vt.grid(tight)
    curve = 1   # the second flow
    p1, p2 = stepped_trace(grid, vt.flows_m3_s[curve], vt.ticks_per_point, 1000, tight)
    base = curve * vt.n_points * vt.ticks_per_point
    for j in (0, 17, 20, 23):
        for m in (0, vt.ticks_per_point - 1):
            s = vt.sample(base + j * vt.ticks_per_point + m + 1, tight)
            assert (s.point, s.curve, s.point_end) == (j, curve, m == vt.ticks_per_point - 1)
            assert (s.p1_pa, s.p2_pa) == (p1[m, j], p2[m, j])
    fresh = ValveTest.of('settled', 1_000_000, 1e-6)   # in order from the curve's start
    for k in range(base + 1, base + 21 * vt.ticks_per_point + 1):
        s = fresh.sample(k, tight)
    assert (s.point, s.p1_pa, s.p2_pa) == (20, p1[-1, 20], p2[-1, 20])
    for q in vt.flows_m3_s:
        a, b = stepped_trace(grid, q, vt.ticks_per_point, 1000, tight,
                             first=vt.ticks_per_point - 1)
        ss = steady_map(grid, np.full(grid.size, q), params=tight)
        band = np.abs(ss['p12_pa']) <= tight.supply_pressure_pa - tight.return_pressure_pa
        err = np.abs(a[-1] - b[-1] - ss['p12_pa'])[band]
        assert np.all(err <= 2e3 + 1e-3 * np.abs(ss['p12_pa'][band])), err.max()


def test_measured_conditions_reach_the_estimate(est):
    """A valve at supply 2 % high and 60 degC: fitted at the measured conditions it reads its
    wear within its deviation; told nominal conditions instead it reads otherwise."""
    truth = replace(VALVE, supply_pressure_pa=P.supply_pressure_pa * 1.02,
                    fluid_temperature_k=333.15)
    curves = curves_of(truth)
    measured = mean_conditions(measure_conditions(truth, 3, 1000))
    e = est.estimate(curves, measured)
    assert not e.mismatch
    assert e.conditions['supply_pressure_pa'] == measured.supply_pressure_pa
    assert abs(e.radial_clearance_m - 3.3e-6) <= 2 * e.radial_clearance_std_m
    assert abs(e.overlap_m - 1.7e-6) <= 2 * e.overlap_std_m
    wrong = est.estimate(curves, true_conditions(P))
    assert (wrong.radial_clearance_m, wrong.overlap_m) != (e.radial_clearance_m, e.overlap_m)


def test_a_test_the_model_does_not_explain_cannot_be_assessed(est):
    """Supply 15 % above what the bench measured: chi beyond its calibrated limit, the
    estimate refuses with the residual and the limit, its deviations widened to the range."""
    truth = replace(VALVE, supply_pressure_pa=P.supply_pressure_pa * 1.15)
    e = est.estimate(curves_of(truth), true_conditions(P))
    assert 'does not explain this test' in e.mismatch and 'limit' in e.mismatch
    assert e.radial_clearance_std_m >= 5e-6 / np.sqrt(12) - 1e-15
    # and outside the service range, measured as such
    e = est.estimate(curves_of(truth), true_conditions(truth))
    assert 'outside the service range' in e.mismatch


def test_unmeasured_conditions_are_said_and_widen_the_deviation(est):
    curves = curves_of(VALVE)
    measured = est.estimate(curves, true_conditions(VALVE))
    assumed = est.estimate(curves, None)
    assert 'nominal assumed' in assumed.note and assumed.conditions['assumed']
    assert assumed.radial_clearance_std_m > measured.radial_clearance_std_m
    assert assumed.overlap_std_m > measured.overlap_std_m


def test_monitor_routes_the_settled_test_and_flags_a_recording_without_conditions():
    """States of a settled valve test (point ends only) through MonitorCore: with the
    readings the report lists the measured conditions; without them (NaN, as eha-diagnose
    fills an old recording) it says nominal was assumed; with conditions beyond the service
    range every wear item is CANNOT_ASSESS with the reason."""
    lim = HealthThresholds.load()
    s = valve_test_schedule('settled')

    def run(reading):
        core = MonitorCore(P, lim, valve_test=None, faults=None)
        reports = []
        t = 0
        for q, xs, p12 in curves_of(VALVE):
            for k, (x, p) in enumerate(zip(xs, p12)):
                t += 1
                st = SimpleNamespace(status=4, valve_test_point=k, valve_test_point_end=True,
                                     valve_test_procedure=1, load_flow_m3_s=q,
                                     spool_position_m=x, p12_pa=p, sim_time_s=t * 0.1,
                                     supply_pressure_measured_pa=reading[0],
                                     return_pressure_measured_pa=reading[1],
                                     fluid_temperature_measured_k=reading[2])
                reports += [j.run() for j in core.on_state(t, st)]
        assert len(reports) == len(s['flows_m3_s'])
        return reports[-1], core
    r, core = run(true_conditions(VALVE).array())
    assert r.method == 'settled-valve-fit' and not r.conditions['assumed']
    assert 'valve_degradation' in core.items and 'leakage_coeff_m3_s_pa' in core.items
    r, _ = run([np.nan] * 3)
    assert r.conditions['assumed'] and 'nominal assumed' in r.message
    r, core = run([P.supply_pressure_pa * 1.15, P.return_pressure_pa, 313.15])
    assert r.level == LEVEL_CANNOT_ASSESS
    assert core.items['radial_clearance_m'].level == LEVEL_CANNOT_ASSESS
    assert 'outside the service range' in core.items['radial_clearance_m'].message


def test_deviations_cover_the_truth_on_a_drifted_set(est):
    """10 valves from a stream used neither for calibration (31) nor the benchmark (201-204),
    drift within the envelope.  The calibration puts 95 % within 2 sigma; over 20 items the
    binomial standard error is sqrt(0.95 * 0.05 / 20) = 0.049, so at least 0.95 - 2 x 0.049
    = 0.85 (17 of 20) must be covered.  No valve may be refused inside the envelope."""
    from eha_ros.training.valve_fit import drifted_cases
    covered, n = 0, 0
    for c in drifted_cases(10, 301):
        seed = c.pop('seed')
        truth = replace(P, **c)
        cond = mean_conditions(measure_conditions(truth, seed, 1000))
        e = est.estimate(curves_of(truth), cond)
        assert not e.mismatch, e.mismatch
        covered += abs(e.radial_clearance_m - truth.radial_clearance_m) <= (
            2 * e.radial_clearance_std_m)
        covered += abs(e.overlap_m - truth.overlap_supply_m) <= 2 * e.overlap_std_m
        n += 2
    assert covered >= 17, f'{covered} of {n} within 2 sigma'


def test_conditions_dataclass_round_trip():
    c = Conditions(2.0e7, 6e5, 313.15)
    assert dataclasses.replace(c, assumed=True).as_dict()['assumed'] is True


def test_graph_maintenance_test_gives_the_benchs_estimate_and_lists_its_conditions(
        eha_graph, tmp_path):
    """The settled maintenance test (two flows) through the graph (lockstep, health monitor,
    recorder): the live monitor's valve-test estimate equals the sweep procedure's - the
    benchmark's -
    for the same valve and seed bit for bit (same transients, same sensor readings), and
    eha-diagnose --json replays it and lists the measured conditions each test used."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from eha_ros.physics import params_to_dict
    from eha_ros.sweep import parse_spec, read_dataset, run_sweep
    wear = {'radial_clearance_m': 3.3e-6, 'overlap_supply_m': 1.7e-6,
            'overlap_return_m': 1.7e-6, 'valve_degradation': 0.05,
            'leakage_coeff_m3_s_pa': 3e-13}
    path = tmp_path / 'maintenance.mcap'
    r = eha_graph(processes=False, scenario='maintenance_test_settled_quick', plant=wear,
                  health=True, record=str(path))
    live = [m for m in r.health if m.method == 'settled-valve-fit']
    assert len(live) == 2   # one estimate per completed curve
    spec = parse_spec({'procedure': 'valve_test', 'valve_test_procedure': 'settled',
                       'flows_m3_s': [0.0, 6e-5], 'cases': [dict(wear, seed=0)]},
                      source='test',
                      base=params_to_dict(default_params()))
    run_sweep(spec, tmp_path / 'sweep', in_process=True)
    row = read_dataset(tmp_path / 'sweep').to_pylist()[0]
    assert row['status'] == 'ok', row['error']
    assert live[-1].radial_clearance_m == row['est_radial_clearance_m']
    assert live[-1].overlap_m == row['est_overlap_m']
    assert live[-1].radial_clearance_std_m == row['est_radial_clearance_std_m']
    out = subprocess.run([str(Path(sys.executable).parent / 'eha-diagnose'), str(path),
                          '--json'], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert d['live_agrees'] is True
    vt = d['conditions_by_test']['valve-test']
    assert not vt['assumed']
    assert vt['supply_pressure_pa'] == row['measured_supply_pressure_pa']
    assert abs(vt['supply_pressure_pa'] - P.supply_pressure_pa) <= 6e4   # the sensor's bias
    k = d['estimates']['valve_degradation']
    assert abs(k['value'] - 0.05) <= 2 * k['std']
    assert set(d['conditions_by_test']) == {'valve-test', 'preflight'}
    e = d['estimates']['radial_clearance_m']
    assert e['value'] == row['est_radial_clearance_m'] and e['method'] == 'settled-valve-fit'


def test_bench_fluid_law_is_the_datasheets_whatever_the_parameters():
    """One fluid law, anchored at the datasheet: a run's parameters never re-anchor it; a
    sheared fluid at 70 degC has the viscosity of its condition, and the bench's sensor reads
    its temperature, not the temperature the datasheet would give that viscosity."""
    b = load_bench()
    law = load_fluid()
    assert b.fluid is law and load_bench() is b   # one law, loaded once
    assert law.viscosity_m2_s(313.15) == 1.4e-5
    assert law.viscosity_m2_s(373.15) == pytest.approx(5.0e-6, rel=1e-12)
    assert law.temperature_k(law.viscosity_m2_s(343.15)) == pytest.approx(343.15, abs=1e-9)
    sheared = replace(default_params(), fluid_temperature_k=343.15, fluid_condition_factor=0.85)
    assert law.temperature_k(sheared.fluid_kinematic_viscosity_m2_s) > 345.0
    s = b.sensors['fluid_temperature_k']
    readings = ConditionSensors(7, b).read(sheared, 200)[:, 2]
    assert abs(readings.mean() - 343.15) <= s.bias + 4 * s.noise_std / np.sqrt(200) + s.resolution


def test_graph_with_a_hot_fluid_params_file_measures_its_temperature_and_agrees_with_the_sweep(
        eha_graph, tmp_path):
    """The maintenance test through the graph with a plant params file whose fluid is at 60 degC
    (its fluid_temperature_k; the monitor keeps its nominal model): the
    plant's sensor reads 60 degC, not the reference 40 degC, and the live estimate equals the
    sweep's for the same fluid, valve and seed bit for bit."""
    import yaml

    from eha_ros.physics import params_to_dict
    from eha_ros.physics.params import config_dir
    from eha_ros.sweep import parse_spec, read_dataset, run_sweep
    t_hot = 333.15
    fluid = {'fluid_temperature_k': t_hot}
    doc = yaml.safe_load((config_dir() / 'eha_params.yaml').read_text())
    doc['fluid_temperature_k']['value'] = t_hot
    params_file = tmp_path / 'hot_fluid.yaml'
    params_file.write_text(yaml.safe_dump(doc))
    wear = {'radial_clearance_m': 2.1e-6, 'overlap_supply_m': 0.6e-6, 'overlap_return_m': 0.6e-6}
    r = eha_graph(processes=False, scenario='maintenance_test_settled_quick', plant=wear,
                  health=True,
                  node_params={'servovalve_plant': {'params_file': str(params_file)}})
    s = load_bench().sensors['fluid_temperature_k']
    measured = r.state['fluid_temperature_measured_k']
    assert abs(float(np.mean(measured)) - t_hot) <= s.bias + s.resolution
    live = [m for m in r.health if m.method == 'settled-valve-fit']
    assert len(live) == 2
    spec = parse_spec({'procedure': 'valve_test', 'valve_test_procedure': 'settled',
                       'flows_m3_s': [0.0, 6e-5], 'cases': [dict(wear, **fluid, seed=0)]},
                      source='test', base=params_to_dict(default_params()))
    run_sweep(spec, tmp_path / 'sweep', in_process=True)
    row = read_dataset(tmp_path / 'sweep').to_pylist()[0]
    assert row['status'] == 'ok', row['error']
    assert abs(row['measured_fluid_temperature_k'] - t_hot) <= s.bias + s.resolution
    assert live[-1].radial_clearance_m == row['est_radial_clearance_m']
    assert live[-1].overlap_m == row['est_overlap_m']
    assert abs(live[-1].radial_clearance_m - wear['radial_clearance_m']) <= (
        2 * live[-1].radial_clearance_std_m)


def test_unit_priors_follow_the_tolerances():
    """The valve fit's priors from config/tolerances.yaml: the laminar factor (fluid condition
    0.85-1.05 over the port width's and the eccentricity's leakage gain, e up to 0.5) lies
    below 1 on average; the edges' Cd w over nominal is about Cd's mid-range over 0.61 (0.62 /
    0.61) with the spread of a uniform range of +-6.6 % (about 3.8 %)."""
    from eha_ros.health.valve_fit import unit_priors
    pr = unit_priors()
    lam_mean, lam_std = pr['laminar']
    assert -0.1 < lam_mean < -0.04 and 0.03 < lam_std < 0.07
    edge_mean, edge_std = pr['edge']
    assert edge_mean == pytest.approx(0.62 / 0.61, rel=3e-3)
    assert edge_std == pytest.approx(0.08 / 0.61 / np.sqrt(12), rel=0.05)
