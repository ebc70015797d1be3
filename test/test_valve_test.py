"""The diagnostic valve test: the plant's tick schedule reproduces the reference's map
procedure bit for bit, the diagnostic network reads the wear from its curves, and the node
graph runs it end to end (plant -> health monitor)."""

import numpy as np
from numpy.testing import assert_array_equal
import pytest

from eha_ros.physics import ParameterError, Plant, default_params, get_scenario
from eha_ros.physics.maps import spool_grid, transient_map
from eha_ros.physics.params import replace
from eha_ros.physics.valve_test import MAP_HOLD_S, MAP_POINTS, ValveTest

P = default_params()
Q = 4.285714285714286e-05  # a flow of the diagnostic network's grid


def _worn(clearance, overlap):
    return replace(P, radial_clearance_m=clearance, overlap_supply_m=overlap,
                   overlap_return_m=overlap)


def test_schedule_and_point_ends_are_the_map():
    """Two flows at 1 kHz: 10 ticks per point, spool positions in grid order for each flow,
    the pressure rising from zero within a hold, and the sample ending each hold equal to
    transient_map's value (same kernel, same step: exact)."""
    p = _worn(4.5e-6, -0.5e-6)
    vt = ValveTest([Q, -Q], 1_000_000, 1e-6)
    assert vt.ticks_per_point == 10 and vt.n_ticks == 2 * MAP_POINTS * 10
    assert vt.duration_s == pytest.approx(2 * MAP_POINTS * MAP_HOLD_S)
    samples = [vt.sample(k, p) for k in range(1, vt.n_ticks + 1)]
    ends = [s for s in samples if s.point_end]
    assert len(ends) == 2 * MAP_POINTS
    xs = spool_grid(MAP_POINTS, p.spool_stroke_m)
    for curve, q in enumerate((Q, -Q)):
        mine = ends[curve * MAP_POINTS:(curve + 1) * MAP_POINTS]
        assert [s.point for s in mine] == list(range(MAP_POINTS))
        assert all(s.curve == curve and s.load_flow_m3_s == q for s in mine)
        assert_array_equal([s.spool_position_m for s in mine], xs)
        ref = transient_map(xs, q, params=p)
        assert_array_equal([s.p1_pa for s in mine], ref['p1_pa'])
        assert_array_equal([s.p2_pa for s in mine], ref['p2_pa'])
    # within the hold of an open point the transient moves (from zero pressures)
    first = samples[:10]
    assert first[0].p2_pa != first[-1].p2_pa and all(s.point == 0 for s in first)


@pytest.mark.parametrize('flows, tick_ns, words', [
    ([], 1_000_000, 'at least one flow'),
    ([Q, float('nan')], 1_000_000, 'finite'),
    ([Q], 3_000_000, 'whole number of ticks'),
])
def test_bad_valve_test_is_refused(flows, tick_ns, words):
    with pytest.raises(ParameterError, match=words):
        ValveTest(flows, tick_ns, 1e-6)


def test_plant_hold_moves_the_clock_only():
    plant = Plant(P)
    plant.advance(0.01, 100)
    state = plant.state.copy()
    plant.hold(1000)
    assert plant.steps == 1100 and plant.time_ns == 1_100_000
    assert_array_equal(plant.state, state)


def test_scenarios_carry_the_valve_test():
    sc = get_scenario('valve_test')
    assert sc.valve_test and len(sc.valve_test_flows_m3_s) == 3
    assert sc.duration_s == pytest.approx(3 * MAP_POINTS * MAP_HOLD_S)
    assert not get_scenario('step_0p1').valve_test


@pytest.mark.parametrize('clearance, overlap', [(2.5e-6, 1e-6), (4.5e-6, -0.5e-6),
                                                (1.7e-6, 3.3e-6)])
def test_network_reads_wear_from_valve_test_curves(clearance, overlap):
    """The estimator on the three default curves of a valve off the network's training grid:
    within 0.05 um of the truth (1 % of the clearance range), a small spread and a residual
    under 50 kPa (the map model at the estimate explains the curves)."""
    from eha_ros.surrogates.health import ValveTestEstimator
    p = _worn(clearance, overlap)
    xs = spool_grid(MAP_POINTS, p.spool_stroke_m)
    flows = get_scenario('valve_test').valve_test_flows_m3_s
    curves = [(q, xs, transient_map(xs, q, params=p)['p12_pa']) for q in flows]
    e = ValveTestEstimator(P).estimate(curves)
    assert abs(e.radial_clearance_m - clearance) < 0.05e-6
    assert abs(e.overlap_m - overlap) < 0.05e-6
    assert e.radial_clearance_std_m < 0.05e-6 and e.overlap_std_m < 0.05e-6
    assert 0 < e.pressure_residual_pa < 5e4
    assert e.samples_used == 3 * MAP_POINTS and e.method == 'diagnostic-network'
    # a curve of another valve's physics is not explained: the residual says so
    other = [(q, xs, 0.6 * p12) for q, xs, p12 in curves]
    assert ValveTestEstimator(P).estimate(other).pressure_residual_pa > 1e6


@pytest.mark.parametrize('processes', [False, True])
def test_graph_runs_the_valve_test_and_the_monitor_reads_the_wear(eha_graph, processes,
                                                                  tmp_path):
    """Lockstep, one-flow valve test on a worn valve (clearance 4.5 um, overlap -0.5 um),
    then 100 ms of operation, nodes in one process and as console scripts (the flows cross
    the command line as a double array; that run is recorded and diagnosed offline): the
    plant's states at the point ends are the map, the health
    monitor publishes the network's estimate within 0.05 um of the truth, graded WARN
    (clearance past its 4 um warning level), and the loop operates again after the test."""
    wear = {'radial_clearance_m': 4.5e-6, 'overlap_supply_m': -0.5e-6,
            'overlap_return_m': -0.5e-6}
    record = str(tmp_path / 'valve_test.mcap') if processes else ''
    r = eha_graph(processes=processes, scenario='valve_test_quick', duration_s=1.43, plant=wear,
                  health=True, record=record)
    st = r.state
    test = st['status'] == 4
    n = MAP_POINTS * 10  # ticks of the test, after the initial state (tick 0)
    assert test.sum() == n and np.all(test[1:n + 1])
    assert not test[n + 1:].any() and test.size == n + 101
    ends = test & st['valve_test_point_end']
    assert_array_equal(st['valve_test_point'][ends], np.arange(MAP_POINTS))
    p = _worn(4.5e-6, -0.5e-6)
    ref = transient_map(spool_grid(MAP_POINTS, p.spool_stroke_m), Q, params=p)
    assert_array_equal(st['p12_pa'][ends], ref['p12_pa'])
    assert np.all(st['load_flow_m3_s'][test] == Q)
    net = [h for h in r.health if h.method == 'diagnostic-network']
    assert len(net) == 1
    h = net[0]
    assert abs(h.radial_clearance_m - 4.5e-6) < 0.05e-6
    assert abs(h.overlap_m + 0.5e-6) < 0.05e-6
    assert h.level == 1 and 'clearance' in h.message and h.samples_used == MAP_POINTS
    # the jack was clamped during the test and the plant is back in operation after it
    assert np.all(st['jack_position_m'][test] == st['jack_position_m'][0])
    assert np.all(np.isin(st['status'][~test], (0, 1, 2)))
    if record:  # offline, from the recording: the same curves, the same estimate
        from eha_ros.tools.diagnose import diagnose
        d = diagnose(record)
        assert d['method'] == 'diagnostic-network' and d['samples_used'] == MAP_POINTS
        assert d['radial_clearance_m'] == h.radial_clearance_m
        assert d['overlap_m'] == h.overlap_m and d['level'] == 'WARN'
