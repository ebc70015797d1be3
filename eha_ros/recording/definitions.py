"""What a recording is made of: the MCAP profile and encodings of rosbag2's layout, the errors
of every reader, the ``ros2msg`` message definitions and type hashes, the QoS as rosbag2
serializes it, and the counting of lost messages from publication sequence numbers.

No ROS imports: the ``.msg`` and type-description files are read from
``<prefix>/share/<pkg>/msg/``.
"""

from __future__ import annotations

from itertools import repeat
import json
import os
from pathlib import Path
import sys
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence

import yaml

from eha_ros.graph import normalize_type

__all__ = ['PROFILE', 'SCHEMA_ENCODING', 'MESSAGE_ENCODING', 'RUN_METADATA_NAME',
           'ROSBAG2_METADATA_NAME', 'ROSBAG2_METADATA_VERSION', 'MCAP_MAGIC',
           'PROGRESS_METADATA_NAME', 'MESSAGE_RECORD_OVERHEAD', 'RecordingError',
           'NotMcapError', 'TruncatedError', 'CorruptError', 'MissingTopicError',
           'message_definition', 'type_hash', 'qos_profile_dict', 'qos_profiles_yaml',
           'count_sequence_gaps', 'SequenceGapCounter', 'describe_source']

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
#: Name of rosbag2's metadata record (key ``serialized_metadata``).
ROSBAG2_METADATA_NAME = 'rosbag2'
#: Name of this package's metadata record: lost messages and run info.
RUN_METADATA_NAME = 'eha_ros'
#: Name of the records a writer adds after each flushed chunk (lost and recorded so far), so a
#: killed recorder's file still says what it had lost (``eha-recover`` reads the last one).
PROGRESS_METADATA_NAME = 'eha_ros_progress'
#: Version of rosbag2's bag metadata written into ``serialized_metadata`` (Jazzy, Kilted).
ROSBAG2_METADATA_VERSION = 9

MCAP_MAGIC = b'\x89MCAP0\r\n'
_DEFINITION_SEPARATOR = '=' * 80
_PRIMITIVE_TYPES = frozenset((
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'))
#: rmw's "infinite" duration, as rosbag2 writes it: {sec: 2**63 // 1e9, nsec: remainder}.
_INFINITE = {'sec': 9223372036, 'nsec': 854775807}
#: Bytes a message adds to a chunk besides its data (opcode, length, channel, sequence, times).
MESSAGE_RECORD_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8


class RecordingError(Exception):
    """A recording cannot be read (base class)."""


class NotMcapError(RecordingError):
    """The input is not an MCAP file."""


class TruncatedError(RecordingError):
    """The file ends before its footer (a writer was killed, or the file was cut)."""


class MissingTopicError(RecordingError, KeyError):
    """A recording has no channel on the topic asked for."""

    def __str__(self):  # the message as given, not KeyError's quoted repr
        return str(self.args[0]) if self.args else ''


class CorruptError(RecordingError):
    """A record of the file is damaged (bad CRC, undecodable chunk or message)."""


# --- message definitions and type hashes ----------------------------------------------------

def _prefixes() -> List[Path]:
    """Install prefixes to look for ``share/<pkg>``: ``AMENT_PREFIX_PATH``, then ``sys.prefix``."""
    entries = os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) + [sys.prefix]
    return list(dict.fromkeys(Path(entry) for entry in entries if entry))


def _interface_file(pkg: str, name: str, suffix: str) -> Optional[Path]:
    for prefix in _prefixes():
        path = prefix / 'share' / pkg / 'msg' / f'{name}{suffix}'
        if path.is_file():
            return path
    return None


def _msg_text(pkg: str, name: str) -> str:
    path = _interface_file(pkg, name, '.msg')
    if path is None:
        where = ', '.join(str(p / 'share' / pkg / 'msg') for p in _prefixes())
        raise ValueError(f'no {name}.msg of package {pkg} in {where}')
    return path.read_text(encoding='utf-8')


def _msg_dependencies(pkg: str, text: str) -> List[str]:
    """Types ``pkg/Type`` used by the fields of a ``.msg`` text, in order of first use."""
    deps: List[str] = []
    for line in text.splitlines():
        words = line.split()
        if not words or words[0].startswith('#'):
            continue
        field_type = words[0].split('[')[0].split('<=')[0]
        if field_type not in _PRIMITIVE_TYPES:
            parts = field_type.split('/')
            deps.append(f'{parts[0]}/{parts[-1]}' if len(parts) > 1 else f'{pkg}/{field_type}')
    return list(dict.fromkeys(deps))


def message_definition(type_name: str) -> str:
    """Full ``ros2msg`` schema text of a message type, as rosbag2 writes it into MCAP.

    The type's ``.msg`` text, then for every type it depends on (recursively, depth first, each
    once): a newline, a line of 80 ``=``, a line ``MSG: pkg/Type`` and that type's ``.msg``
    text. The ``.msg`` files are read from ``<prefix>/share/<pkg>/msg/``.

    Parameters
    ----------
    type_name : str
        ``pkg/msg/Type`` or ``pkg/Type``.

    Raises
    ------
    ValueError
        If a ``.msg`` file of the type or of a dependency is not installed.
    """
    pkg, _, name = normalize_type(type_name).split('/')
    root = _msg_text(pkg, name)
    parts = [root]
    seen = {f'{pkg}/{name}'}

    def append(dep_pkg: str, text: str) -> None:
        for dep in sorted(_msg_dependencies(dep_pkg, text)):
            if dep in seen:
                continue
            seen.add(dep)
            d_pkg, d_name = dep.split('/')
            d_text = _msg_text(d_pkg, d_name)
            parts.append(f'\n{_DEFINITION_SEPARATOR}\nMSG: {dep}\n{d_text}')
            append(d_pkg, d_text)

    append(pkg, root)
    return ''.join(parts)


def type_hash(type_name: str) -> str:
    """``RIHS01_<sha256>`` type hash of a message type, from its installed ``.json`` type
    description; ``''`` where none is installed."""
    pkg, _, name = normalize_type(type_name).split('/')
    path = _interface_file(pkg, name, '.json')
    if path is None:
        return ''
    try:
        for entry in json.loads(path.read_text(encoding='utf-8')).get('type_hashes', ()):
            if entry.get('type_name') == f'{pkg}/msg/{name}':
                return str(entry.get('hash_string', ''))
    except (OSError, ValueError, AttributeError):
        pass
    return ''


# --- QoS as rosbag2 serializes it -----------------------------------------------------------

def _duration(value) -> Dict[str, int]:
    if isinstance(value, Mapping):
        return {'sec': int(value['sec']), 'nsec': int(value['nsec'])}
    ns = value if isinstance(value, int) else int(getattr(value, 'nanoseconds', 0))
    if ns >= 2**63 - 1 or ns < 0:
        return dict(_INFINITE)
    sec, nsec = divmod(ns, 1_000_000_000)
    return {'sec': sec, 'nsec': nsec}


def _policy(value) -> str:
    """An rclpy QoS policy enum (or a string) as ``rmw_qos_*_policy_to_str`` spells it."""
    return getattr(value, 'name', str(value)).lower()


def qos_profile_dict(qos=None) -> Dict[str, Any]:
    """One QoS profile in rosbag2's YAML layout (``offered_qos_profiles`` entries).

    Parameters
    ----------
    qos : rclpy.qos.QoSProfile or dict, optional
        A profile (e.g. ``TopicEndpointInfo.qos_profile`` of a discovered publisher) or a dict
        already in this layout; default: the graph's QoS (reliable, keep last
        ``graph.QOS_DEPTH``, volatile).
    """
    if qos is None:
        from eha_ros import graph
        return {'history': graph.QOS_HISTORY, 'depth': graph.QOS_DEPTH,
                'reliability': graph.QOS_RELIABILITY, 'durability': graph.QOS_DURABILITY,
                'deadline': dict(_INFINITE), 'lifespan': dict(_INFINITE),
                'liveliness': 'automatic', 'liveliness_lease_duration': dict(_INFINITE),
                'avoid_ros_namespace_conventions': False}
    if isinstance(qos, Mapping):
        durations = ('deadline', 'lifespan', 'liveliness_lease_duration')
        return {k: _duration(v) if k in durations else v for k, v in qos.items()}
    return {'history': _policy(qos.history), 'depth': int(qos.depth),
            'reliability': _policy(qos.reliability), 'durability': _policy(qos.durability),
            'deadline': _duration(qos.deadline), 'lifespan': _duration(qos.lifespan),
            'liveliness': _policy(qos.liveliness),
            'liveliness_lease_duration': _duration(qos.liveliness_lease_duration),
            'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions)}


def qos_profiles_yaml(profiles: Optional[Sequence] = None) -> str:
    """``offered_qos_profiles`` channel metadata: a YAML list of :func:`qos_profile_dict`."""
    profiles = [None] if profiles is None else profiles
    return yaml.safe_dump([qos_profile_dict(p) for p in profiles], sort_keys=False,
                          default_flow_style=False)


# --- lost messages ----------------------------------------------------------------------------

class SequenceGapCounter:
    """Count messages lost between a publisher and a subscriber from publication sequence
    numbers.

    DDS numbers every sample a writer (publisher) sends, 1, 2, 3, ...; a subscriber that takes
    sample ``n`` after sample ``m`` of the same writer missed ``n - m - 1`` samples (dropped by
    the publisher's or the subscriber's history, or the network). Samples published before the
    first one taken are not counted as lost (the subscriber had not matched yet) but are
    reported as ``missed_at_start``. A sequence number at or below the last one (a duplicate,
    or a restarted publisher reusing its identity) restarts the count for that publisher.
    """

    def __init__(self):
        self._last: Dict[Any, int] = {}
        self.lost = 0
        self.received = 0
        self.missed_at_start = 0
        self.publishers = 0

    def add(self, sequence: Optional[int], publisher: Any = None) -> int:
        """Account for one received message; returns how many were lost just before it."""
        self.received += 1
        if sequence is None:
            return 0
        last = self._last.get(publisher)
        self._last[publisher] = sequence
        if last is None:
            self.publishers += 1
            self.missed_at_start += max(0, sequence - 1)
            return 0
        gap = max(0, sequence - last - 1)
        self.lost += gap
        return gap


def count_sequence_gaps(sequences: Iterable[Optional[int]],
                        publishers: Optional[Iterable[Any]] = None) -> int:
    """Messages lost in a stream of publication sequence numbers (see
    :class:`SequenceGapCounter`); ``publishers`` gives each message's publisher id."""
    counter = SequenceGapCounter()
    for seq, pub in zip(sequences, repeat(None) if publishers is None else publishers):
        counter.add(seq, pub)
    return counter.lost


def describe_source(source) -> str:
    """How error messages name a recording: its path, or ``input`` for bytes and streams."""
    return str(source) if isinstance(source, (str, os.PathLike)) else 'input'
