"""Build and install eha_ros: Python code, ROS 2 message interfaces and ROS package files.

One ``pip install .`` gives the nodes and the messages: ``build_py`` is extended to generate
and compile the ``msg/*.msg`` interfaces (see ``rosidl_build/``, no CMake), copy the generated
``eha_ros.msg`` package and its extension module into the build tree, and add the libraries and
ROS package files to ``data_files``:

======================================================  =============================
``<prefix>/lib/libeha_ros__rosidl_*.so``                message libraries
``<prefix>/share/eha_ros/{package.xml,msg/,config/}``   ROS package files
``<prefix>/share/ament_index/resource_index/...``       ament index entries
``<prefix>/lib/eha_ros/<script>``                       ``ros2 run`` launchers
======================================================  =============================
"""

import glob
import os
import shutil
import stat
import sys

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py
from setuptools.dist import Distribution

# setuptools provides distutils (its own copy) once imported; it has no install_data of its own.
from distutils.command.install_data import install_data  # noqa: I100

try:
    from setuptools.errors import SetupError
except ImportError:  # setuptools < 59
    from distutils.errors import DistutilsSetupError as SetupError

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)  # rosidl_build/ is a build helper, not part of the installed package

PACKAGE = 'eha_ros'
VERSION = '0.1.0'
CONSOLE_SCRIPTS = [
    'eha-simulate = eha_ros.tools.simulate:main',
    'eha-build-db = eha_ros.training.database:main',
    'command_generator = eha_ros.nodes.command_generator:main',
    'controller = eha_ros.nodes.controller:main',
    'servovalve_plant = eha_ros.nodes.servovalve_plant:main',
    'health_monitor = eha_ros.nodes.health_monitor:main',
    'recorder = eha_ros.nodes.recorder:main',
    'foxglove_bridge = eha_ros.nodes.foxglove_bridge:main',
    'eha-replay = eha_ros.recording.replay:main',
    'eha-echo = eha_ros.recording.echo:main',
    'eha-compare = eha_ros.recording.compare:main',
    'eha-diagnose = eha_ros.tools.diagnose:main',
    'eha-campaign = eha_ros.tools.campaign:main',
    'eha-graph = eha_ros.tools.graph:main',
    'eha-recover = eha_ros.recording.recover:main',
    'eha-sweep = eha_ros.sweep.cli:main',
]
LAUNCHER_DIR = os.path.join('lib', PACKAGE)


def _relative(pattern):
    """Sorted files matching ``pattern`` below the source folder, relative to it."""
    return sorted(os.path.relpath(p, HERE) for p in glob.glob(os.path.join(HERE, pattern)))


class BinaryDistribution(Distribution):
    """Mark the wheel as platform-specific: it carries compiled message libraries."""

    def has_ext_modules(self):
        return True


class BuildPyWithInterfaces(build_py):
    """``build_py`` that also generates and compiles the ROS 2 message interfaces."""

    def run(self):
        from rosidl_build import build_interfaces, InterfaceError

        # Start from an empty package folder: no file of an earlier build gets packaged.
        shutil.rmtree(os.path.join(self.build_lib, PACKAGE), ignore_errors=True)

        msg_files = _relative(os.path.join('msg', '*.msg'))
        build_temp = self.get_finalized_command('build').build_temp
        try:
            result = build_interfaces(
                PACKAGE, HERE, [os.path.join(HERE, m) for m in msg_files],
                os.path.join(HERE, build_temp, 'rosidl'),
                log=lambda line: self.announce(line, level=2))
        except InterfaceError as exc:
            raise SetupError(f'invalid interface: {exc}') from None
        super().run()

        # Generated Python package eha_ros.msg and the extension module rclpy imports.
        package_build_dir = os.path.join(self.build_lib, PACKAGE)
        generated_msg = os.path.join(package_build_dir, 'msg')
        if os.path.isdir(generated_msg):
            shutil.rmtree(generated_msg)
        shutil.copytree(os.path.join(result.python_package_dir, 'msg'), generated_msg,
                        ignore=shutil.ignore_patterns('*.c'))
        for module in result.extension_modules:
            self.copy_file(str(module), package_build_dir)

        launchers = _write_launchers(os.path.join(HERE, build_temp, 'launchers'))
        share = os.path.join('share', PACKAGE)
        index = os.path.join('share', 'ament_index', 'resource_index')
        # install_data holds a reference to this list: extend it in place.
        self.distribution.data_files.extend([
            ('lib', [str(p) for p in result.libraries]),
            (os.path.join(share, 'msg'),
             [str(p) for p in result.msg_files + result.idl_files +
              result.type_description_files]),
            (os.path.join(index, 'rosidl_interfaces'), [str(result.index_file)]),
            (LAUNCHER_DIR, launchers),
        ])


def _write_launchers(folder):
    """Write ``lib/eha_ros/<script>`` shell launchers that run ``<prefix>/bin/<script>``.

    pip installs console scripts into ``<prefix>/bin`` and ignores ``setup.cfg``'s
    ``install_scripts``; ``ros2 run eha_ros <script>`` looks in ``<prefix>/lib/eha_ros``.
    """
    os.makedirs(folder, exist_ok=True)
    paths = []
    for entry in CONSOLE_SCRIPTS:
        name = entry.split('=')[0].strip()
        path = os.path.join(folder, name)
        with open(path, 'w', encoding='utf-8') as handle:
            handle.write(
                '#!/bin/sh\n'
                f'# Launcher for `ros2 run {PACKAGE} {name}`: runs the console script that pip\n'
                '# installed into <prefix>/bin (this file is <prefix>/lib/eha_ros/<name>).\n'
                'here=$(CDPATH= cd -- "$(dirname -- "$0")" && pwd)\n'
                f'exec "$here/../../bin/{name}" "$@"\n')
        mode = os.stat(path).st_mode
        os.chmod(path, mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
        paths.append(path)
    return paths


class InstallDataKeepingScripts(install_data):
    """``install_data`` that skips the launchers where the real scripts go to lib/eha_ros.

    With ``setup.py install`` (as colcon runs it), ``setup.cfg`` already puts the console
    scripts into ``<prefix>/lib/eha_ros``; the launchers must not overwrite them.
    """

    def run(self):
        scripts_dir = os.path.normpath(self.get_finalized_command('install').install_scripts)
        if scripts_dir == os.path.normpath(os.path.join(self.install_dir, LAUNCHER_DIR)):
            self.data_files = [entry for entry in self.data_files if entry[0] != LAUNCHER_DIR]
        super().run()


setup(
    name=PACKAGE,
    version=VERSION,
    description='Electro-hydraulic servo actuator simulation, surrogates and health '
                'estimation with ROS 2 interfaces',
    license='Apache-2.0',
    python_requires='>=3.10',
    packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*']),
    package_data={PACKAGE: ['**/*.json', '**/*.npz', '**/*.pt']},
    data_files=[
        (os.path.join('share', 'ament_index', 'resource_index', 'packages'),
         [os.path.join('resource', PACKAGE)]),
        (os.path.join('share', PACKAGE), ['package.xml']),
        (os.path.join('share', PACKAGE, 'config'), _relative(os.path.join('config', '*.yaml'))),
        (os.path.join('share', PACKAGE, 'config', 'sweeps'),
         _relative(os.path.join('config', 'sweeps', '*.yaml'))),
        (os.path.join('share', PACKAGE, 'config', 'foxglove'),
         _relative(os.path.join('config', 'foxglove', '*.json'))),
    ],
    # Installed by requirements.txt (pip) or by the ROS distribution (colcon/rosdep).
    install_requires=[],
    zip_safe=False,
    entry_points={'console_scripts': CONSOLE_SCRIPTS},
    cmdclass={'build_py': BuildPyWithInterfaces, 'install_data': InstallDataKeepingScripts},
    distclass=BinaryDistribution,
)
