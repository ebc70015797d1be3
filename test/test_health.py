"""Wear estimation from in-service samples and the health levels."""

import numpy as np
import pytest

from eha_ros.physics import ParameterError, default_params, simulate
from eha_ros.physics.params import replace
from eha_ros.surrogates.health import (ERROR, OK, WARN, HealthEstimate, HealthThresholds,
                                       InServiceEstimator, classify)

P = default_params()


@pytest.mark.parametrize('clearance, overlap', [(4.5e-6, 1e-6), (2.5e-6, -1e-6)])
def test_in_service_fit_recovers_wear(clearance, overlap):
    """A 0.1 mm sine at 5*pi rad/s on a valve of known wear, sampled at 1 kHz: the steady-fit
    estimate is within 0.15 um of the truth on both parameters (the bias left comes from the
    chambers' dynamics that a steady model ignores)."""
    p = replace(P, radial_clearance_m=clearance, overlap_supply_m=overlap,
                overlap_return_m=overlap)
    r = simulate(p, 'sine_0p1_5pi', duration_s=1.0, controller_period_s=1e-3, record_dt_s=1e-3)
    m = r['time_s'] >= 0.3
    e = InServiceEstimator(P).estimate(r['spool_position_m'][m], r['load_flow_m3_s'][m],
                                       r['p12_pa'][m])
    assert abs(e.radial_clearance_m - clearance) < 0.15e-6
    assert abs(e.overlap_m - overlap) < 0.15e-6
    assert 0 < e.radial_clearance_std_m < 0.2e-6 and 0 < e.overlap_std_m < 0.2e-6
    assert e.samples_used == 200 and e.method == 'steady-fit'
    # the data reject the nominal valve: a level is raised
    assert e.nominal_residual_pa > 3 * e.pressure_residual_pa
    assert classify(e, HealthThresholds.load())[0] in (WARN, ERROR)


def test_too_few_samples_refused():
    with pytest.raises(ParameterError, match='at least 10'):
        InServiceEstimator(P).estimate([0.0] * 5, [0.0] * 5, [np.nan] * 5)


def _est(clr, lap, res=1e4):
    return HealthEstimate(clr, 1e-8, lap, 1e-8, res, 100, 'steady-fit')


def test_levels_follow_the_thresholds():
    lim = HealthThresholds.load()
    assert classify(_est(2.5e-6, 1e-6), lim)[0] == OK
    assert classify(_est(4.2e-6, 1e-6), lim)[0] == WARN
    assert classify(_est(5.5e-6, 1e-6), lim)[0] == ERROR
    assert classify(_est(2.5e-6, -0.5e-6), lim)[0] == WARN
    assert classify(_est(2.5e-6, -1.5e-6), lim)[0] == ERROR
    level, text = classify(_est(2.5e-6, 1e-6, res=5e6), lim)
    assert level == ERROR and 'does not explain' in text


def test_in_service_levels_need_the_data_to_reject_the_nominal_valve():
    """With the nominal valve's residual known: below ``anomaly_ratio`` x the best fit's (or x
    ``model_bias_pa``, whichever is larger) the data cannot tell the wear from nominal (OK
    whatever the fit says); above it the estimate grades the level, and a deviation with the
    fit inside the limits is a WARN."""
    lim = HealthThresholds.load()
    assert lim.anomaly_ratio == 3.0

    def est(clr, lap, nominal_res):
        e = _est(clr, lap, res=2e4)
        e.nominal_residual_pa = nominal_res
        return e
    assert lim.model_bias_pa == 5e4
    level, text = classify(est(6e-6, -1e-6, 1.2e5), lim)    # ratio 1.2e5 / 5e4 = 2.4
    assert level == OK and 'consistent with the nominal valve' in text
    assert classify(est(6e-6, -1e-6, 1.6e5), lim)[0] == ERROR  # 3.2
    assert classify(est(4.2e-6, 1e-6, 1.6e5), lim)[0] == WARN
    level, text = classify(est(2.5e-6, 1e-6, 1.6e5), lim)
    assert level == WARN and 'valve test' in text
    # the floor: a fit far better than the model's bias on a healthy valve proves nothing
    e = est(6e-6, -1e-6, 1.2e5)
    e.pressure_residual_pa = 1e3     # unfloored ratio 120
    assert classify(e, lim)[0] == OK


@pytest.mark.parametrize('text, msg', [
    ('clearance_warn_m: 1\n', 'missing'),
    ('[1, 2]\n', 'expected a mapping'),
    ('clearance_warn_m: {value: 6.0e-6}\nclearance_error_m: 5.0e-6\noverlap_warn_m: 0\n'
     'overlap_error_m: -1.0e-6\nresidual_error_pa: 1.0e+6\nanomaly_ratio: 3\n'
     'model_bias_pa: 5.0e+4\n', 'clearance_warn < clearance'),
    ('clearance_warn_m: 4.0e-6\nclearance_error_m: 5.0e-6\noverlap_warn_m: 0\n'
     'overlap_error_m: -1.0e-6\nresidual_error_pa: 1.0e+6\nanomaly_ratio: 0.5\n'
     'model_bias_pa: 5.0e+4\n', 'anomaly ratio'),
])
def test_bad_threshold_files(tmp_path, text, msg):
    f = tmp_path / 'h.yaml'
    f.write_text(text)
    with pytest.raises(ParameterError, match=msg):
        HealthThresholds.load(f)
