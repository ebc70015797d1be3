"""Parse and validate ROS 2 ``.msg`` files without importing any ROS package.

The checks mirror the grammar that ``rosidl_adapter`` accepts, but every error is a single line
that names the file, the line and the field, so a malformed interface fails the build with a
message that points at the fix. Types from other packages are resolved against the ``share/``
folders of the install prefixes that hold ROS packages (a virtual environment with the ``ros-*``
wheels, or a ROS 2 distribution such as ``/opt/ros/<distro>``).
"""

from dataclasses import dataclass, field
import importlib.util
import keyword
import math
import os
from pathlib import Path
import re
import sys
from typing import Dict, Iterable, List, Optional, Sequence, Set, Tuple

#: Primitive ``.msg`` types and the kind of value a constant or default of that type holds.
PRIMITIVE_TYPES: Dict[str, str] = {
    'bool': 'bool',
    'byte': 'int',
    'char': 'int',
    'float32': 'float',
    'float64': 'float',
    'int8': 'int',
    'uint8': 'int',
    'int16': 'int',
    'uint16': 'int',
    'int32': 'int',
    'uint32': 'int',
    'int64': 'int',
    'uint64': 'int',
    'string': 'str',
    'wstring': 'str',
}

#: Inclusive value ranges of the integer primitive types.
INTEGER_RANGES: Dict[str, Tuple[int, int]] = {
    'byte': (0, 255),
    'char': (0, 255),
    'int8': (-2**7, 2**7 - 1),
    'uint8': (0, 2**8 - 1),
    'int16': (-2**15, 2**15 - 1),
    'uint16': (0, 2**16 - 1),
    'int32': (-2**31, 2**31 - 1),
    'uint32': (0, 2**32 - 1),
    'int64': (-2**63, 2**63 - 1),
    'uint64': (0, 2**64 - 1),
}

# Same patterns as rosidl_adapter.parser.
_NAME_PATTERN = re.compile(r'^(?!.*__)(?!.*_$)[a-z][a-z0-9_]*$')
_MESSAGE_NAME_PATTERN = re.compile(r'^[A-Z][A-Za-z0-9]*$')
_CONSTANT_NAME_PATTERN = re.compile(r'^[A-Z]([A-Z0-9_]?[A-Z0-9]+)*$')
_TYPE_PATTERN = re.compile(
    r'^(?P<base>[A-Za-z][A-Za-z0-9_/]*)'
    r'(?:<=(?P<string_bound>[0-9]+))?'
    r'(?P<array>\[(?:(?P<upper><=)?(?P<size>[0-9]+))?\])?$')
_IDL_INCLUDE_PATTERN = re.compile(r'#include\s+"(?P<pkg>[a-z0-9_]+)/msg/(?P<name>\w+)\.idl"')


class InterfaceError(ValueError):
    """A malformed or unresolvable interface definition; ``str()`` is one line."""


@dataclass(frozen=True)
class FieldSpec:
    """One field of a message.

    Attributes
    ----------
    name : str
        Field name.
    type_string : str
        The type exactly as written, e.g. ``float64``, ``std_msgs/Header``, ``uint8[<=4]``.
    base_type : str
        Primitive type name, or ``pkg/Name`` for a message type.
    line : int
        1-based line number in the ``.msg`` file.
    """

    name: str
    type_string: str
    base_type: str
    line: int

    @property
    def is_primitive(self) -> bool:
        """Whether the base type is a primitive (not a message) type."""
        return self.base_type in PRIMITIVE_TYPES


@dataclass(frozen=True)
class ConstantSpec:
    """One constant of a message (``TYPE NAME=VALUE``)."""

    name: str
    type_string: str
    value: object
    line: int


@dataclass
class MessageSpec:
    """The parsed content of one ``.msg`` file."""

    package: str
    name: str
    path: Path
    fields: List[FieldSpec] = field(default_factory=list)
    constants: List[ConstantSpec] = field(default_factory=list)

    @property
    def full_name(self) -> str:
        """``pkg/Name`` of the message."""
        return f'{self.package}/{self.name}'


def _display(path: Path) -> str:
    """Return ``path`` relative to the working directory when it lies below it."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _error(path: Path, line: int, what: str, detail: str) -> InterfaceError:
    text = f'{_display(path)}:{line}: {what}: {detail}'
    return InterfaceError(' '.join(text.split()))


def _parse_value(kind: str, type_name: str, text: str) -> object:
    """Convert a constant or default value; raise ``ValueError`` with a short reason."""
    text = text.strip()
    if kind == 'str':
        if len(text) >= 2 and text[0] == text[-1] and text[0] in '\'"':
            return text[1:-1]
        return text
    if kind == 'bool':
        lowered = text.lower()
        if lowered in ('true', '1'):
            return True
        if lowered in ('false', '0'):
            return False
        raise ValueError(f'{text!r} is not a bool (true/false/1/0)')
    if kind == 'float':
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f'{text!r} is not a number') from None
        if type_name == 'float32' and math.isfinite(value) and abs(value) > 3.4028235e38:
            raise ValueError(f'{text!r} is out of range for float32')
        return value
    try:
        value = int(text, 0)
    except ValueError:
        raise ValueError(f'{text!r} is not an integer') from None
    low, high = INTEGER_RANGES[type_name]
    if not low <= value <= high:
        raise ValueError(f'{value} is out of range [{low}, {high}] for {type_name}')
    return value


def _parse_type(type_string: str, package: str) -> Tuple[str, bool]:
    """Return ``(base_type, is_array)`` for a type token, or raise ``ValueError``."""
    match = _TYPE_PATTERN.match(type_string)
    if match is None:
        raise ValueError(f'malformed type {type_string!r}')
    base = match.group('base')
    if match.group('array') is not None and match.group('upper') and not match.group('size'):
        raise ValueError(f'malformed array bound in {type_string!r}')
    if match.group('string_bound') is not None and base not in ('string', 'wstring'):
        raise ValueError(f'only string types take an upper bound, not {base!r}')
    if base in PRIMITIVE_TYPES:
        return base, match.group('array') is not None
    parts = base.split('/')
    if len(parts) == 3 and parts[1] == 'msg':
        parts = [parts[0], parts[2]]
    if len(parts) == 1:
        parts = [package, parts[0]]
    if len(parts) != 2 or not _NAME_PATTERN.match(parts[0]) or \
            not _MESSAGE_NAME_PATTERN.match(parts[1]):
        raise ValueError(f'unknown type {type_string!r}')
    return '/'.join(parts), match.group('array') is not None


def parse_msg_text(text: str, package: str, name: str, path: Path) -> MessageSpec:
    """Parse the text of a ``.msg`` file.

    Parameters
    ----------
    text : str
        File content.
    package : str
        Package the message belongs to (used for types written without a package).
    name : str
        Message name (the file stem).
    path : pathlib.Path
        File path, used in error messages only.

    Returns
    -------
    MessageSpec
        Fields and constants in file order. Types are not resolved here.

    Raises
    ------
    InterfaceError
        On the first syntax error, with file, line and field in a single line.
    """
    path = Path(path)
    if not _MESSAGE_NAME_PATTERN.match(name):
        raise _error(path, 1, f'message {name!r}',
                     'file name must be CamelCase (e.g. ActuatorState.msg)')
    spec = MessageSpec(package=package, name=name, path=path)
    seen: Dict[str, int] = {}
    for number, raw in enumerate(text.replace('\t', ' ').splitlines(), start=1):
        line = raw.split('#', 1)[0].strip()
        if not line:
            continue
        type_string, _, rest = line.partition(' ')
        rest = rest.strip()
        if not rest:
            raise _error(path, number, f'line {line!r}',
                         'expected "<type> <name>" or "<type> <NAME>=<value>"')
        if '=' in rest:
            const_name, _, value_text = rest.partition('=')
            const_name = const_name.strip()
            what = f'constant {const_name!r}'
            if type_string not in PRIMITIVE_TYPES:
                raise _error(path, number, what,
                             f'constants must have a primitive type, not {type_string!r}')
            if not _CONSTANT_NAME_PATTERN.match(const_name):
                raise _error(path, number, what,
                             'invalid name (use UPPER_CASE letters, digits, single underscores)')
            try:
                value = _parse_value(PRIMITIVE_TYPES[type_string], type_string, value_text)
            except ValueError as exc:
                raise _error(path, number, what, str(exc)) from None
            if const_name in seen:
                raise _error(path, number, what,
                             f'duplicate name (first defined on line {seen[const_name]})')
            seen[const_name] = number
            spec.constants.append(ConstantSpec(const_name, type_string, value, number))
            continue
        field_name, _, default_text = rest.partition(' ')
        what = f'field {field_name!r}'
        try:
            base_type, is_array = _parse_type(type_string, package)
        except ValueError as exc:
            raise _error(path, number, what, str(exc)) from None
        if not _NAME_PATTERN.match(field_name):
            raise _error(path, number, what,
                         'invalid name (use lower_case letters, digits, single underscores, '
                         'starting with a letter)')
        if keyword.iskeyword(field_name):
            raise _error(path, number, what, 'is a Python keyword')
        if field_name in seen:
            raise _error(path, number, what,
                         f'duplicate name (first defined on line {seen[field_name]})')
        if default_text.strip():
            if base_type not in PRIMITIVE_TYPES:
                raise _error(path, number, what, 'only primitive fields take a default value')
            if not is_array:
                try:
                    _parse_value(PRIMITIVE_TYPES[base_type], base_type, default_text)
                except ValueError as exc:
                    raise _error(path, number, what, f'bad default: {exc}') from None
        seen[field_name] = number
        spec.fields.append(FieldSpec(field_name, type_string, base_type, number))
    return spec


def parse_msg_file(path, package: str) -> MessageSpec:
    """Parse one ``.msg`` file; see :func:`parse_msg_text`."""
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as exc:
        raise InterfaceError(f'{_display(path)}: cannot read: {exc}') from None
    return parse_msg_text(text, package, path.stem, path)


def ros_prefixes(extra: Iterable[str] = ()) -> List[Path]:
    """Install prefixes that hold ROS packages, most specific first.

    Looks at ``extra``, ``AMENT_PREFIX_PATH``, the prefixes that the importable generator and
    interface packages were installed into (this finds pip's isolated build environment), and
    ``sys.prefix``. Only prefixes with a ``share/`` folder are returned.
    """
    candidates: List[Path] = [Path(p) for p in extra]
    candidates += [Path(p) for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
                   if p]
    for module in ('rosidl_generator_c', 'std_msgs', 'rclpy'):
        try:
            found = importlib.util.find_spec(module)
        except (ImportError, ValueError):
            found = None
        if found is not None and found.origin:
            # <prefix>/lib/pythonX.Y/site-packages/<module>/__init__.py
            candidates.append(Path(found.origin).resolve().parents[4])
    candidates.append(Path(sys.prefix))
    result: List[Path] = []
    for candidate in candidates:
        if (candidate / 'share').is_dir() and candidate not in result:
            result.append(candidate)
    return result


def find_interface_file(package: str, name: str, prefixes: Sequence[Path]) -> Optional[Path]:
    """Return ``share/<package>/msg/<name>.msg`` (or ``.idl``) from the first prefix with it."""
    for prefix in prefixes:
        for suffix in ('.msg', '.idl'):
            candidate = Path(prefix) / 'share' / package / 'msg' / (name + suffix)
            if candidate.is_file():
                return candidate
    return None


def _referenced_types(path: Path, package: str) -> List[str]:
    """Message types referenced by an installed ``.msg`` or ``.idl`` file (best effort)."""
    if path.suffix == '.idl':
        text = path.read_text(encoding='utf-8', errors='replace')
        return [f"{m.group('pkg')}/{m.group('name')}" for m in _IDL_INCLUDE_PATTERN.finditer(text)]
    try:
        spec = parse_msg_file(path, package)
    except InterfaceError:
        return []
    return [f.base_type for f in spec.fields if not f.is_primitive]


def validate_interfaces(
    msg_files: Sequence, package: str, prefixes: Optional[Sequence[Path]] = None,
) -> Tuple[List[MessageSpec], List[str]]:
    """Parse the package's ``.msg`` files and resolve every message type they use.

    Parameters
    ----------
    msg_files : sequence of path-like
        The package's ``.msg`` files.
    package : str
        The package name.
    prefixes : sequence of pathlib.Path, optional
        Install prefixes to resolve other packages' types in; default :func:`ros_prefixes`.

    Returns
    -------
    specs : list of MessageSpec
        One per file, in the given order.
    dependencies : list of str
        Every other package whose messages are used, directly or through other messages,
        sorted so that a package comes after the packages it depends on.

    Raises
    ------
    InterfaceError
        One line naming the file, line and field of the first problem found.
    """
    if prefixes is None:
        prefixes = ros_prefixes()
    if not _NAME_PATTERN.match(package):
        raise InterfaceError(f'invalid package name {package!r}')
    specs = [parse_msg_file(path, package) for path in msg_files]
    local = {spec.name: spec for spec in specs}
    if len(local) != len(specs):
        raise InterfaceError(f'{package}: two .msg files define the same message name')
    # Direct references: unknown types are errors that name the field.
    pending: List[str] = []
    for spec in specs:
        for fld in spec.fields:
            if fld.is_primitive:
                continue
            dep_package, dep_name = fld.base_type.split('/')
            if dep_package == package:
                if dep_name not in local:
                    raise _error(spec.path, fld.line, f'field {fld.name!r}',
                                 f'unknown type {fld.type_string!r} (no {dep_name}.msg in this '
                                 f'package)')
                continue
            if find_interface_file(dep_package, dep_name, prefixes) is None:
                share_dirs = [p / 'share' for p in prefixes
                              if (p / 'share' / dep_package).is_dir()]
                reason = (f"package '{dep_package}' has no message '{dep_name}'" if share_dirs
                          else f"package '{dep_package}' not found under "
                               f"{', '.join(str(p / 'share') for p in prefixes) or 'no prefix'}")
                raise _error(spec.path, fld.line, f'field {fld.name!r}',
                             f'unknown type {fld.type_string!r} ({reason})')
            pending.append(fld.base_type)
    # Transitive closure over installed packages, ordered dependencies-first.
    edges: Dict[str, Set[str]] = {}
    seen_types: Set[str] = set()
    while pending:
        full = pending.pop()
        if full in seen_types:
            continue
        seen_types.add(full)
        dep_package, dep_name = full.split('/')
        edges.setdefault(dep_package, set())
        path = find_interface_file(dep_package, dep_name, prefixes)
        if path is None:
            raise InterfaceError(f'{full}: not found under the share/ folders of '
                                 f"{', '.join(map(str, prefixes))}")
        for ref in _referenced_types(path, dep_package):
            ref_package = ref.split('/')[0]
            if ref_package != dep_package:
                edges[dep_package].add(ref_package)
            pending.append(ref)
    ordered: List[str] = []

    def visit(name: str, stack: Tuple[str, ...] = ()) -> None:
        if name in ordered or name in stack:
            return
        for child in sorted(edges.get(name, ())):
            visit(child, stack + (name,))
        ordered.append(name)

    for name in sorted(edges):
        visit(name)
    return specs, ordered
