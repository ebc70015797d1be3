"""The main job and the offline tools on recordings of the real graph."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from eha_ros.recording.reader import McapReader
from eha_ros.tools.campaign import run_campaign
from eha_ros.tools.diagnose import diagnose

BIN = Path(sys.executable).parent


def test_graph_recording_holds_every_tick_and_diagnoses_nominal_valve(eha_graph, tmp_path):
    path = tmp_path / 'run.mcap'
    r = eha_graph(processes=False, scenario='sine_0p1_10pi', duration_s=0.4, record=str(path))
    counts, ticks = {}, []
    for msg in McapReader(str(path)):
        counts[msg.topic] = counts.get(msg.topic, 0) + 1
        if msg.topic == '/eha/state':
            ticks.append(msg.message.tick // 1000)
    missing = sorted(set(range(401)) - set(ticks))
    assert counts['/eha/state'] == r.state['tick'].size == 401, f'missing ticks {missing}'
    assert counts['/clock'] >= 401 and counts['/eha/servovalve_command'] >= 400
    d = diagnose(str(path), update_period_s=0.2)
    assert abs(d['radial_clearance_m'] - 2.5e-6) <= 2 * d['radial_clearance_std_m']
    assert abs(d['overlap_m'] - 1.0e-6) <= 2 * d['overlap_std_m']
    assert d['level'] == 'OK' and d['samples_used'] > 100 and d['kind'] == 'in-service'


def test_diagnose_cli_bad_input(tmp_path, ros_env):
    bad = tmp_path / 'not.mcap'
    bad.write_text('hello')
    out = subprocess.run([str(BIN / 'eha-diagnose'), str(bad)], capture_output=True, text=True,
                         cwd=tmp_path, env=ros_env)
    assert out.returncode == 2 and out.stderr.count('\n') == 1 and 'not.mcap' in out.stderr
    out = subprocess.run([str(BIN / 'eha-diagnose'), str(tmp_path / 'missing.mcap')],
                         capture_output=True, text=True, cwd=tmp_path, env=ros_env)
    assert out.returncode == 2 and 'missing.mcap' in out.stderr


def test_campaign_runs_records_compares_and_reports(tmp_path, ros_env, monkeypatch):
    for k, v in ros_env.items():
        monkeypatch.setenv(k, v)
    out = tmp_path / 'campaign'
    s = run_campaign(out, scenarios=['step_0p1'], models=['hf', 'lut'],
                     progress=lambda line: None, valve_tests=['worn'],
                     valve_test_scenario='valve_test_quick', compare_models=['dlut', 'lut'],
                     seeds=2)
    assert (out / 'report.md').is_file() and (out / 'step_0p1' / 'p12.png').is_file()
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['models'][0] == 'hf'
    for model in summary['models'][1:]:
        err = summary['relative_error_vs_hf']['step_0p1'][model]
        assert 0 < err['jack_position_m'] < 1.0  # a surrogate loop that tracks the command
    assert set(summary['models']) == {'hf', 'lut'}
    worn = summary['valve_test']['worn']
    assert worn['method'] == 'diagnostic-network' and worn['level'] == 'WARN'
    assert abs(worn['radial_clearance_m'] - worn['true_radial_clearance_m']) < 0.05e-6
    assert abs(worn['overlap_m'] - worn['true_overlap_m']) < 0.05e-6
    assert 'Maintenance test' in (out / 'report.md').read_text()
    # the health monitor ran live in every run; its recorded verdicts are the replay's
    live = summary['health_live']
    assert set(live) == {f'step_0p1/{m}' for m in summary['models']} | {'valve_test_quick/worn'}
    for key, h in live.items():
        assert h['live_messages'] >= 1 and h['live_agrees'] is True, key
    # physics-only comparison: noise off against the yardstick, with noise against hf's spread
    c = summary['comparison']
    assert c['models'] == ['dlut', 'lut'] and (out / 'comparison' / 'step_0p1.png').is_file()
    nf = c['noise_free']['step_0p1']
    assert 0 < nf['yardstick']['jack'] < 0.01 and nf['bound']['p12'] >= 0.05
    for m, got in nf['models'].items():  # a model meets the case when it is within both bounds
        assert got['meets'] == (got['jack'] <= nf['bound']['jack']
                                and got['p12'] <= nf['bound']['p12']), m
    assert nf['models']['dlut']['meets']
    assert c['noise']['step_0p1']['hf_seed_to_seed']['p12'] > 0
    assert 'yardstick' in (out / 'report.md').read_text()
    assert s == summary
    with pytest.raises(FileExistsError):
        run_campaign(out, scenarios=['step_0p1'], models=['hf'])
