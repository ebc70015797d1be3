"""Run the rosidl code generators on a package's ``.msg`` files, without CMake.

This does in Python what ``rosidl_generate_interfaces()`` does through CMake: translate each
``.msg`` to ``.idl`` (``rosidl_adapter``), compute the type descriptions and hashes
(``rosidl_generator_type_description``), then expand the templates of the C generator, the C
typesupports (dispatch, Fast DDS, introspection) and the Python generator. Each generator reads
a JSON arguments file, written here with the same keys CMake writes.

The ``rosidl_*`` packages are imported inside the functions, so that :mod:`rosidl_build.spec`
stays usable where the generators are not installed.
"""

import contextlib
from dataclasses import dataclass, field
import io
import json
from pathlib import Path
import shutil
from typing import Dict, List, Sequence

from .spec import InterfaceError

#: C typesupport implementations generated and dispatched to by ``rosidl_typesupport_c``.
TYPESUPPORT_IMPLEMENTATIONS = (
    'rosidl_typesupport_fastrtps_c',
    'rosidl_typesupport_introspection_c',
)

#: Python extension modules generated; rclpy imports only the ``rosidl_typesupport_c`` one.
PYTHON_TYPESUPPORTS = ('rosidl_typesupport_c',)


@dataclass
class GeneratedSources:
    """Where the generated code of one package lies.

    Attributes
    ----------
    package : str
        Package name.
    out_dir : pathlib.Path
        Root of everything generated.
    msg_files : list of pathlib.Path
        The package's ``.msg`` files (absolute).
    idl_files : list of pathlib.Path
        ``<out_dir>/idl/msg/<Name>.idl``, one per message.
    type_description_files : list of pathlib.Path
        ``<out_dir>/type_description/msg/<Name>.json``, one per message.
    include_dirs : list of pathlib.Path
        Roots of the generated headers (``<out_dir>/rosidl_generator_c`` etc.).
    sources : dict
        Generator name (``rosidl_generator_c``, ...) to its C/C++ sources.
    python_package_dir : pathlib.Path
        ``<out_dir>/rosidl_generator_py/<package>``: holds ``msg/`` and the extension sources.
    dependencies : list of str
        Packages whose messages are used, dependencies first.
    """

    package: str
    out_dir: Path
    msg_files: List[Path]
    idl_files: List[Path] = field(default_factory=list)
    type_description_files: List[Path] = field(default_factory=list)
    include_dirs: List[Path] = field(default_factory=list)
    sources: Dict[str, List[Path]] = field(default_factory=dict)
    python_package_dir: Path = Path()
    dependencies: List[str] = field(default_factory=list)


def find_share(package: str, prefixes: Sequence[Path]) -> Path:
    """Return ``<prefix>/share/<package>`` from the first prefix that has its package.xml."""
    for prefix in prefixes:
        candidate = Path(prefix) / 'share' / package
        if (candidate / 'package.xml').is_file():
            return candidate
    raise InterfaceError(
        f"ROS package '{package}' not found under the share/ folders of "
        f"{', '.join(map(str, prefixes)) or 'no prefix'}; install its ros-* wheel or source a "
        'ROS 2 distribution')


def _write_args(path: Path, **arguments) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(arguments, indent=2), encoding='utf-8')
    return str(path)


def _visibility_header(template: Path, output: Path, package: str) -> None:
    text = template.read_text(encoding='utf-8')
    text = text.replace('@PROJECT_NAME@', package).replace('@PROJECT_NAME_UPPER@',
                                                           package.upper())
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(text, encoding='utf-8')


def _translate(package: str, package_dir: Path, msg_file: Path, idl_dir: Path) -> Path:
    """Translate one ``.msg`` to ``.idl``, turning adapter errors into one-line errors."""
    from rosidl_adapter.msg import convert_msg_to_idl

    relative = msg_file.relative_to(package_dir)
    quiet = io.StringIO()
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            return Path(convert_msg_to_idl(package_dir, package, relative, idl_dir))
    except Exception as exc:  # the adapter raises several unrelated exception types
        reason = ' '.join(str(exc).split()) or type(exc).__name__
        raise InterfaceError(f'{relative}: {reason}') from None


def generate_sources(
    package: str,
    package_dir: Path,
    msg_files: Sequence[Path],
    out_dir: Path,
    prefixes: Sequence[Path],
    dependencies: Sequence[str],
) -> GeneratedSources:
    """Generate the C, C typesupport and Python sources of a package's messages.

    Parameters
    ----------
    package : str
        Package name.
    package_dir : pathlib.Path
        Package root; ``msg_files`` lie below it (``msg/<Name>.msg``).
    msg_files : sequence of pathlib.Path
        The ``.msg`` files, already checked by :func:`rosidl_build.spec.validate_interfaces`.
    out_dir : pathlib.Path
        Output folder; emptied first.
    prefixes : sequence of pathlib.Path
        Install prefixes holding the generators and the dependency packages.
    dependencies : sequence of str
        Packages whose messages are used (from ``validate_interfaces``).

    Returns
    -------
    GeneratedSources
    """
    from rosidl_generator_c import generate_c
    from rosidl_generator_py import generate_py
    from rosidl_generator_type_description import generate_type_hash
    from rosidl_typesupport_c import generate_c as generate_typesupport_c
    from rosidl_typesupport_fastrtps_c import generate_typesupport_fastrtps_c
    from rosidl_typesupport_introspection_c import generate_c as generate_introspection_c

    package_dir = Path(package_dir).resolve()
    out_dir = Path(out_dir).resolve()
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    result = GeneratedSources(package=package, out_dir=out_dir,
                              msg_files=[Path(m).resolve() for m in msg_files],
                              dependencies=list(dependencies))

    idl_root = out_dir / 'idl'
    for msg_file in result.msg_files:
        result.idl_files.append(_translate(package, package_dir, msg_file, idl_root / 'msg'))
    idl_tuples = [f'{idl_root}:{p.relative_to(idl_root).as_posix()}' for p in result.idl_files]

    dep_shares = {dep: find_share(dep, prefixes) for dep in dependencies}
    ros_interface_dependencies = [
        f'{dep}:{idl}' for dep, share in dep_shares.items()
        for idl in sorted((share / 'msg').glob('*.idl'))]
    common = dict(package_name=package, idl_tuples=idl_tuples,
                  ros_interface_dependencies=ros_interface_dependencies,
                  target_dependencies=[])
    args_dir = out_dir / 'arguments'

    def templates(generator: str) -> Path:
        return find_share(generator, prefixes) / 'resource'

    # Type descriptions and RIHS01 hashes, needed by the C generator.
    hashes_dir = out_dir / 'type_description'
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet):
        generated = generate_type_hash(_write_args(
            args_dir / 'rosidl_generator_type_description.json', **common,
            output_dir=str(hashes_dir),
            template_dir=str(templates('rosidl_generator_type_description')),
            include_paths=[f'{dep}:{share}' for dep, share in dep_shares.items()]))
    result.type_description_files = sorted(Path(p) for p in generated)
    type_description_tuples = [
        f"msg/{p.stem}.idl:{p}" for p in result.type_description_files]

    def output(generator: str) -> Path:
        root = out_dir / generator
        result.include_dirs.append(root)
        return root / package

    # C structures, functions and type descriptions.
    c_out = output('rosidl_generator_c')
    _visibility_header(templates('rosidl_generator_c') /
                       'rosidl_generator_c__visibility_control.h.in',
                       c_out / 'msg' / 'rosidl_generator_c__visibility_control.h', package)
    generate_c(_write_args(
        args_dir / 'rosidl_generator_c.json', **common, output_dir=str(c_out),
        template_dir=str(templates('rosidl_generator_c')),
        type_description_tuples=type_description_tuples,
        ros_interface_files=[str(m) for m in result.msg_files]))
    result.sources['rosidl_generator_c'] = sorted((c_out / 'msg' / 'detail').glob('*.c'))

    # Fast DDS (CDR) serialization, in C++.
    fast_out = output('rosidl_typesupport_fastrtps_c')
    _visibility_header(templates('rosidl_typesupport_fastrtps_c') /
                       'rosidl_typesupport_fastrtps_c__visibility_control.h.in',
                       fast_out / 'msg' / 'rosidl_typesupport_fastrtps_c__visibility_control.h',
                       package)
    generate_typesupport_fastrtps_c(_write_args(
        args_dir / 'rosidl_typesupport_fastrtps_c.json', **common, output_dir=str(fast_out),
        template_dir=str(templates('rosidl_typesupport_fastrtps_c'))))
    result.sources['rosidl_typesupport_fastrtps_c'] = sorted(
        (fast_out / 'msg' / 'detail').glob('*.cpp'))

    # Introspection (used by dynamic typesupports and tools).
    intro_out = output('rosidl_typesupport_introspection_c')
    _visibility_header(
        templates('rosidl_typesupport_introspection_c') /
        'rosidl_typesupport_introspection_c__visibility_control.h.in',
        intro_out / 'msg' / 'rosidl_typesupport_introspection_c__visibility_control.h', package)
    generate_introspection_c(_write_args(
        args_dir / 'rosidl_typesupport_introspection_c.json', **common,
        output_dir=str(intro_out),
        template_dir=str(templates('rosidl_typesupport_introspection_c'))))
    result.sources['rosidl_typesupport_introspection_c'] = sorted(
        (intro_out / 'msg' / 'detail').glob('*.c'))

    # Dispatch from the C typesupport identifier to the implementations above.
    ts_out = output('rosidl_typesupport_c')
    generate_typesupport_c(_write_args(
        args_dir / 'rosidl_typesupport_c.json', **common, output_dir=str(ts_out),
        template_dir=str(templates('rosidl_typesupport_c'))),
        list(TYPESUPPORT_IMPLEMENTATIONS))
    result.sources['rosidl_typesupport_c'] = sorted((ts_out / 'msg').glob('*.cpp'))

    # Python classes, their C conversion functions and the extension module entry points.
    py_out = output('rosidl_generator_py')
    py_out.mkdir(parents=True, exist_ok=True)
    with contextlib.redirect_stdout(quiet):
        generate_py(_write_args(
            args_dir / 'rosidl_generator_py.json', **common, output_dir=str(py_out),
            template_dir=str(templates('rosidl_generator_py'))),
            list(PYTHON_TYPESUPPORTS))
    result.sources['rosidl_generator_py'] = sorted((py_out / 'msg').glob('*_s.c'))
    result.python_package_dir = py_out
    return result
