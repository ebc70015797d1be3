"""Parameter changes during a run: text form, schedule checks, and simulate() with events equal
to the ROS graph's loop (Plant + PositionController, parameters changed between ticks)."""

import math

import numpy as np
from numpy.testing import assert_array_equal
import pytest

from eha_ros.physics import (CONTROLLER_RUNTIME, PLANT_RUNTIME, Event, EventSchedule, Plant,
                             default_params, format_event, get_scenario, parse_event, simulate)
from eha_ros.physics.params import SPEC_BY_NAME, ParameterError, replace
from eha_ros.physics.plant import PositionController

P = default_params()
PERIOD_NS = 1_000_000  # the graph's 1 kHz tick
FIELDS = ('jack_position_m', 'p12_pa', 'spool_position_m', 'current_command_a')


def _graph_loop(p, scenario, duration_s, events, seed=0, fluid=None):
    """The ROS graph's loop: at each tick, apply the due events to the plant and the
    controller, then update the controller on the sensor and advance the plant one tick."""
    plant = Plant(p, dt_s=1e-6, seed=seed, fluid=fluid)
    ctl = PositionController(p, period_s=PERIOD_NS * 1e-9)
    schedule = EventSchedule(events, period_ns=PERIOD_NS)
    sc = get_scenario(scenario)
    out = {f: [] for f in FIELDS}
    for k in range(round(duration_s * 1e9) // PERIOD_NS):
        due = schedule.due(k * PERIOD_NS)
        if due:
            q = replace(plant.params, **{n: v for ev in due for n, v in ev.changes})
            plant.set_params(q)
            ctl.params = q
        i = ctl.update(sc.value((k * PERIOD_NS) * 1e-9), plant.measured_position_m())
        snap = plant.snapshot()
        for f in FIELDS[:-1]:
            out[f].append(snap[f])
        out['current_command_a'].append(i)
        plant.advance(i, PERIOD_NS // plant.dt_ns)
    return {f: np.array(v) for f, v in out.items()}


def _assert_same(sim, loop):
    n = loop['jack_position_m'].size
    assert sim['jack_position_m'].size == n + 1  # and the final state
    for f in FIELDS:
        assert_array_equal(sim[f][:n], loop[f], err_msg=f)


def _sim(p, scenario, duration_s, events, **kw):
    return simulate(p, scenario, duration_s, controller_period_s=PERIOD_NS * 1e-9,
                    record_dt_s=None, events=events, **kw)


# --- simulate with events == the graph's loop, bit for bit ------------------------------------

@pytest.mark.parametrize('scenario, events, changed_tick', [
    ('step_0p1', [(0.1, {'overlap_supply_m': 2.7e-6})], 100),
    ('step_0p1', [(0.0504, {'jack_static_friction_n': 800.0,
                            'jack_dynamic_friction_n': 600.0})], 51),  # between ticks
    ('sine_0p1_10pi', [(0.06, {'kp_a_m': 25.0}), (0.06, {'kp_a_m': 4.0, 'ki_a_m_s': 50.0})],
     60),  # a controller change; two at the same time, the later wins
    ('step_0p1', [(0.0, {'overlap_supply_m': -1e-6, 'overlap_return_m': -1e-6})], 0),
], ids=['wear', 'between-ticks', 'gains-same-time', 'at-zero'])
def test_simulate_with_events_equals_graph_loop(scenario, events, changed_tick):
    sim = _sim(P, scenario, 0.15, events, seed=3)
    _assert_same(sim, _graph_loop(P, scenario, 0.15, events, seed=3))
    assert [e['tick'] for e in sim.events] == [changed_tick] * len(events)
    assert sim.events[0]['time_s'] == (changed_tick * PERIOD_NS) * 1e-9
    assert sim.events[-1]['changes'] == events[-1][1]
    assert sim.params == P  # the parameters the run started with
    if changed_tick:  # the run without events until the change: its tick's state, not current
        ref = _sim(P, scenario, 0.15, None, seed=3)
        for f in FIELDS:
            n = changed_tick + (f != 'current_command_a')
            assert_array_equal(sim[f][:n], ref[f][:n], err_msg=f)
            assert not np.array_equal(sim[f], ref[f]), f


def test_event_at_zero_equals_run_with_those_parameters():
    """A change at t = 0 is in effect from the first tick (the rest state is that of the
    starting parameters; these changes leave it alone)."""
    changes = {'kp_a_m': 15.0, 'jack_static_friction_n': 400.0, 'hysteresis_a': 2e-4}
    sim = _sim(P, 'step_0p1', 0.1, [(0.0, changes)], seed=1)
    ref = _sim(replace(P, **changes), 'step_0p1', 0.1, None, seed=1)
    for f in sim.data:
        assert_array_equal(sim[f], ref[f], err_msg=f)


def test_dynamic_surrogate_reprepared_at_the_event():
    from eha_ros.surrogates.registry import load_surrogate
    events = ['0.03:radial_clearance_m=3.5e-6']
    sim = _sim(P, 'step_0p1', 0.08, events, fluid=load_surrogate('dlut', P))
    _assert_same(sim, _graph_loop(P, 'step_0p1', 0.08, events, fluid=load_surrogate('dlut', P)))
    ref = _sim(P, 'step_0p1', 0.08, None, fluid=load_surrogate('dlut', P))
    assert_array_equal(sim['p12_pa'][:31], ref['p12_pa'][:31])
    assert not np.array_equal(sim['p12_pa'][31:], ref['p12_pa'][31:])


def test_recording_grid_and_noise_do_not_depend_on_segments():
    """Recording every 3rd tick at 10 kHz, with noise: the rows fall on the same ticks as
    without events, and an event that changes nothing changes no bit."""
    kw = dict(dt_s=1e-6, controller_period_s=1e-4, record_dt_s=3e-4, seed=2)
    same = [(0.0124, {'kp_a_m': P.kp_a_m}), (0.05, {'offset_a': P.offset_a})]
    a = simulate(P, 'sine_0p1_10pi', 0.0995, **kw)
    b = simulate(P, 'sine_0p1_10pi', 0.0995, events=same, **kw)
    for f in a.data:
        assert_array_equal(a[f], b[f], err_msg=f)
    assert [e['tick'] for e in b.events] == [124, 500]


def test_events_after_the_end_are_checked_but_not_applied():
    r = _sim(P, 'step_0p1', 0.05, [(0.05, {'kp_a_m': 1.0})])
    assert r.events == []
    with pytest.raises(ParameterError, match='kp_a_m'):
        _sim(P, 'step_0p1', 0.05, [(1.0, {'kp_a_m': -1.0})])


def test_unstable_change_is_refused_before_the_run():
    with pytest.raises(ParameterError, match='stability limit'):
        simulate(P, 'step_0p1', 0.01, dt_s=2e-6,
                 events=[(0.005, {'radial_clearance_m': 1e-3, 'overlap_supply_m': -1e-3,
                                  'overlap_return_m': -1e-3})])


# --- text form --------------------------------------------------------------------------------

@pytest.mark.parametrize('ev', [
    Event(0.1, (('overlap_supply_m', 2.7e-6),)),
    Event(1 / 3, (('kp_a_m', 0.1 + 0.2), ('offset_a', -1e-300), ('ki_a_m_s', 5e-324))),
    Event(0.0, {'external_force_n': 1234.5}),
])
def test_format_parse_round_trip_is_exact(ev):
    back = parse_event(format_event(ev))
    assert back == ev and hash(back) == hash(ev)
    assert [v for _, v in back.changes] == [v for _, v in ev.changes]


def test_parse_tolerates_whitespace_and_keeps_order():
    ev = parse_event(' 0.25 : kp_a_m = 20 , current_limit_a=0.008 ')
    assert ev == Event(0.25, (('kp_a_m', 20.0), ('current_limit_a', 0.008)))
    assert ev.as_dict() == {'kp_a_m': 20.0, 'current_limit_a': 0.008}
    assert list(ev.as_dict()) == ['kp_a_m', 'current_limit_a']


@pytest.mark.parametrize('text, why', [
    ('overlap_supply_m=1e-6', 'no colon'),
    ('soon:kp_a_m=1', "time 'soon' is not a number"),
    ('0.1:kp_a_m', "'kp_a_m' is not name=value"),
    ('0.1:kp_a_m=fast', "value 'fast' of kp_a_m is not a number"),
    ('0.1:', "'' is not name=value"),
    ('-0.1:kp_a_m=1', 'must be finite and not negative'),
    ('nan:kp_a_m=1', 'must be finite and not negative'),
    ('0.1:kp_a_m=nan', 'is not finite'),
    ('0.1:kp_a_m=1,kp_a_m=2', 'changed twice'),
])
def test_bad_text_is_refused_in_one_line(text, why):
    with pytest.raises(ParameterError) as exc:
        parse_event(text)
    msg = str(exc.value)
    assert '\n' not in msg and repr(text) in msg and why in msg, msg


# --- schedule ---------------------------------------------------------------------------------

def test_runtime_names_are_parameters():
    assert set(PLANT_RUNTIME + CONTROLLER_RUNTIME) <= set(SPEC_BY_NAME)
    assert not {'noise_std_a', 'noise_sample_time_s'} & set(PLANT_RUNTIME + CONTROLLER_RUNTIME)


def test_unknown_name_is_refused_with_nearest_names():
    with pytest.raises(ParameterError, match=r"event '0.1:overlap_suply_m=2e-06': unknown "
                       r'parameter overlap_suply_m; nearest allowed: overlap_supply_m'):
        EventSchedule([(0.1, {'overlap_suply_m': 2e-6})])


@pytest.mark.parametrize('name', ['supply_pressure_pa', 'noise_std_a', 'bulk_modulus_pa'])
def test_fixed_parameter_is_refused_pointing_to_the_parameter_file(name):
    with pytest.raises(ParameterError, match=f'parameter {name} is fixed for a run: set it in '
                       'the physical parameter file'):
        EventSchedule([f'0.1:{name}=1.0'])
    with pytest.raises(ParameterError, match=f'parameter {name} is fixed'):
        simulate(P, 'step_0p1', 0.01, events=[(0.005, {name: 1.0})])


def test_name_outside_this_schedules_list_is_refused():
    with pytest.raises(ParameterError, match='parameter kp_a_m may not change in this schedule'):
        EventSchedule(['0.1:kp_a_m=3'], allowed=PLANT_RUNTIME)


@pytest.mark.parametrize('t_s', [-1e-3, math.nan, math.inf])
def test_bad_time_is_refused(t_s):
    with pytest.raises(ParameterError, match='must be finite and not negative'):
        EventSchedule([(t_s, {'kp_a_m': 1.0})])


def test_bad_values_are_refused():
    with pytest.raises(ParameterError, match='value of kp_a_m = nan is not finite'):
        EventSchedule([(0.1, {'kp_a_m': math.nan})])
    with pytest.raises(ParameterError, match="value of kp_a_m = 'big' is not a number"):
        EventSchedule([(0.1, {'kp_a_m': 'big'})])
    with pytest.raises(ParameterError, match='changes no parameter'):
        EventSchedule([(0.1, {})])


def test_non_physical_value_is_refused_naming_the_event():
    s = EventSchedule([(0.2, {'overlap_supply_m': 2e-3}), (0.1, {'kp_a_m': 5.0})])
    with pytest.raises(ParameterError, match=r"event '0.2:overlap_supply_m=0.002': parameter "
                       'overlap_supply_m = 0.002 m is non-physical'):
        s.validate(P)
    # cumulative: each event alone is fine, together dynamic friction exceeds static
    s = EventSchedule([(0.1, {'jack_dynamic_friction_n': 190.0}),
                       (0.2, {'jack_static_friction_n': 150.0})])
    with pytest.raises(ParameterError, match=r"event '0.2:jack_static_friction_n=150.0': "
                       'parameter jack_dynamic_friction_n must not exceed'):
        s.validate(P)


def test_validate_returns_the_parameters_after_each_event():
    s = EventSchedule([(0.2, {'kp_a_m': 7.0}), (0.1, {'kp_a_m': 5.0, 'offset_a': 1e-4})])
    after = s.validate(P)
    assert after == [replace(P, kp_a_m=5.0, offset_a=1e-4), replace(P, kp_a_m=7.0,
                                                                    offset_a=1e-4)]


def test_due_applies_at_the_first_tick_at_or_after_the_event_time():
    evs = [Event(0.0025, {'kp_a_m': 3.0}), Event(0.001, {'kp_a_m': 1.0}),
           Event(0.002, {'kp_a_m': 2.0}), Event(0.001, {'ki_a_m_s': 1.0})]
    s = EventSchedule(evs, period_ns=PERIOD_NS)
    assert list(s) == [evs[1], evs[3], evs[2], evs[0]]  # by time, equal times as given
    assert [s.tick_of(e) for e in s] == [1, 1, 2, 3]
    assert s.due(0) == [] and len(s.pending) == 4
    assert s.due(999_999) == []
    assert s.due(1_000_000) == [evs[1], evs[3]]
    assert s.due(2_000_000) == [evs[2]]
    assert s.due(2_000_000) == []
    assert s.due(3_000_000) == [evs[0]] and s.pending == ()
    assert len(s) == 4  # iteration and len cover the whole schedule
    with pytest.raises(ParameterError, match='period_ns'):
        EventSchedule(evs).tick_of(evs[0])
