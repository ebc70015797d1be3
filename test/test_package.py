"""The installed layout: the files ROS 2 tools and rclpy look for under the install prefix."""

import os
from pathlib import Path
import site
import sys

import pytest

import eha_ros

PREFIX = Path(sys.prefix)
LIBRARIES = [f'libeha_ros__rosidl_{kind}.so' for kind in (
    'generator_c', 'generator_py', 'typesupport_c', 'typesupport_fastrtps_c',
    'typesupport_introspection_c')]
MESSAGES = ('ActuatorCommand', 'ActuatorState', 'GraphEvent', 'HealthStatus',
            'ServovalveCommand')


def test_tests_use_the_installed_package():
    """The source folder has no generated eha_ros.msg: it must never shadow the install."""
    installed = [Path(p).resolve() for p in site.getsitepackages()]
    location = Path(eha_ros.__file__).resolve()
    assert any(location.is_relative_to(p) for p in installed), (
        f'eha_ros imported from {location}, not from {installed}: run `make test`')


def test_version():
    assert isinstance(eha_ros.__version__, str) and eha_ros.__version__.count('.') == 2


def test_ros_package_files():
    share = PREFIX / 'share'
    assert (share / 'eha_ros' / 'package.xml').is_file()
    assert (share / 'ament_index' / 'resource_index' / 'packages' / 'eha_ros').is_file()
    for name in MESSAGES:
        for suffix in ('.msg', '.idl', '.json'):
            assert (share / 'eha_ros' / 'msg' / (name + suffix)).is_file(), name + suffix
    index = share / 'ament_index' / 'resource_index' / 'rosidl_interfaces' / 'eha_ros'
    assert set(index.read_text().split()) == {
        f'msg/{name}{suffix}' for name in MESSAGES for suffix in ('.idl', '.msg')}


def test_message_libraries_installed():
    for name in LIBRARIES:
        assert (PREFIX / 'lib' / name).is_file(), name
    modules = list(Path(eha_ros.__file__).parent.glob('eha_ros_s__rosidl_typesupport_c*.so'))
    assert len(modules) == 1


def test_console_script_and_ros2_run_launcher():
    assert (PREFIX / 'bin' / 'eha-simulate').is_file()
    launcher = PREFIX / 'lib' / 'eha_ros' / 'eha-simulate'
    assert launcher.is_file() and os.access(launcher, os.X_OK)
    assert '../../bin/eha-simulate' in launcher.read_text()


def test_ament_index_lookup(monkeypatch):
    from ament_index_python.packages import get_package_share_directory
    from ament_index_python.resources import get_resource

    monkeypatch.setenv('AMENT_PREFIX_PATH', str(PREFIX))
    share = Path(get_package_share_directory('eha_ros'))
    assert share == PREFIX / 'share' / 'eha_ros'
    content, _ = get_resource('rosidl_interfaces', 'eha_ros')
    assert 'msg/ActuatorState.msg' in content.split()


def test_package_xml_declares_dependencies():
    from catkin_pkg.package import parse_package

    package = parse_package(str(PREFIX / 'share' / 'eha_ros' / 'package.xml'))
    package.validate()
    assert package.name == 'eha_ros' and package.package_format == 3
    assert package.version == eha_ros.__version__
    assert package.get_build_type() == 'ament_python'
    run = {d.name for d in package.exec_depends}
    assert {'rclpy', 'std_msgs', 'builtin_interfaces', 'diagnostic_msgs', 'rosgraph_msgs',
            'rosidl_default_runtime', 'python3-numpy'} <= run
    assert {'python3-pytest'} <= {d.name for d in package.test_depends}
    assert {'rosidl_default_generators'} <= {d.name for d in package.buildtool_depends}
    assert 'rosidl_interface_packages' in {g.name for g in package.member_of_groups}


@pytest.mark.parametrize('name', MESSAGES)
def test_installed_msg_files_document_every_field(name):
    """Each field and constant has a comment line (meaning and unit) right above it."""
    lines = (PREFIX / 'share' / 'eha_ros' / 'msg' / f'{name}.msg').read_text().splitlines()
    for number, line in enumerate(lines):
        if line.strip() and not line.lstrip().startswith('#'):
            assert number > 0 and lines[number - 1].lstrip().startswith('#'), (
                f'{name}.msg:{number + 1}: {line!r} has no comment above it')
