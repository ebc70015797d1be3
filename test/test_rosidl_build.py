"""The interface checks of the build helper (rosidl_build/, run by setup.py at build time).

A malformed ``.msg`` must stop the build with one line that names the file and the field.
"""

import importlib.util
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]


def _load_build_helper():
    """Import rosidl_build from the source tree (it is a build helper, not installed)."""
    init = REPO / 'rosidl_build' / '__init__.py'
    spec = importlib.util.spec_from_file_location(
        'rosidl_build', init, submodule_search_locations=[str(init.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules['rosidl_build'] = module
    spec.loader.exec_module(module)
    return module


rosidl_build = _load_build_helper()
PREFIXES = [Path(sys.prefix)]  # the venv holds std_msgs and builtin_interfaces (ros-* wheels)


def test_package_messages_are_valid():
    msg_files = sorted((REPO / 'msg').glob('*.msg'))
    specs, dependencies = rosidl_build.validate_interfaces(msg_files, 'eha_ros', PREFIXES)
    assert [s.name for s in specs] == [
        'ActuatorCommand', 'ActuatorState', 'GraphEvent', 'HealthStatus', 'ServovalveCommand']
    assert dependencies == ['builtin_interfaces', 'std_msgs']  # dependencies first
    state = {s.name: s for s in specs}['ActuatorState']
    assert len(state.fields) == 25
    assert {c.name: c.value for c in state.constants} == {
        'STATUS_OK': 0, 'STATUS_END_STOP': 1, 'STATUS_CAVITATION': 2, 'STATUS_DIVERGED': 3,
        'STATUS_VALVE_TEST': 4, 'STATUS_PREFLIGHT': 5, 'STATUS_STOPPED': 6,
        'VALVE_TEST_REFERENCE': 0, 'VALVE_TEST_SETTLED': 1, 'SAFE_NONE': 0, 'SAFE_HOLD': 1,
        'SAFE_NULL_CURRENT': 2, 'SAFE_STOP': 3}


@pytest.mark.parametrize('line, field, reason', [
    ('float46 jack_position_m', 'jack_position_m', "unknown type 'float46'"),
    ('std_msgs/Hedaer source', 'source', "package 'std_msgs' has no message 'Hedaer'"),
    ('nosuch_msgs/Thing thing', 'thing', "package 'nosuch_msgs' not found"),
    ('Missing local_thing', 'local_thing', 'no Missing.msg in this package'),
    ('float64 JackPosition', 'JackPosition', 'invalid name'),
    ('float64 jack__position', 'jack__position', 'invalid name'),
    ('float64 lambda', 'lambda', 'Python keyword'),
    ('float64 p1_pa 1.5e', 'p1_pa', 'not a number'),
    ('uint8 STATUS_BAD=256', 'STATUS_BAD', 'out of range'),
    ('uint8 status_bad=1', 'status_bad', 'invalid name'),
    ('uint8[<] samples', 'samples', 'malformed'),
])
def test_malformed_msg_fails_with_one_line(tmp_path, line, field, reason):
    bad = tmp_path / 'msg' / 'Broken.msg'
    bad.parent.mkdir()
    bad.write_text(f'# A broken message.\n\nstd_msgs/Header header\n{line}\n')
    with pytest.raises(rosidl_build.InterfaceError) as caught:
        rosidl_build.validate_interfaces([bad], 'eha_ros', PREFIXES)
    message = str(caught.value)
    assert '\n' not in message
    assert 'Broken.msg:4:' in message
    assert repr(field) in message and reason in message


def test_duplicate_field_names_the_first_definition(tmp_path):
    bad = tmp_path / 'Twice.msg'
    bad.write_text('float64 p1_pa\nfloat64 p2_pa\nfloat64 p1_pa\n')
    with pytest.raises(rosidl_build.InterfaceError, match=r"Twice.msg:3: field 'p1_pa': "
                                                          r'duplicate name .*line 1'):
        rosidl_build.validate_interfaces([bad], 'eha_ros', PREFIXES)


def test_line_without_field_name(tmp_path):
    bad = tmp_path / 'Short.msg'
    bad.write_text('float64\n')
    with pytest.raises(rosidl_build.InterfaceError, match=r'Short.msg:1: line .*expected'):
        rosidl_build.parse_msg_file(bad, 'eha_ros')


def test_command_line_reports_one_line(tmp_path):
    bad = tmp_path / 'Bad.msg'
    bad.write_text('float64 ok_m\nfloat46 speed_m_s\n')
    done = subprocess.run(
        [sys.executable, '-m', 'rosidl_build', 'check', str(bad)], cwd=REPO,
        capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith('error: ') and 'Bad.msg:2' in lines[0]
    assert "field 'speed_m_s'" in lines[0] and "unknown type 'float46'" in lines[0]
