"""Compile the generated interface code into the libraries rclpy loads, without CMake.

Builds, for package ``pkg``, the same shared libraries as ``rosidl_generate_interfaces()``
(C part only, which is all rclpy needs)::

    libpkg__rosidl_generator_c.so                  structures, init/fini, type descriptions
    libpkg__rosidl_typesupport_introspection_c.so  member tables
    libpkg__rosidl_typesupport_fastrtps_c.so       CDR (de)serialization for Fast DDS
    libpkg__rosidl_typesupport_c.so                dispatch to the two above at run time
    libpkg__rosidl_generator_py.so                 Python <-> C conversion functions
    pkg_s__rosidl_typesupport_c<EXT_SUFFIX>        the extension module rclpy imports

The libraries belong in ``<prefix>/lib`` (the typesupport dispatch finds its implementations
there through the library search path); the extension module belongs next to the generated
``msg/`` package. Objects are compiled in parallel; compiler output is shown only on failure.
"""

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
import os
from pathlib import Path
import shlex
import shutil
import subprocess
import sysconfig
from typing import Callable, List, Optional, Sequence

from .generate import GeneratedSources, PYTHON_TYPESUPPORTS


class CompileError(RuntimeError):
    """A compiler or linker command failed; the message holds the command and its output."""


@dataclass
class BuiltInterfaces:
    """Compiled artefacts of one package's interfaces."""

    libraries: List[Path] = field(default_factory=list)
    extension_modules: List[Path] = field(default_factory=list)


@dataclass
class _Target:
    name: str
    output: Path
    sources: List[Path]
    language: str  # 'c' or 'c++'
    libraries: List[str]
    defines: List[str] = field(default_factory=list)
    python: bool = False
    rpath: str = '$ORIGIN'


def _compiler(language: str) -> str:
    variable, default = ('CC', 'cc') if language == 'c' else ('CXX', 'c++')
    command = os.environ.get(variable, default)
    if shutil.which(shlex.split(command)[0]) is None:
        raise CompileError(
            f'no {language.upper()} compiler found ({variable}={command!r}); building the '
            'message libraries needs gcc and g++ (Debian/Ubuntu: apt-get install g++)')
    return command


def _run(command: List[str]) -> None:
    done = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if done.returncode != 0:
        raise CompileError(f'command failed ({done.returncode}): {shlex.join(command)}\n'
                           f'{done.stdout}')


def _include_dirs(gen: GeneratedSources, prefixes: Sequence[Path], python: bool) -> List[str]:
    dirs = [str(d) for d in gen.include_dirs]
    for prefix in prefixes:
        include = Path(prefix) / 'include'
        if include.is_dir():
            # ROS 2 installs headers as include/<pkg>/<pkg>/...; older layouts use include/<pkg>.
            dirs.append(str(include))
            dirs += sorted(str(d) for d in include.iterdir()
                           if d.is_dir() and not d.name.startswith('python'))
    if python:
        import numpy

        dirs += [sysconfig.get_paths()['include'], numpy.get_include()]
    return dirs


def _targets(gen: GeneratedSources, lib_dir: Path, ext_dir: Path) -> List[_Target]:
    pkg = gen.package
    deps = gen.dependencies

    def dep_libs(suffix: str) -> List[str]:
        return [f'{dep}__{suffix}' for dep in reversed(deps)]

    generator_c = f'{pkg}__rosidl_generator_c'
    typesupport_c = f'{pkg}__rosidl_typesupport_c'
    generator_py = f'{pkg}__rosidl_generator_py'
    targets = [
        _Target(generator_c, lib_dir / f'lib{generator_c}.so',
                gen.sources['rosidl_generator_c'], 'c',
                dep_libs('rosidl_generator_c') + ['rosidl_runtime_c', 'rcutils'],
                [f'ROSIDL_GENERATOR_C_BUILDING_DLL_{pkg}']),
        _Target(f'{pkg}__rosidl_typesupport_introspection_c',
                lib_dir / f'lib{pkg}__rosidl_typesupport_introspection_c.so',
                gen.sources['rosidl_typesupport_introspection_c'], 'c',
                [generator_c] + dep_libs('rosidl_typesupport_introspection_c') +
                dep_libs('rosidl_generator_c') +
                ['rosidl_typesupport_introspection_c', 'rosidl_runtime_c', 'rcutils'],
                [f'ROSIDL_TYPESUPPORT_INTROSPECTION_C_BUILDING_DLL_{pkg}']),
        _Target(f'{pkg}__rosidl_typesupport_fastrtps_c',
                lib_dir / f'lib{pkg}__rosidl_typesupport_fastrtps_c.so',
                gen.sources['rosidl_typesupport_fastrtps_c'], 'c++',
                [generator_c] + dep_libs('rosidl_typesupport_fastrtps_c') +
                dep_libs('rosidl_generator_c') +
                ['rosidl_typesupport_fastrtps_c', 'rosidl_typesupport_fastrtps_cpp',
                 'rosidl_runtime_c', 'rmw', 'fastcdr', 'rcutils'],
                [f'ROSIDL_TYPESUPPORT_FASTRTPS_C_BUILDING_DLL_{pkg}']),
        _Target(typesupport_c, lib_dir / f'lib{typesupport_c}.so',
                gen.sources['rosidl_typesupport_c'], 'c++',
                [generator_c] + dep_libs('rosidl_typesupport_c') +
                ['rosidl_typesupport_c', 'rosidl_runtime_c', 'rcpputils', 'rcutils'],
                [f'ROSIDL_GENERATOR_C_BUILDING_DLL_{pkg}']),
        _Target(generator_py, lib_dir / f'lib{generator_py}.so',
                gen.sources['rosidl_generator_py'], 'c',
                [generator_c, typesupport_c] + dep_libs('rosidl_generator_py') +
                dep_libs('rosidl_generator_c') + ['rosidl_runtime_c', 'rcutils'],
                python=True),
    ]
    ext_suffix = sysconfig.get_config_var('EXT_SUFFIX') or '.so'
    for impl in PYTHON_TYPESUPPORTS:
        name = f'{pkg}_s__{impl}'
        targets.append(_Target(
            name, ext_dir / f'{name}{ext_suffix}',
            [gen.python_package_dir / f'_{pkg}_s.ep.{impl}.c'], 'c',
            [generator_py, typesupport_c, generator_c, 'rosidl_runtime_c', 'rosidl_typesupport_c',
             'rcutils'],
            python=True,
            # <prefix>/lib/pythonX.Y/site-packages/<pkg>/ -> <prefix>/lib
            rpath='$ORIGIN/../../..'))
    return targets


def compile_interfaces(
    gen: GeneratedSources,
    prefixes: Sequence[Path],
    build_dir: Path,
    jobs: Optional[int] = None,
    log: Callable[[str], None] = lambda message: None,
) -> BuiltInterfaces:
    """Compile and link the generated sources.

    Parameters
    ----------
    gen : GeneratedSources
        Output of :func:`rosidl_build.generate.generate_sources`.
    prefixes : sequence of pathlib.Path
        Install prefixes with the ROS headers (``include/``) and libraries (``lib/``).
    build_dir : pathlib.Path
        Folder for objects; libraries go to ``<build_dir>/lib``, the extension module to the
        generated Python package folder.
    jobs : int, optional
        Parallel compiler processes; default the number of CPUs.
    log : callable, optional
        Receives one progress line per linked artefact.

    Returns
    -------
    BuiltInterfaces

    Raises
    ------
    CompileError
        If a compiler is missing or a command fails.
    """
    build_dir = Path(build_dir).resolve()
    obj_dir = build_dir / 'obj'
    lib_dir = build_dir / 'lib'
    for folder in (obj_dir, lib_dir):
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
    ext_dir = gen.python_package_dir
    targets = _targets(gen, lib_dir, ext_dir)
    for target in targets:
        if not target.sources:
            raise CompileError(f'no generated sources for {target.name}')

    lib_dirs = [str(lib_dir)] + [str(Path(p) / 'lib') for p in prefixes
                                 if (Path(p) / 'lib').is_dir()]
    optimisation = os.environ.get('EHA_ROSIDL_CFLAGS', '-O2').split()

    def compile_one(item):
        target, source = item
        obj = obj_dir / target.name / (source.name + '.o')
        obj.parent.mkdir(parents=True, exist_ok=True)
        standard = '-std=c11' if target.language == 'c' else '-std=c++17'
        command = shlex.split(_compiler(target.language)) + [
            standard, '-fPIC', '-w', *optimisation, '-c', str(source), '-o', str(obj)]
        command += [f'-D{d}' for d in target.defines]
        command += [f'-I{d}' for d in _include_dirs(gen, prefixes, target.python)]
        _run(command)
        return obj

    work = [(target, source) for target in targets for source in target.sources]
    with ThreadPoolExecutor(max_workers=jobs or os.cpu_count() or 1) as pool:
        objects = list(pool.map(compile_one, work))

    built = BuiltInterfaces()
    for target in targets:
        target_objects = [o for (t, _), o in zip(work, objects) if t is target]
        command = shlex.split(_compiler(target.language)) + [
            '-shared', '-o', str(target.output), *map(str, target_objects)]
        if not target.python:
            # Unresolved symbols are build errors, not import-time errors.
            command.append('-Wl,--no-undefined')
        command += [f'-L{d}' for d in lib_dirs]
        command += [f'-Wl,-rpath-link,{d}' for d in lib_dirs]
        command += [f'-Wl,-rpath,{target.rpath}']
        command += [f'-l{lib}' for lib in target.libraries]
        _run(command)
        log(f'linked {target.output.name}')
        if target.output.parent == lib_dir:
            built.libraries.append(target.output)
        else:
            built.extension_modules.append(target.output)
    return built
