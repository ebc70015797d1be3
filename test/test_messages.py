"""The generated message classes: import, constants, field checks, and transport.

The transport tests put every field of every message through CDR serialization, in-process
and between two separate processes over Fast DDS, and compare the result bit for bit.
"""

import json
from pathlib import Path
import subprocess
import sys

import pytest

from eha_ros.testing import MESSAGE_TYPES, message_class, message_to_bitwise_json, sample_message

# Generous limits: they only bound a hung test; discovery usually takes well under 1 s.
DISCOVERY_TIMEOUT_S = 10.0
PROCESS_TIMEOUT_S = 60.0


def test_messages_import():
    from eha_ros.msg import ActuatorCommand, ActuatorState, HealthStatus, ServovalveCommand

    for cls in (ActuatorCommand, ActuatorState, HealthStatus, ServovalveCommand):
        assert cls.__module__.startswith('eha_ros.msg.')


def test_fields_in_file_order():
    from eha_ros.msg import ActuatorState, HealthStatus

    assert list(ActuatorState.get_fields_and_field_types()) == [
        'header', 'jack_position_m', 'jack_position_measured_m', 'jack_velocity_m_s',
        'spool_position_m', 'flapper_position_m', 'p1_pa', 'p2_pa', 'p12_pa',
        'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n', 'sim_time_s', 'tick',
        'model', 'status', 'valve_test_point', 'valve_test_point_end', 'valve_test_procedure',
        'supply_pressure_measured_pa', 'return_pressure_measured_pa',
        'fluid_temperature_measured_k', 'command_age_ticks', 'safe_action', 'final_state']
    assert ActuatorState.get_fields_and_field_types()['tick'] == 'uint64'
    assert ActuatorState.get_fields_and_field_types()['command_age_ticks'] == 'uint32'
    assert ActuatorState.get_fields_and_field_types()['status'] == 'uint8'
    assert list(HealthStatus.get_fields_and_field_types()) == [
        'header', 'radial_clearance_m', 'radial_clearance_std_m', 'overlap_m', 'overlap_std_m',
        'pressure_residual_pa', 'level', 'method', 'message', 'samples_used',
        'parameter_names', 'parameter_values', 'parameter_stds', 'parameter_levels']
    assert HealthStatus.get_fields_and_field_types()['samples_used'] == 'uint32'
    assert HealthStatus.get_fields_and_field_types()['parameter_values'] == 'sequence<double>'


def test_constants():
    from eha_ros.msg import ActuatorState, HealthStatus

    assert (ActuatorState.STATUS_OK, ActuatorState.STATUS_END_STOP,
            ActuatorState.STATUS_CAVITATION, ActuatorState.STATUS_DIVERGED,
            ActuatorState.STATUS_VALVE_TEST, ActuatorState.STATUS_PREFLIGHT,
            ActuatorState.STATUS_STOPPED) == (0, 1, 2, 3, 4, 5, 6)
    from eha_ros.watchdog import SAFE_CODES, SAFE_NONE
    assert ActuatorState.SAFE_NONE == SAFE_NONE
    assert {a: getattr(ActuatorState, f'SAFE_{a.upper()}') for a in SAFE_CODES} == SAFE_CODES
    assert (HealthStatus.LEVEL_OK, HealthStatus.LEVEL_WARN, HealthStatus.LEVEL_ERROR,
            HealthStatus.LEVEL_CANNOT_ASSESS) == (0, 1, 2, 3)
    assert (ActuatorState.VALVE_TEST_REFERENCE, ActuatorState.VALVE_TEST_SETTLED) == (0, 1)
    # Constants are also visible on instances.
    assert ActuatorState().STATUS_DIVERGED == 3


def test_defaults_are_zero():
    from eha_ros.msg import ActuatorState

    msg = ActuatorState()
    assert msg.jack_position_m == 0.0 and msg.tick == 0 and msg.model == ''
    assert msg.status == ActuatorState.STATUS_OK
    assert msg.header.frame_id == '' and msg.header.stamp.sec == 0


def test_unknown_field_raises_attribute_error():
    from eha_ros.msg import ActuatorState

    msg = ActuatorState()
    with pytest.raises(AttributeError, match='jack_positon_m'):
        msg.jack_positon_m = 0.1  # misspelt
    with pytest.raises(AttributeError):
        _ = msg.no_such_field


@pytest.mark.parametrize('field, value', [
    ('jack_position_m', '0.1'),       # str into float64
    ('jack_position_m', 1),           # int into float64
    ('tick', -1),                     # below uint64 range
    ('tick', 2**64),                  # above uint64 range
    ('status', 256),                  # above uint8 range
    ('model', 3),                     # int into string
    ('header', 'frame'),              # not a std_msgs/Header
])
def test_wrong_type_or_range_raises(field, value):
    from eha_ros.msg import ActuatorState

    msg = ActuatorState(check_fields=True)
    with pytest.raises(AssertionError, match=field):
        setattr(msg, field, value)


def test_unknown_constructor_argument_raises():
    from eha_ros.msg import HealthStatus

    with pytest.raises(AssertionError, match='levle'):
        HealthStatus(levle=1, check_fields=True)


def test_sample_messages_differ_from_defaults():
    """Every leaf of every sample differs from its default, so the transport tests are strict."""
    def leaves(data, path=''):
        if isinstance(data, dict):
            for key, value in data.items():
                yield from leaves(value, f'{path}.{key}')
        else:
            yield path, data

    for type_name in MESSAGE_TYPES:
        cls = message_class(type_name)
        sample = dict(leaves(message_to_bitwise_json(sample_message(cls))))
        default = dict(leaves(message_to_bitwise_json(cls())))
        assert sample.keys() == default.keys()
        same = [path for path in sample if sample[path] == default[path] and path != '.type']
        assert not same, f'{type_name}: sample equals default in {same}'


@pytest.mark.parametrize('type_name', MESSAGE_TYPES)
def test_cdr_round_trip_in_process(ros_env, type_name):
    from rclpy.serialization import deserialize_message, serialize_message

    cls = message_class(type_name)
    msg = sample_message(cls)
    data = serialize_message(msg)
    assert isinstance(data, bytes) and len(data) > 4
    back = deserialize_message(data, cls)
    assert back == msg
    assert message_to_bitwise_json(back) == message_to_bitwise_json(msg)


def test_every_message_crosses_processes_intact(ros_env, tmp_path):
    """A publisher process and a subscriber process exchange every message type over DDS."""
    command = [sys.executable, '-m', 'eha_ros.testing']
    # Working directory outside the source tree: `python -m` puts it first on sys.path.
    options = dict(env=ros_env, cwd=tmp_path, text=True,
                   stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    subscriber = subprocess.Popen(command + ['sub', '--timeout', str(3 * DISCOVERY_TIMEOUT_S)],
                                  **options)
    publisher = subprocess.Popen(command + ['pub', '--timeout', str(3 * DISCOVERY_TIMEOUT_S)],
                                 stdin=subprocess.PIPE, **options)
    try:
        sub_out, sub_err = subscriber.communicate(timeout=PROCESS_TIMEOUT_S)
    finally:
        if subscriber.poll() is None:
            subscriber.kill()
            subscriber.communicate()
        try:
            # Closing its stdin (after writing nothing) tells the publisher to stop.
            _, pub_err = publisher.communicate(input='', timeout=PROCESS_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            publisher.kill()
            _, pub_err = publisher.communicate()
    assert subscriber.returncode == 0, f'subscriber: {sub_err}\npublisher: {pub_err}'
    assert publisher.returncode == 0, f'publisher: {pub_err}'

    result = json.loads(sub_out.strip().splitlines()[-1])
    assert 'site-packages' in Path(result['eha_ros_file']).parts
    for type_name in MESSAGE_TYPES:
        expected = message_to_bitwise_json(sample_message(message_class(type_name)))
        assert result['messages'][type_name] == expected, type_name
