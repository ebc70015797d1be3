"""``eha-graph`` (the launch-free launcher) and ``config/graph.yaml`` (every node's parameters
with their defaults in ROS 2's params-file form).

Every run gets its own ROS domain and log folder (``ros_env``)."""

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np
from numpy.testing import assert_array_equal
import pytest
import yaml

from eha_ros import graph
from eha_ros.recording.definitions import RecordingError
from eha_ros.recording.reader import scan

BIN = Path(sys.executable).parent
INSTALLED_YAML = Path(sys.prefix) / 'share' / 'eha_ros' / 'config' / 'graph.yaml'
TIMEOUT_S = 120


def _run(args, env, cwd, **kw):
    return subprocess.run([str(BIN / 'eha-graph'), *args], env=env, cwd=cwd, text=True,
                          capture_output=True, timeout=TIMEOUT_S, **kw)


def _one_line_error(stderr, prog='eha-graph'):
    lines = [line for line in stderr.strip().splitlines() if line.startswith(f'{prog}: error')]
    assert len(lines) == 1, stderr
    return lines[0]


# --- config/graph.yaml ------------------------------------------------------------------------

def test_graph_yaml_holds_every_declared_parameter_and_default(ros_env):
    """The installed graph.yaml is what `eha-graph --print-params` prints from the nodes'
    declarations, and rcl's own params-file parser gives every node exactly those values."""
    import rclpy

    from eha_ros.nodes.command_generator import CommandGenerator
    from eha_ros.nodes.controller import Controller
    from eha_ros.nodes.health_monitor import HealthMonitor
    from eha_ros.nodes.servovalve_plant import ServovalvePlant
    from eha_ros.tools.graph import defaults_yaml, node_defaults

    text = INSTALLED_YAML.read_text()
    assert text == defaults_yaml()
    data = yaml.safe_load(text)
    defaults = node_defaults()
    assert {k.strip('/') for k in data} == set(graph.NODES) | {'recorder', 'foxglove_bridge'}
    for node, values in defaults.items():
        assert data[f'/{node}']['ros__parameters'] == values, node
        for name, value in values.items():  # floats stay floats: ROS types by the YAML form
            assert type(data[f'/{node}']['ros__parameters'][name]) is type(value), name
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']),
               args=['--ros-args', '--params-file', str(INSTALLED_YAML)])
    try:
        for name, cls in (('command_generator', CommandGenerator), ('controller', Controller),
                          ('servovalve_plant', ServovalvePlant),
                          ('health_monitor', HealthMonitor)):
            node = cls(context=context)
            try:
                for pname, value in defaults[name].items():
                    got = node.get_parameter(pname).value
                    got = list(got) if not isinstance(got, (str, bool, int, float)) else got
                    assert got == value, (name, pname)
            finally:
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_graph_yaml_is_read_by_a_node_started_with_params_file(ros_env, tmp_path):
    """`servovalve_plant --ros-args --params-file FILE` takes the file's values: a
    non-physical clearance in it is refused at start, naming the parameter."""
    data = yaml.safe_load(INSTALLED_YAML.read_text())
    data['/servovalve_plant']['ros__parameters']['radial_clearance_m'] = 0.0
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump(data))
    out = subprocess.run([str(BIN / 'servovalve_plant'), '--ros-args', '--params-file', str(bad)],
                         env=ros_env, cwd=tmp_path, text=True, capture_output=True,
                         timeout=TIMEOUT_S)
    assert out.returncode == 2
    assert 'radial_clearance_m' in _one_line_error(out.stderr, 'servovalve_plant')


# --- eha-graph --------------------------------------------------------------------------------

def test_lockstep_one_process_run_equals_the_physics_with_every_setting(ros_env, tmp_path,
                                                                        capfd):
    """--one-process lockstep with --health, --record, --set, --params-file, --seed, --dt,
    --rate, --duration, --json: the recorded jack position equals the physics-only loop with
    the same settings bit for bit (so each reached the nodes), and the summary says so."""
    from eha_ros.physics import default_params, simulate
    from eha_ros.physics.params import replace
    from eha_ros.recording.arrays import load_topic_arrays
    from eha_ros.tools.graph import main

    params = yaml.safe_load(INSTALLED_YAML.read_text())
    params['/controller']['ros__parameters']['kp_a_m'] = 12.5
    params['/command_generator']['ros__parameters']['scenario'] = 'ramp_0p1'  # --scenario wins
    custom = tmp_path / 'custom.yaml'
    custom.write_text(yaml.safe_dump(params))
    record = tmp_path / 'run.mcap'
    code = main(['--one-process', '--mode', 'lockstep', '--scenario', 'sine_0p1_10pi',
                 '--duration', '0.06', '--health', '--record', str(record), '--seed', '3',
                 '--dt', '2e-6', '--rate', '1000', '--params-file', str(custom),
                 '--set', 'servovalve_plant.radial_clearance_m=4e-6',
                 '--set', 'health_monitor.settle_s=0.0', '--json'])
    captured = capfd.readouterr()
    out = captured.out
    assert code == 0, captured.err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary['complete'] and summary['layout'] == 'one-process'
    assert summary['scenario'] == 'sine_0p1_10pi' and summary['states'] == 61
    assert summary['ticks_missing'] == 0 and not summary['diverged']
    assert summary['recording']['complete'] and summary['recording']['lost'] == {
        t: 0 for t in summary['recording']['messages']}
    assert summary['recording']['messages'][graph.TOPIC_STATE] >= 61
    assert 'health' in summary
    p = replace(default_params(), radial_clearance_m=4e-6, kp_a_m=12.5)
    ref = simulate(p, 'sine_0p1_10pi', duration_s=0.06, dt_s=2e-6, controller_period_s=1e-3,
                   record_dt_s=None, seed=3)
    state = load_topic_arrays(record, graph.TOPIC_STATE)
    _, first = np.unique(state['stamp_ns'], return_index=True)
    assert_array_equal(state['jack_position_m'][first], ref['jack_position_m'][:first.size])


def test_split_integrator_run_equals_the_physics(ros_env, tmp_path, capfd):
    """--integrator split --dt 1e-5 reaches the plant: the recorded jack position equals
    simulate(integrator='split') at that step bit for bit; an unknown integrator is refused
    before anything starts."""
    from eha_ros.physics import default_params, simulate
    from eha_ros.recording.arrays import load_topic_arrays
    from eha_ros.tools.graph import main

    record = tmp_path / 'run.mcap'
    code = main(['--one-process', '--mode', 'lockstep', '--scenario', 'step_0p1',
                 '--duration', '0.05', '--record', str(record), '--dt', '1e-5',
                 '--integrator', 'split', '--json'])
    captured = capfd.readouterr()
    assert code == 0, captured.err
    ref = simulate(default_params(), 'step_0p1', duration_s=0.05, dt_s=1e-5,
                   controller_period_s=1e-3, record_dt_s=None, integrator='split')
    state = load_topic_arrays(record, graph.TOPIC_STATE)
    _, first = np.unique(state['stamp_ns'], return_index=True)
    assert first.size == 51
    assert_array_equal(state['jack_position_m'][first], ref['jack_position_m'][:first.size])
    assert main(['--one-process', '--integrator', 'rk4', '--duration', '0.01']) == 2
    assert "integrator 'rk4' must be one of explicit, split" in capfd.readouterr().err


def test_realtime_processes_run_prints_a_summary(ros_env, tmp_path):
    out = _run(['--processes', '--mode', 'realtime', '--scenario', 'sine_0p1_5pi', '--model',
                'lut', '--duration', '0.3'], ros_env, tmp_path)
    assert out.returncode == 0, out.stderr
    assert 'sine_0p1_5pi model lut, realtime, processes: complete' in out.stdout
    assert 'states' in out.stdout


#: Nodes that report their timing on /diagnostics.
TICKING = ('command_generator', 'controller', 'servovalve_plant')


def _timing_reports(path):
    """The last report of each status name on /diagnostics in a recording ({} if unreadable)."""
    from eha_ros.recording.reader import iter_decoded
    reports = {}
    try:
        for msg in iter_decoded(path, topics=[graph.TOPIC_DIAGNOSTICS]):
            for st in msg.message.status:
                reports[st.name] = {kv.key: kv.value for kv in st.values}
    except (OSError, RecordingError):  # not created yet, or only its header
        pass
    return reports


def test_ctrl_c_stops_every_node_and_keeps_the_recording(ros_env, tmp_path):
    """SIGINT to the process group (a terminal's Ctrl-C) in the middle of a realtime run:
    every node process ends, the recording is closed complete, the exit status is 130. The
    recording holds each node's timing report from /diagnostics."""
    record = tmp_path / 'run.mcap'
    proc = subprocess.Popen([str(BIN / 'eha-graph'), '--mode', 'realtime', '--scenario',
                             'sine_0p1_5pi', '--duration', '120', '--record', str(record)],
                            env=ros_env, cwd=tmp_path, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        line = ''
        while 'running' not in line:
            line = proc.stderr.readline()
            assert line or proc.poll() is None, proc.stderr.read()
        pids = [int(p) for p in line.replace(')', ' ').split('pid ')[1:] for p in [p.split()[0]]]
        assert len(pids) == 4  # command generator, controller, plant, recorder
        deadline = time.monotonic() + TIMEOUT_S
        while not {f'{n}: timing' for n in TICKING} <= _timing_reports(record).keys():
            assert time.monotonic() < deadline  # until every node's timing is recorded
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, stderr
    assert 'interrupted' in stdout
    for pid in pids:
        assert not Path(f'/proc/{pid}').exists() or 'Z' in Path(f'/proc/{pid}/stat').read_text(
        ).split()[2], pid
    info = scan(record, strict=True)
    assert info.complete and info.message_counts[graph.TOPIC_STATE] > 0
    reports = _timing_reports(record)
    import yaml

    from eha_ros.physics.params import config_dir
    config = yaml.safe_load((config_dir() / 'graph.yaml').read_text())
    for node in TICKING:
        values = {k: float(v) for k, v in reports[f'{node}: timing'].items()
                  if k.endswith(('(Hz)', 'window', '(ms)', 'startup', '(%)'))}
        # the report describes this run: the node's configured rate, ticks counted, a
        # percentage that is one, whole counts
        assert values['Target frequency (Hz)'] == config[f'/{node}']['ros__parameters']['rate_hz']
        assert values['Events in window'] >= 1 and values['Actual frequency (Hz)'] > 0
        assert 0 <= values['On time since startup (%)'] <= 100
        for key in ('Slipped ticks since startup', 'Overruns since startup'):
            assert values[key] >= 0 and values[key].is_integer(), (node, key)


def test_a_refused_value_exits_2_naming_it(ros_env, tmp_path):
    """A non-physical value reaches the plant, which refuses it at start: one line naming the
    node and the parameter, exit 2 (bad input), as for a name no node declares."""
    out = _run(['--processes', '--duration', '0.05',
                '--set', 'servovalve_plant.radial_clearance_m=0.0'], ros_env, tmp_path)
    assert out.returncode == 2
    line = _one_line_error(out.stderr)
    assert 'servovalve_plant' in line and 'radial_clearance_m' in line


def test_a_failing_node_gives_a_non_zero_exit(ros_env, tmp_path):
    """A node that dies during the run (the controller, killed once the graph runs): exit 1,
    one line naming it."""
    proc = subprocess.Popen([str(BIN / 'eha-graph'), '--processes', '--mode', 'realtime',
                             '--duration', '60'], env=ros_env, cwd=tmp_path, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        line = proc.stderr.readline()
        assert 'controller (pid' in line, line
        pid = int(line.split('controller (pid ')[1].split(')')[0])
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1
    line = _one_line_error(line + err)
    assert 'controller' in line and 'killed by SIGKILL' in line


@pytest.mark.parametrize('args, words', [
    (['--scenario', 'no_such'], ['no_such']),
    (['--model', 'warp'], ['warp']),
    (['--mode', 'sometimes'], ['sometimes']),
    (['--set', 'radial_clearance_m=4e-6'], ['node.parameter=value']),
    (['--set', 'pump.x=1'], ['pump']),
    (['--set', 'controller.mode=realtime'], ['controller.mode', '--mode']),
    (['--params-file', '/nonexistent/graph.yaml'], ['/nonexistent/graph.yaml']),
    (['--duration', '-1'], ['--duration']),
    (['--record', 'EXISTING'], ['exists']),
])
def test_bad_input_is_refused_in_one_line(ros_env, tmp_path, capfd, args, words):
    from eha_ros.tools.graph import main

    existing = tmp_path / 'existing.mcap'
    existing.write_bytes(b'keep')
    args = [str(existing) if a == 'EXISTING' else a for a in args]
    assert main(args) == 2
    line = _one_line_error(capfd.readouterr().err)
    for w in words:
        assert w in line
    assert existing.read_bytes() == b'keep'


def test_list_prints_every_scenario(capfd):
    from eha_ros.physics import load_scenarios
    from eha_ros.tools.graph import main

    assert main(['--list']) == 0
    names = [line.split()[0] for line in capfd.readouterr().out.splitlines()]
    assert names == sorted(load_scenarios()) and set(graph.REFERENCE_SCENARIOS) <= set(names)
