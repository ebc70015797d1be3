"""Wear estimation from in-service samples and the health levels."""

import numpy as np
import pytest

from eha_ros.physics import ParameterError, default_params, simulate
from eha_ros.physics.params import replace
from eha_ros.health.posterior import InServiceEstimator
from eha_ros.health.thresholds import (ERROR, OK, WARN, HealthEstimate, HealthThresholds,
                                       classify, classify_fault)

P = default_params()


@pytest.mark.parametrize('clearance, overlap', [(4.5e-6, 1e-6), (2.5e-6, -1e-6)])
def test_in_service_posterior_covers_the_truth(clearance, overlap):
    """A 0.1 mm sine at 5*pi rad/s on a valve of known wear, sampled at 1 kHz: the posterior
    mean is within 2 standard deviations of the truth on both parameters, the deviations are
    those of an informative fit (below 0.7 um, tighter than the uniform prior's 1.4 um), the
    data reject the nominal valve and a level is raised."""
    p = replace(P, radial_clearance_m=clearance, overlap_supply_m=overlap,
                overlap_return_m=overlap)
    r = simulate(p, 'sine_0p1_5pi', duration_s=1.0, controller_period_s=1e-3, record_dt_s=1e-3)
    m = r['time_s'] >= 0.3
    e = InServiceEstimator(P).estimate(r['spool_position_m'][m], r['load_flow_m3_s'][m],
                                       r['p12_pa'][m])
    assert abs(e.radial_clearance_m - clearance) <= 2 * e.radial_clearance_std_m
    assert abs(e.overlap_m - overlap) <= 2 * e.overlap_std_m
    assert 0 < e.radial_clearance_std_m < 0.7e-6 and 0 < e.overlap_std_m < 0.7e-6
    assert e.samples_used == 200 and e.method == 'steady-fit'
    assert e.nominal_residual_pa > 3 * max(e.pressure_residual_pa, 5e4)
    assert classify(e, HealthThresholds.load())[0] in (WARN, ERROR)


def test_uninformative_motion_is_not_labelled_precise():
    """A 0.01 mm ramp on the nominal valve keeps the spool inside the overlap: the steady
    model's residual at the nominal wear is no worse than the best fit's floor, so clearance
    and overlap trade off.  The posterior says so: deviations near the prior's (clearance
    over 0.8 um), the truth within 2 sigma, level OK, and the message states that the two
    cannot be separated."""
    r = simulate(P, 'ramp_0p01', controller_period_s=1e-3, record_dt_s=1e-3)
    m = r['time_s'] >= 0.05
    e = InServiceEstimator(P).estimate(r['spool_position_m'][m], r['load_flow_m3_s'][m],
                                       r['p12_pa'][m])
    assert e.radial_clearance_std_m > 0.8e-6
    assert abs(e.radial_clearance_m - P.radial_clearance_m) <= 2 * e.radial_clearance_std_m
    assert abs(e.overlap_m - P.overlap_supply_m) <= 2 * e.overlap_std_m
    level, text = classify(e, HealthThresholds.load())
    assert level == OK
    assert 'not separable' in text


def test_too_few_samples_refused():
    with pytest.raises(ParameterError, match='at least 10'):
        InServiceEstimator(P).estimate([0.0] * 5, [0.0] * 5, [np.nan] * 5)


def _est(clr, lap, res=1e4):
    return HealthEstimate(clr, 1e-8, lap, 1e-8, res, 100, 'steady-fit')


def _levels(lim):
    """Wear [m] inside each band of ``lim`` (whatever config/health.yaml says): nominal, then
    half-way between warn and error, then as far beyond error again."""
    c_warn = 0.5 * (lim.clearance_warn_m + lim.clearance_error_m)
    c_err = 2 * lim.clearance_error_m - lim.clearance_warn_m
    o_warn = 0.5 * (lim.overlap_warn_m + lim.overlap_error_m)
    o_err = 2 * lim.overlap_error_m - lim.overlap_warn_m
    return c_warn, c_err, o_warn, o_err


def test_levels_follow_the_thresholds():
    lim = HealthThresholds.load()
    clr, lap = P.radial_clearance_m, P.overlap_supply_m
    assert lim.clearance_warn_m > clr and lim.overlap_warn_m < lap  # nominal is healthy
    c_warn, c_err, o_warn, o_err = _levels(lim)
    assert classify(_est(clr, lap), lim)[0] == OK
    assert classify(_est(c_warn, lap), lim)[0] == WARN
    assert classify(_est(c_err, lap), lim)[0] == ERROR
    assert classify(_est(clr, o_warn), lim)[0] == WARN
    assert classify(_est(clr, o_err), lim)[0] == ERROR
    level, text = classify(_est(clr, lap, res=2 * lim.residual_error_pa), lim)
    assert level == ERROR and 'does not explain' in text


def test_in_service_levels_need_the_data_to_reject_the_nominal_valve():
    """With the nominal valve's residual known: below ``anomaly_ratio`` x the best fit's (or x
    ``model_bias_pa``, whichever is larger) the data cannot tell the wear from nominal (OK
    whatever the fit says); above it the estimate grades the level, and a deviation with the
    fit inside the limits is a WARN."""
    lim = HealthThresholds.load()
    c_warn, c_err, o_warn, o_err = _levels(lim)
    fit_res = 0.4 * lim.model_bias_pa           # a fit better than the model: floored
    floor = max(fit_res, lim.model_bias_pa)
    below, above = 0.8 * lim.anomaly_ratio * floor, 1.07 * lim.anomaly_ratio * floor

    def est(clr, lap, nominal_res):
        e = _est(clr, lap, res=fit_res)
        e.nominal_residual_pa = nominal_res
        return e
    level, text = classify(est(c_err, o_err, below), lim)
    assert level == OK and 'consistent with the nominal valve' in text
    assert classify(est(c_err, o_err, above), lim)[0] == ERROR
    assert classify(est(c_warn, P.overlap_supply_m, above), lim)[0] == WARN
    level, text = classify(est(P.radial_clearance_m, P.overlap_supply_m, above), lim)
    assert level == WARN and 'valve test' in text
    # with the posterior's probabilities, a limit counts only with enough mass beyond it
    p = lim.evidence_probability
    e = est(c_warn, P.overlap_supply_m, above)
    e.beyond = {'clearance_warn': p - 0.05, 'clearance_error': 0.1, 'overlap_warn': 0.0,
                'overlap_error': 0.0}
    level, text = classify(e, lim)
    assert level == WARN and 'do not pin' in text
    e.beyond['clearance_warn'] = round(p + 0.02, 2)
    level, text = classify(e, lim)
    assert level == WARN and f'probability {p + 0.02:.2f}' in text
    e.beyond['clearance_error'] = p + 0.01
    assert classify(e, lim)[0] == ERROR
    # the floor: a fit far better than the model's bias on a healthy valve proves nothing
    e = est(c_err, o_err, below)
    e.pressure_residual_pa = 1e-3 * lim.model_bias_pa
    assert classify(e, lim)[0] == OK


def test_fault_levels_need_evidence():
    """A pre-flight estimate passes a limit only when it is beyond it by z sigma (z from
    ``evidence_probability``); the offset's limits apply to its magnitude."""
    from statistics import NormalDist
    lim = HealthThresholds.load()
    z = NormalDist().inv_cdf(lim.evidence_probability)
    f = lim.fault('demagnetisation')
    sd = (f.error - f.warn) / 10
    assert classify_fault(f.name, f.warn - sd, sd, lim)[0] == OK
    level, text = classify_fault(f.name, f.warn + 0.5 * z * sd, sd, lim)
    assert level == OK and 'not proven' in text
    assert classify_fault(f.name, f.warn + 1.5 * z * sd, sd, lim)[0] == WARN
    level, text = classify_fault(f.name, f.error + 1.5 * z * sd, sd, lim)
    assert level == ERROR and f'error limit {f.error:g}' in text
    o = lim.fault('offset_a')
    assert o.absolute
    sd = (o.error - o.warn) / 10
    assert classify_fault(o.name, -(o.error + 1.5 * z * sd), sd, lim)[0] == ERROR
    assert classify_fault(o.name, -(o.warn + 1.5 * z * sd), sd, lim)[0] == WARN


_REST = ('evidence_probability: 0.95\nseparable_correlation: 0.9\nstale_after_s: 2\n'
         'likelihood_temperature: 16\n')
_GOOD = ('clearance_warn_m: 4.0e-6\nclearance_error_m: 5.0e-6\noverlap_warn_m: 0\n'
         'overlap_error_m: -1.0e-6\nresidual_error_pa: 1.0e+6\nanomaly_ratio: 3\n'
         'model_bias_pa: 5.0e+4\n' + _REST)


@pytest.mark.parametrize('text, msg', [
    ('clearance_warn_m: 1\n', 'missing'),
    ('[1, 2]\n', 'expected a mapping'),
    ('clearance_warn_m: {value: 6.0e-6}\nclearance_error_m: 5.0e-6\noverlap_warn_m: 0\n'
     'overlap_error_m: -1.0e-6\nresidual_error_pa: 1.0e+6\nanomaly_ratio: 3\n'
     'model_bias_pa: 5.0e+4\n' + _REST, 'clearance_warn < clearance'),
    ('clearance_warn_m: 4.0e-6\nclearance_error_m: 5.0e-6\noverlap_warn_m: 0\n'
     'overlap_error_m: -1.0e-6\nresidual_error_pa: 1.0e+6\nanomaly_ratio: 0.5\n'
     'model_bias_pa: 5.0e+4\n' + _REST, 'anomaly ratio'),
    (_GOOD + 'faults:\n  demagnetisation: {warn: 0.3, error: 0.2}\n', 'warn < error'),
    (_GOOD.replace('stale_after_s: 2', 'stale_after_s: 0'), 'stale_after_s'),
])
def test_bad_threshold_files(tmp_path, text, msg):
    f = tmp_path / 'h.yaml'
    f.write_text(text)
    with pytest.raises(ParameterError, match=msg):
        HealthThresholds.load(f)


def test_diagnostics_go_stale_when_states_stop(ros_env):
    """The monitor in this process, fed ten states by a test publisher and then none: its
    /diagnostics carry one status per monitored parameter (plus the estimate), all with the
    hardware id; parameters never estimated are STALE; once no state has come for
    stale_after_s every status is STALE and says for how long."""
    import time

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.parameter import Parameter

    from eha_ros.graph import TOPIC_DIAGNOSTICS, TOPIC_STATE
    from eha_ros.msg import ActuatorState
    from eha_ros.nodes.common import QOS, make_executor
    from eha_ros.nodes.health_monitor import HealthMonitor
    from eha_ros.health.monitor import ITEMS
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        mon = HealthMonitor(context=ctx, parameter_overrides=[
            Parameter('stale_after_s', value=0.3), Parameter('hardware_id', value='sv-42')])
        peer = rclpy.create_node('stale_probe', context=ctx)
        got = []
        peer.create_subscription(DiagnosticArray, TOPIC_DIAGNOSTICS, got.append, QOS)
        pub = peer.create_publisher(ActuatorState, TOPIC_STATE, QOS)
        ex = make_executor(ctx)
        ex.add_node(mon)
        ex.add_node(peer)
        end = time.monotonic() + 10
        while pub.get_subscription_count() < 1 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        for k in range(10):
            m = ActuatorState()
            m.header.stamp.nanosec = (k + 1) * 1_000_000
            m.sim_time_s = (k + 1) * 1e-3
            pub.publish(m)
            ex.spin_once(timeout_sec=0.01)
        got.clear()
        end = time.monotonic() + 10
        while time.monotonic() < end and not any(
                'no actuator state for' in a.status[0].message for a in got):
            ex.spin_once(timeout_sec=0.05)
        arr = next(a for a in got if 'no actuator state for' in a.status[0].message)
        names = [s.name for s in arr.status]
        assert names == ['health_monitor: estimate'] + [f'health_monitor: {n}' for n in ITEMS]
        assert all(s.level == DiagnosticStatus.STALE for s in arr.status)
        assert all(s.hardware_id == 'sv-42' for s in arr.status)
        mon.close()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_cached_reader_reads_a_file_once_per_state(tmp_path):
    """The one artefact reader cached by modification time: an unchanged file is read once,
    a rewritten one again, a missing one raises and leaves nothing kept, ``clear`` forgets."""
    import os
    from eha_ros.artefacts import CachedReader
    reads = []

    def read(path):
        reads.append(path)
        return path.read_text()

    reader = CachedReader(read)
    f = tmp_path / 'a.npz'
    with pytest.raises(FileNotFoundError):
        reader(f)
    f.write_text('one')
    os.utime(f, ns=(1_000_000_000, 1_000_000_000))
    assert reader(f) == reader(tmp_path / '.' / 'a.npz') == 'one'
    assert len(reads) == 2  # the failed read and one read of 'one'
    f.write_text('two')
    os.utime(f, ns=(2_000_000_000, 2_000_000_000))
    assert reader(f) == 'two' and len(reads) == 3
    reader.clear()
    assert reader(f) == 'two' and len(reads) == 4
