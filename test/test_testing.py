"""The test helpers: domain ID reservation and isolated ROS environments; the source tree's
explanation of its missing messages."""

import os
from pathlib import Path
import subprocess
import sys

from eha_ros.isolation import allocate_domain_id, DOMAIN_IDS, ros_environment


def test_domain_ids_are_exclusive_until_released(tmp_path):
    leases = [allocate_domain_id(tmp_path) for _ in range(5)]
    try:
        ids = [lease.domain_id for lease in leases]
        assert len(set(ids)) == len(ids)
        assert all(i in DOMAIN_IDS for i in ids)
    finally:
        for lease in leases:
            lease.release()


def test_all_domain_ids_taken_raises(tmp_path):
    leases = [allocate_domain_id(tmp_path) for _ in DOMAIN_IDS]
    try:
        try:
            allocate_domain_id(tmp_path)
        except RuntimeError as exc:
            assert 'in use' in str(exc)
        else:
            raise AssertionError('expected RuntimeError')
    finally:
        for lease in leases:
            lease.release()
    allocate_domain_id(tmp_path).release()  # free again


def test_ros_environment_is_isolated_and_cleaned_up():
    with ros_environment() as first, ros_environment() as second:
        assert first['ROS_DOMAIN_ID'] != second['ROS_DOMAIN_ID']
        assert first['ROS_LOG_DIR'] != second['ROS_LOG_DIR']
        assert first['RMW_IMPLEMENTATION'] == 'rmw_fastrtps_cpp'
        log_dir = Path(first['ROS_LOG_DIR'])
        assert log_dir.is_dir()
        assert 'PATH' in first  # built on the current environment
    assert not log_dir.exists()


def test_ros_env_fixture_sets_and_restores_os_environ(ros_env):
    assert os.environ['ROS_DOMAIN_ID'] == ros_env['ROS_DOMAIN_ID']
    assert os.environ['ROS_LOG_DIR'] == ros_env['ROS_LOG_DIR']
    assert 1 <= int(os.environ['ROS_DOMAIN_ID']) <= 101


def test_importing_messages_from_the_source_tree_explains_why_it_fails():
    """From the repository root the source folder shadows the installed package, which alone
    has the generated messages: the error says so and what to do."""
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, '-c', 'import eha_ros.msg'], cwd=root,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith('ModuleNotFoundError: eha_ros.msg is generated when the package')
    assert str(root / 'eha_ros') in last and 'Run from another directory' in last
