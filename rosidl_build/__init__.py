"""Build a package's ROS 2 message interfaces from Python, without CMake.

Used by ``setup.py`` at build time (it is not installed). The steps:

1. :mod:`rosidl_build.spec` parses and checks every ``.msg`` file and resolves the message
   types it uses against the install prefixes that hold ROS packages. Errors are one line that
   names the file, line and field.
2. :mod:`rosidl_build.generate` runs the rosidl generators (``.msg`` -> ``.idl`` -> type
   hashes -> C, C typesupports, Python).
3. :mod:`rosidl_build.compile` compiles the C/C++ code into the ``lib<pkg>__rosidl_*.so``
   libraries and the Python extension module that rclpy imports.

Run ``python -m rosidl_build --help`` for the command-line interface.
"""

from dataclasses import dataclass
from pathlib import Path
import time
from typing import Callable, List, Optional, Sequence

from .spec import InterfaceError, parse_msg_file, ros_prefixes, validate_interfaces

__all__ = [
    'BuildResult',
    'InterfaceError',
    'build_interfaces',
    'parse_msg_file',
    'ros_prefixes',
    'validate_interfaces',
]


@dataclass
class BuildResult:
    """Everything produced for one package, ready to be installed.

    Attributes
    ----------
    python_package_dir : pathlib.Path
        Generated Python package folder; install its ``msg/`` subpackage and
        ``extension_modules`` into the package's import folder.
    extension_modules : list of pathlib.Path
        Python extension modules (already inside ``python_package_dir``).
    libraries : list of pathlib.Path
        Shared libraries for ``<prefix>/lib``.
    msg_files, idl_files, type_description_files : list of pathlib.Path
        Files for ``<prefix>/share/<package>/msg``.
    index_file : pathlib.Path
        ``rosidl_interfaces`` ament index entry, for
        ``<prefix>/share/ament_index/resource_index/rosidl_interfaces/<package>``.
    dependencies : list of str
        Packages whose messages the interfaces use.
    """

    python_package_dir: Path
    extension_modules: List[Path]
    libraries: List[Path]
    msg_files: List[Path]
    idl_files: List[Path]
    type_description_files: List[Path]
    index_file: Path
    dependencies: List[str]


def build_interfaces(
    package: str,
    package_dir,
    msg_files: Sequence,
    build_dir,
    prefixes: Optional[Sequence[Path]] = None,
    jobs: Optional[int] = None,
    log: Callable[[str], None] = print,
) -> BuildResult:
    """Check, generate and compile a package's messages.

    Parameters
    ----------
    package : str
        Package name (also the Python import name).
    package_dir : path-like
        Package root; the ``.msg`` files lie in its ``msg/`` folder.
    msg_files : sequence of path-like
        The ``.msg`` files.
    build_dir : path-like
        Scratch folder for generated code, objects and libraries.
    prefixes : sequence of pathlib.Path, optional
        Install prefixes with the ROS packages; default :func:`ros_prefixes`.
    jobs : int, optional
        Parallel compiler processes.
    log : callable, optional
        Receives progress lines.

    Returns
    -------
    BuildResult

    Raises
    ------
    InterfaceError
        A malformed or unresolvable ``.msg`` (one-line message naming file and field).
    rosidl_build.compile.CompileError
        A compiler is missing or failed.
    """
    from .compile import compile_interfaces
    from .generate import generate_sources

    start = time.monotonic()
    package_dir = Path(package_dir).resolve()
    build_dir = Path(build_dir).resolve()
    prefixes = list(prefixes) if prefixes is not None else ros_prefixes()
    msg_files = sorted(Path(m).resolve() for m in msg_files)
    specs, dependencies = validate_interfaces(msg_files, package, prefixes)
    log(f'rosidl_build: {len(specs)} messages of {package}, using {", ".join(dependencies)}')
    gen = generate_sources(package, package_dir, msg_files, build_dir / 'generated', prefixes,
                           dependencies)
    built = compile_interfaces(gen, prefixes, build_dir, jobs=jobs)
    index_file = build_dir / 'ament_index' / 'rosidl_interfaces' / package
    index_file.parent.mkdir(parents=True, exist_ok=True)
    entries = sorted([f'msg/{p.name}' for p in gen.idl_files] +
                     [f'msg/{p.name}' for p in msg_files])
    index_file.write_text('\n'.join(entries) + '\n', encoding='utf-8')
    log(f'rosidl_build: built {len(built.libraries)} libraries and '
        f'{len(built.extension_modules)} extension module(s) in {time.monotonic() - start:.1f} s')
    return BuildResult(
        python_package_dir=gen.python_package_dir,
        extension_modules=built.extension_modules,
        libraries=built.libraries,
        msg_files=msg_files,
        idl_files=gen.idl_files,
        type_description_files=gen.type_description_files,
        index_file=index_file,
        dependencies=dependencies,
    )
