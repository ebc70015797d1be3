"""Write and read MCAP recordings in the layout rosbag2's MCAP storage uses.

Layout written by :class:`McapWriter`:

* profile ``ros2``; one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``:
  the type's ``.msg`` text followed, for every (nested) dependency once, by a line of 80 ``=``,
  ``MSG: pkg/Type`` and that type's ``.msg`` text (:func:`message_definition`; the ``.msg``
  files come from ``<prefix>/share/<pkg>/msg/``);
* one channel per topic, message encoding ``cdr``, with the channel metadata rosbag2 writes:
  ``offered_qos_profiles`` (YAML list of the publishers' QoS) and ``topic_type_hash``
  (``RIHS01_...`` from the installed type description ``.json``);
* messages with log and publish times in integer nanoseconds and the publisher's sequence
  number (modulo 2**32);
* zstd (or lz4) compressed chunks, each written out and flushed when it is closed, so that a
  writer killed mid-way leaves a file readable up to its last complete chunk;
* at close, a metadata record ``rosbag2`` (key ``serialized_metadata``: the bag's metadata as
  YAML, version 9) and a metadata record ``eha_ros`` (lost messages per topic, run info), then
  the summary section and footer.

:class:`McapReader` reads such files (and rosbag2's) sequentially, without the summary
section, so a truncated file yields every message up to its last complete chunk;
:func:`load_topic_arrays` loads one topic into numpy arrays for analysis. Neither needs
``rclpy``: messages are decoded from the schemas in the file (``mcap_ros2``).
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
import struct
import sys
import time
from typing import (Any, BinaryIO, Dict, Iterable, Iterator, List, Mapping, NamedTuple,
                    Optional, Sequence, Union)

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (Channel, Chunk, Footer, Header, Message, Metadata, Schema)
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer
import numpy as np
import yaml

from eha_ros.recording.topics import normalize_type

__all__ = ['PROFILE', 'SCHEMA_ENCODING', 'MESSAGE_ENCODING', 'RUN_METADATA_NAME',
           'ROSBAG2_METADATA_NAME', 'RecordingError', 'NotMcapError', 'TruncatedError',
           'CorruptError', 'MissingTopicError', 'message_definition', 'type_hash',
           'qos_profile_dict', 'qos_profiles_yaml', 'McapWriter', 'RecordedMessage',
           'ChannelInfo', 'RecordingInfo',
           'McapReader', 'scan', 'iter_decoded', 'load_topic_arrays', 'message_to_dict',
           'flatten', 'count_sequence_gaps', 'SequenceGapCounter']

PROFILE = 'ros2'
SCHEMA_ENCODING = 'ros2msg'
MESSAGE_ENCODING = 'cdr'
#: Name of rosbag2's metadata record (key ``serialized_metadata``).
ROSBAG2_METADATA_NAME = 'rosbag2'
#: Name of this package's metadata record: lost messages and run info.
RUN_METADATA_NAME = 'eha_ros'
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
_MESSAGE_RECORD_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8


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
    out: List[Path] = []
    for entry in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) + [sys.prefix]:
        if entry and Path(entry) not in out:
            out.append(Path(entry))
    return out


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
        line = line.strip()
        if not line or line.startswith('#'):
            continue
        field_type = line.split()[0]
        field_type = field_type.split('[')[0].split('<=')[0]
        if field_type in _PRIMITIVE_TYPES:
            continue
        if '/' in field_type:
            parts = field_type.split('/')
            dep = f'{parts[0]}/{parts[-1]}'
        else:
            dep = f'{pkg}/{field_type}'
        if dep not in deps:
            deps.append(dep)
    return deps


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
        data = json.loads(path.read_text(encoding='utf-8'))
        wanted = f'{pkg}/msg/{name}'
        for entry in data.get('type_hashes', ()):
            if entry.get('type_name') == wanted:
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
    if isinstance(value, str):
        return value.lower()
    return getattr(value, 'name', str(value)).lower()


def qos_profile_dict(qos=None) -> Dict[str, Any]:
    """One QoS profile in rosbag2's YAML layout (``offered_qos_profiles`` entries).

    Parameters
    ----------
    qos : rclpy.qos.QoSProfile or dict, optional
        A profile (e.g. ``TopicEndpointInfo.qos_profile`` of a discovered publisher) or a dict
        already in this layout; default: the graph's QoS (reliable, keep last ``topics.QOS_DEPTH``, volatile).
    """
    if qos is None:
        from eha_ros.recording import topics
        return {'history': topics.QOS_HISTORY, 'depth': topics.QOS_DEPTH,
                'reliability': topics.QOS_RELIABILITY, 'durability': topics.QOS_DURABILITY,
                'deadline': dict(_INFINITE), 'lifespan': dict(_INFINITE),
                'liveliness': 'automatic', 'liveliness_lease_duration': dict(_INFINITE),
                'avoid_ros_namespace_conventions': False}
    if isinstance(qos, Mapping):
        out = dict(qos)
        for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
            if key in out:
                out[key] = _duration(out[key])
        return out
    return {'history': _policy(qos.history), 'depth': int(qos.depth),
            'reliability': _policy(qos.reliability), 'durability': _policy(qos.durability),
            'deadline': _duration(qos.deadline), 'lifespan': _duration(qos.lifespan),
            'liveliness': _policy(qos.liveliness),
            'liveliness_lease_duration': _duration(qos.liveliness_lease_duration),
            'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions)}


def qos_profiles_yaml(profiles: Optional[Sequence] = None) -> str:
    """``offered_qos_profiles`` channel metadata: a YAML list of :func:`qos_profile_dict`."""
    if profiles is None:
        profiles = [None]
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
        gap = sequence - last - 1
        if gap > 0:
            self.lost += gap
            return gap
        return 0


def count_sequence_gaps(sequences: Iterable[Optional[int]],
                        publishers: Optional[Iterable[Any]] = None) -> int:
    """Messages lost in a stream of publication sequence numbers (see
    :class:`SequenceGapCounter`); ``publishers`` gives each message's publisher id."""
    counter = SequenceGapCounter()
    sequences = list(sequences)
    pubs = list(publishers) if publishers is not None else [None] * len(sequences)
    for seq, pub in zip(sequences, pubs):
        counter.add(seq, pub)
    return counter.lost


# --- writer -----------------------------------------------------------------------------------

def _compression(name: str) -> CompressionType:
    name = (name or 'none').lower()
    if name == 'auto':
        for candidate, module in (('zstd', 'zstandard'), ('lz4', 'lz4.frame')):
            try:
                __import__(module)
                return _compression(candidate)
            except ImportError:
                continue
        return CompressionType.NONE
    table = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4,
             'none': CompressionType.NONE, '': CompressionType.NONE}
    if name not in table:
        raise ValueError(f'unknown compression {name!r} (zstd, lz4, none or auto)')
    return table[name]


def _message_type_name(msg) -> str:
    """``pkg/msg/Type`` of a generated rclpy message instance."""
    cls = type(msg)
    return f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"


class McapWriter:
    """Write a recording: a context manager around ``mcap.writer.Writer``.

    Parameters
    ----------
    output : str, os.PathLike or binary stream
        File to create, or a writable binary stream (e.g. ``io.BytesIO``; left open).
    chunk_size : int
        Uncompressed bytes of messages per chunk (default 1 MiB).
    compression : {'auto', 'zstd', 'lz4', 'none'}
        Chunk compression; ``auto``: zstd, else lz4, else none.
    flush_interval_s : float, optional
        Also close the chunk in progress when it is older than this, so that a killed writer
        loses at most this much (``None``: only full chunks are written out).
    overwrite : bool
        Replace an existing file; by default an existing ``output`` raises ``FileExistsError``.
    run_info : dict, optional
        Run information stored in the ``eha_ros`` metadata record (JSON-serialisable).

    Examples
    --------
    >>> buf = io.BytesIO()
    >>> with McapWriter(buf) as writer:                       # doctest: +SKIP
    ...     writer.add_topic('/eha/state', 'eha_ros/msg/ActuatorState')
    ...     writer.write('/eha/state', cdr_bytes, log_time_ns=1_000_000)
    """

    def __init__(self, output: Union[str, os.PathLike, BinaryIO], *,
                 chunk_size: int = 1 << 20, compression: str = 'auto',
                 flush_interval_s: Optional[float] = None, overwrite: bool = False,
                 run_info: Optional[Mapping[str, Any]] = None):
        if chunk_size <= 0:
            raise ValueError(f'chunk_size must be positive, got {chunk_size}')
        self._compression = _compression(compression)
        if isinstance(output, (str, os.PathLike)):
            self.path: Optional[Path] = Path(output)
            self._stream = open(self.path, 'wb' if overwrite else 'xb')
            self._owns_stream = True
        else:
            self.path = None
            self._stream = output
            self._owns_stream = False
        self._chunk_size = int(chunk_size)
        self._flush_interval_s = flush_interval_s
        # The mcap writer never closes a chunk by itself: this class does (see write()).
        self._writer = Writer(self._stream, chunk_size=2**62, compression=self._compression)
        from eha_ros import __version__
        self._writer.start(profile=PROFILE, library=f'eha_ros {__version__}')
        self._schemas: Dict[str, int] = {}
        self._channels: Dict[str, int] = {}
        self._topic_meta: Dict[str, Dict[str, Any]] = {}
        self.message_counts: Dict[str, int] = {}
        self.lost_counts: Dict[str, int] = {}
        self.run_info: Dict[str, Any] = dict(run_info or {})
        self._pending_bytes = 0
        self._chunk_opened = time.monotonic()
        self._first_log_ns: Optional[int] = None
        self._last_log_ns: Optional[int] = None
        self.chunks_written = 0
        self.closed = False

    # context manager
    def __enter__(self) -> 'McapWriter':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def topics(self) -> Dict[str, str]:
        """Registered topics and their types."""
        return {t: m['type'] for t, m in self._topic_meta.items()}

    def add_topic(self, topic: str, type_name: str, *,
                  offered_qos_profiles: Union[None, str, Sequence] = None,
                  topic_type_hash: Optional[str] = None,
                  definition: Optional[str] = None) -> int:
        """Register a topic (MCAP channel) and, once per type, its schema; returns the channel id.

        Parameters
        ----------
        topic : str
            Topic name.
        type_name : str
            ``pkg/msg/Type``.
        offered_qos_profiles : str or list, optional
            QoS of the topic's publishers: YAML text, or profiles for :func:`qos_profiles_yaml`;
            default the graph's QoS.
        topic_type_hash : str, optional
            Default: from the installed type description (:func:`type_hash`).
        definition : str, optional
            ``ros2msg`` schema text; default :func:`message_definition`.
        """
        if topic in self._channels:
            raise ValueError(f'topic {topic} is already registered')
        type_name = normalize_type(type_name)
        if type_name not in self._schemas:
            text = definition if definition is not None else message_definition(type_name)
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding=SCHEMA_ENCODING, data=text.encode('utf-8'))
        if isinstance(offered_qos_profiles, str):
            qos_yaml = offered_qos_profiles
        else:
            qos_yaml = qos_profiles_yaml(offered_qos_profiles)
        hash_string = type_hash(type_name) if topic_type_hash is None else topic_type_hash
        channel_id = self._writer.register_channel(
            topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=self._schemas[type_name],
            metadata={'offered_qos_profiles': qos_yaml, 'topic_type_hash': hash_string})
        self._channels[topic] = channel_id
        self._topic_meta[topic] = {'type': type_name, 'qos': qos_yaml, 'hash': hash_string}
        self.message_counts.setdefault(topic, 0)
        return channel_id

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: Optional[int] = None, sequence: int = 0) -> None:
        """Append one serialized (CDR) message of a registered topic.

        Parameters
        ----------
        log_time_ns, publish_time_ns : int
            Reception and publication times, ns (``publish_time_ns`` defaults to the log time).
        sequence : int
            Publisher's sequence number (stored modulo 2**32).
        """
        channel_id = self._channels.get(topic)
        if channel_id is None:
            raise KeyError(f'topic {topic} is not registered (add_topic first)')
        log_time_ns = int(log_time_ns)
        self._writer.add_message(
            channel_id=channel_id, log_time=log_time_ns, data=bytes(data),
            publish_time=log_time_ns if publish_time_ns is None else int(publish_time_ns),
            sequence=int(sequence) & 0xFFFFFFFF)
        self.message_counts[topic] += 1
        if self._first_log_ns is None or log_time_ns < self._first_log_ns:
            self._first_log_ns = log_time_ns
        if self._last_log_ns is None or log_time_ns > self._last_log_ns:
            self._last_log_ns = log_time_ns
        if self._pending_bytes == 0:
            self._chunk_opened = time.monotonic()
        self._pending_bytes += len(data) + _MESSAGE_RECORD_OVERHEAD
        if self._pending_bytes >= self._chunk_size or (
                self._flush_interval_s is not None
                and time.monotonic() - self._chunk_opened >= self._flush_interval_s):
            self.flush()

    def write_message(self, topic: str, msg, log_time_ns: int,
                      publish_time_ns: Optional[int] = None, sequence: int = 0) -> None:
        """Serialize an rclpy message (needs ``rclpy``) and :meth:`write` it; registers the
        topic with the message's type on first use."""
        from rclpy.serialization import serialize_message

        if topic not in self._channels:
            self.add_topic(topic, _message_type_name(msg))
        self.write(topic, serialize_message(msg), log_time_ns, publish_time_ns, sequence)

    def flush(self) -> None:
        """Close the chunk in progress and write everything out (no ``fsync``)."""
        if self._pending_bytes:
            self.chunks_written += 1
        self._writer.flush()
        self._pending_bytes = 0
        self._chunk_opened = time.monotonic()

    def rosbag2_metadata(self) -> Dict[str, Any]:
        """The bag metadata rosbag2 stores in ``serialized_metadata`` (version 9 layout)."""
        start = self._first_log_ns or 0
        duration = (self._last_log_ns - start) if self._last_log_ns is not None else 0
        total = sum(self.message_counts.values())
        name = self.path.name if self.path is not None else ''
        topics = []
        for topic, meta in self._topic_meta.items():
            topics.append({
                'topic_metadata': {
                    'name': topic, 'type': meta['type'],
                    'serialization_format': MESSAGE_ENCODING,
                    'offered_qos_profiles': yaml.safe_load(meta['qos']) or [],
                    'type_description_hash': meta['hash']},
                'message_count': self.message_counts.get(topic, 0)})
        return {
            'version': ROSBAG2_METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': total,
            'topics_with_message_count': topics,
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [name],
            'files': [{'path': name, 'starting_time': {'nanoseconds_since_epoch': start},
                       'duration': {'nanoseconds': duration}, 'message_count': total}],
            'custom_data': {},
            'ros_distro': os.environ.get('ROS_DISTRO', 'kilted'),
        }

    def close(self) -> None:
        """Write the metadata records, the summary and the footer; close an owned file."""
        if self.closed:
            return
        self.closed = True
        try:
            self.flush()
            self._writer.add_metadata(ROSBAG2_METADATA_NAME, {
                'serialized_metadata': yaml.safe_dump(self.rosbag2_metadata(), sort_keys=False,
                                                       default_flow_style=False)})
            lost = {t: int(self.lost_counts.get(t, 0)) for t in self._topic_meta}
            lost.update({t: int(n) for t, n in self.lost_counts.items()})
            self._writer.add_metadata(RUN_METADATA_NAME, {
                'lost_messages': json.dumps(lost, sort_keys=True),
                'recorded_messages': json.dumps(self.message_counts, sort_keys=True),
                'run': json.dumps(self.run_info, sort_keys=True, default=str),
            })
            self._writer.finish()
            self._stream.flush()
        finally:
            if self._owns_stream:
                self._stream.close()


# --- reader -----------------------------------------------------------------------------------

class RecordedMessage(NamedTuple):
    """One message of a recording."""

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes
    message: Any  # decoded message (None when not decoded)


class ChannelInfo(NamedTuple):
    """One topic of a recording."""

    id: int
    topic: str
    type_name: str
    message_encoding: str
    metadata: Dict[str, str]
    schema_encoding: str
    schema_text: str


class RecordingInfo(NamedTuple):
    """What :func:`scan` found in a recording."""

    channels: Dict[str, ChannelInfo]
    message_counts: Dict[str, int]
    first_log_ns: Optional[int]
    last_log_ns: Optional[int]
    metadata: Dict[str, Dict[str, str]]
    chunks: int
    complete: bool
    problem: Optional[str]

    @property
    def topics(self) -> Dict[str, str]:
        """Topics and their types."""
        return {t: c.type_name for t, c in self.channels.items()}

    def lost_messages(self) -> Dict[str, int]:
        """Lost messages per topic from the ``eha_ros`` metadata record ({} if absent)."""
        raw = self.metadata.get(RUN_METADATA_NAME, {}).get('lost_messages')
        return {str(k): int(v) for k, v in json.loads(raw).items()} if raw else {}

    def run_info(self) -> Dict[str, Any]:
        """Run information from the ``eha_ros`` metadata record ({} if absent)."""
        raw = self.metadata.get(RUN_METADATA_NAME, {}).get('run')
        return json.loads(raw) if raw else {}

    def rosbag2_metadata(self) -> Dict[str, Any]:
        """rosbag2's ``serialized_metadata`` parsed ({} if absent)."""
        raw = self.metadata.get(ROSBAG2_METADATA_NAME, {}).get('serialized_metadata')
        return yaml.safe_load(raw) if raw else {}


_RECORD_READERS = {
    Opcode.HEADER: Header.read, Opcode.FOOTER: Footer.read, Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read, Opcode.CHUNK: Chunk.read, Opcode.METADATA: Metadata.read,
}


def _describe(source) -> str:
    return str(source) if isinstance(source, (str, os.PathLike)) else 'input'


class McapReader:
    """Read the messages of a recording in file order: an iterator of :class:`RecordedMessage`.

    The file is read sequentially (the summary section is not needed), so a file whose writer
    was killed, or that was cut, yields every message up to its last complete chunk.

    Parameters
    ----------
    source : str, os.PathLike, bytes or binary stream
        The recording. A stream must be at the start of the file (it is rewound for every
        iteration when seekable).
    topics : iterable of str, optional
        Only messages of these topics.
    decode : bool
        Decode messages (``mcap_ros2``) into ``RecordedMessage.message``.
    strict : bool
        Raise :class:`TruncatedError` / :class:`CorruptError` where the file ends early or is
        damaged; by default iteration stops there and :attr:`problem` says why.

    Attributes
    ----------
    channels : dict
        ``topic -> ChannelInfo`` seen so far.
    metadata : dict
        ``name -> {key: value}`` of the metadata records seen so far.
    complete : bool
        Whether the last iteration reached the footer.
    problem : str or None
        Why the last iteration stopped early.

    Raises
    ------
    NotMcapError
        If the input does not start with the MCAP magic bytes.
    """

    def __init__(self, source, *, topics: Optional[Iterable[str]] = None, decode: bool = True,
                 strict: bool = False):
        self._source = source
        self._topics = set(topics) if topics is not None else None
        self._decode = decode
        self.strict = strict
        self.channels: Dict[str, ChannelInfo] = {}
        self.metadata: Dict[str, Dict[str, str]] = {}
        self.complete = False
        self.problem: Optional[str] = None
        self.chunks = 0
        self._decoders: Dict[int, Any] = {}

    def __iter__(self) -> Iterator[RecordedMessage]:
        return self._messages()

    # -- low level
    def _open(self):
        src = self._source
        if isinstance(src, (bytes, bytearray, memoryview)):
            return io.BytesIO(bytes(src)), True, len(src)
        if isinstance(src, (str, os.PathLike)):
            handle = open(src, 'rb')
            return handle, True, os.fstat(handle.fileno()).st_size
        if hasattr(src, 'seek') and getattr(src, 'seekable', lambda: False)():
            src.seek(0)
            end = src.seek(0, io.SEEK_END)
            src.seek(0)
            return src, False, end
        return src, False, None

    def _stop(self, exc_type, message: str):
        self.problem = message
        if self.strict:
            raise exc_type(message)

    def _records(self) -> Iterator[Any]:
        """Top-level records in file order; stops (or raises) at truncation or damage."""
        stream, owned, size = self._open()
        self.complete = False
        self.problem = None
        self.chunks = 0
        try:
            magic = stream.read(len(MCAP_MAGIC))
            if magic != MCAP_MAGIC:
                if 0 < len(magic) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(magic):
                    self._stop(TruncatedError, f'{_describe(self._source)}: file ends within '
                               'its MCAP magic bytes (truncated)')
                    return
                what = 'empty file' if not magic else 'no MCAP magic bytes at the start'
                raise NotMcapError(f'{_describe(self._source)}: not an MCAP file ({what})')
            offset = len(MCAP_MAGIC)
            while True:
                head = stream.read(9)
                if len(head) < 9:
                    self._stop(TruncatedError, f'{_describe(self._source)}: file ends at byte '
                               f'{offset + len(head)} before its footer (truncated)')
                    return
                opcode, length = struct.unpack('<BQ', head)
                if size is not None and offset + 9 + length > size:
                    self._stop(TruncatedError, f'{_describe(self._source)}: record at byte '
                               f'{offset} runs past the end of the file (truncated)')
                    return
                if length > 1 << 34:
                    self._stop(CorruptError, f'{_describe(self._source)}: record at byte '
                               f'{offset} claims {length} bytes (corrupt)')
                    return
                body = stream.read(length)
                if len(body) < length:
                    self._stop(TruncatedError, f'{_describe(self._source)}: record at byte '
                               f'{offset} is cut short (truncated)')
                    return
                reader = _RECORD_READERS.get(opcode)
                record = None
                if reader is not None:
                    try:
                        record = reader(ReadDataStream(io.BytesIO(body)))
                    except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
                        self._stop(CorruptError, f'{_describe(self._source)}: damaged '
                                   f'{Opcode(opcode).name.lower()} record at byte {offset} '
                                   f'({exc or type(exc).__name__})')
                        return
                offset += 9 + length
                if record is not None:
                    yield offset, record
                if isinstance(record, Footer):
                    if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                        self._stop(TruncatedError, f'{_describe(self._source)}: file ends '
                                   'without its closing magic bytes (truncated)')
                        return
                    self.complete = True
                    return
        finally:
            if owned:
                stream.close()

    def _add_schema_channel(self, schemas: Dict[int, Schema], record) -> None:
        if isinstance(record, Schema):
            schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            if record.topic in self.channels:
                return
            schema = schemas.get(record.schema_id)
            self.channels[record.topic] = ChannelInfo(
                id=record.id, topic=record.topic,
                type_name=schema.name if schema else '',
                message_encoding=record.message_encoding, metadata=dict(record.metadata),
                schema_encoding=schema.encoding if schema else '',
                schema_text=schema.data.decode('utf-8', 'replace') if schema else '')

    def _messages(self) -> Iterator[RecordedMessage]:
        schemas: Dict[int, Schema] = {}
        by_id: Dict[int, ChannelInfo] = {}
        self.channels = {}
        self.metadata = {}

        def handle(records):
            for rec in records:
                if isinstance(rec, (Schema, Channel)):
                    self._add_schema_channel(schemas, rec)
                    if isinstance(rec, Channel) and rec.topic in self.channels:
                        by_id.setdefault(rec.id, self.channels[rec.topic])
                elif isinstance(rec, Message):
                    yield rec

        for offset, record in self._records():
            if isinstance(record, Chunk):
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                except Exception as exc:  # zstd/lz4 errors, CRC mismatch, EndOfFile
                    self._stop(CorruptError, f'{_describe(self._source)}: damaged chunk '
                               f'ending at byte {offset} ({exc})')
                    return
                self.chunks += 1
                records: Iterable = inner
            elif isinstance(record, Metadata):
                self.metadata[record.name] = dict(record.metadata)
                continue
            else:
                records = (record,)
            for msg in handle(records):
                channel = by_id.get(msg.channel_id)
                if channel is None:
                    self._stop(CorruptError, f'{_describe(self._source)}: message on unknown '
                               f'channel {msg.channel_id}')
                    return
                if self._topics is not None and channel.topic not in self._topics:
                    continue
                decoded = None
                if self._decode:
                    try:
                        decoded = self._decoder(schemas, channel)(msg.data)
                    except Exception as exc:
                        self._stop(CorruptError, f'{_describe(self._source)}: cannot decode a '
                                   f'{channel.type_name} message on {channel.topic} ({exc})')
                        return
                yield RecordedMessage(channel.topic, channel.type_name, msg.log_time,
                                      msg.publish_time, msg.sequence, msg.data, decoded)

    def _decoder(self, schemas: Dict[int, Schema], channel: ChannelInfo):
        decoder = self._decoders.get(channel.id)
        if decoder is None:
            from mcap_ros2.decoder import DecoderFactory

            schema = next((s for s in schemas.values() if s.name == channel.type_name), None)
            decoder = DecoderFactory().decoder_for(channel.message_encoding, schema)
            if decoder is None:
                raise CorruptError(f'no decoder for {channel.message_encoding} messages of '
                                   f'{channel.type_name} (schema encoding '
                                   f'{channel.schema_encoding!r})')
            self._decoders[channel.id] = decoder
        return decoder


def scan(source, *, strict: bool = False) -> RecordingInfo:
    """Read a whole recording without decoding messages: topics, counts, metadata, integrity.

    Every chunk's CRC is checked. With ``strict``, a truncated or damaged file raises
    (:class:`TruncatedError`, :class:`CorruptError`); otherwise ``complete`` and ``problem``
    of the result say how far the file could be read. A non-MCAP input always raises
    :class:`NotMcapError`.
    """
    reader = McapReader(source, decode=False, strict=strict)
    counts: Dict[str, int] = {}
    first = last = None
    for msg in reader:
        counts[msg.topic] = counts.get(msg.topic, 0) + 1
        first = msg.log_time_ns if first is None else min(first, msg.log_time_ns)
        last = msg.log_time_ns if last is None else max(last, msg.log_time_ns)
    for topic in reader.channels:
        counts.setdefault(topic, 0)
    return RecordingInfo(dict(reader.channels), counts, first, last, dict(reader.metadata),
                         reader.chunks, reader.complete, reader.problem)


def iter_decoded(source, topics: Optional[Iterable[str]] = None,
                 strict: bool = False) -> Iterator[RecordedMessage]:
    """Decoded messages of a recording in file order (see :class:`McapReader`)."""
    return iter(McapReader(source, topics=topics, strict=strict))


# --- flattening and numpy arrays --------------------------------------------------------------

def _is_rclpy_message(msg) -> bool:
    return hasattr(type(msg), 'get_fields_and_field_types')


def _field_names(msg) -> List[str]:
    if _is_rclpy_message(msg):
        return list(msg.get_fields_and_field_types())
    return list(getattr(msg, '__slots__', ()))


def _is_message(value) -> bool:
    return _is_rclpy_message(value) or (hasattr(value, '__slots__') and
                                        not isinstance(value, (str, bytes)))


def message_to_dict(msg) -> Any:
    """A message (rclpy or decoded from a recording) as nested dicts and lists of plain values.

    Floats stay floats, integers ints (also ``byte`` fields, which rclpy gives as ``bytes``);
    sequences and arrays become lists.
    """
    if _is_rclpy_message(msg):
        out = {}
        for name, field_type in msg.get_fields_and_field_types().items():
            value = getattr(msg, name)
            if field_type == 'octet' and isinstance(value, bytes):  # rclpy: b'\x01' for a byte
                value = value[0]
            out[name] = message_to_dict(value)
        return out
    if _is_message(msg):
        return {name: message_to_dict(getattr(msg, name)) for name in _field_names(msg)}
    if isinstance(msg, (bytes, bytearray)):
        return list(msg)
    if isinstance(msg, np.ndarray):
        return [message_to_dict(v) for v in msg.tolist()]
    if isinstance(msg, (list, tuple)) or type(msg).__name__ == 'array':
        return [v[0] if isinstance(v, bytes) and len(v) == 1 else message_to_dict(v)
                for v in msg]
    if isinstance(msg, np.generic):
        return msg.item()
    return msg


def flatten(msg, prefix: str = '') -> Dict[str, Any]:
    """Scalar fields of a message as ``{'a.b.c': value}`` (sequences as lists, in one key)."""
    out: Dict[str, Any] = {}
    data = message_to_dict(msg) if not isinstance(msg, dict) else msg

    def walk(value, key):
        if isinstance(value, dict):
            for name, item in value.items():
                walk(item, f'{key}.{name}' if key else name)
        else:
            out[key] = value

    walk(data, prefix)
    return out


def _time_fields(flat: Dict[str, Any]) -> Dict[str, Any]:
    """Fold ``x.sec``/``x.nanosec`` pairs into ``x_ns``; ``header.stamp`` becomes ``stamp_ns``
    and ``header.frame_id`` is dropped."""
    out: Dict[str, Any] = {}
    for key, value in flat.items():
        if key.endswith('.nanosec') and key[:-8] + '.sec' in flat:
            continue
        if key.endswith('.sec') and key[:-4] + '.nanosec' in flat:
            base = key[:-4]
            ns = int(value) * 1_000_000_000 + int(flat[base + '.nanosec'])
            out['stamp_ns' if base == 'header.stamp' else base.replace('.', '_') + '_ns'] = ns
            continue
        if key == 'header.frame_id':
            continue
        out[key] = value
    return out


def load_topic_arrays(source, topic: str, *, strict: bool = False) -> Dict[str, np.ndarray]:
    """Load one topic of a recording into numpy arrays, one per scalar field.

    Returns
    -------
    dict
        ``log_time_ns``, ``publish_time_ns`` (int64, ns); ``stamp_ns`` (int64, ns, from
        ``header.stamp``); every other time ``x`` (``sec``/``nanosec``) as ``x_ns``; every
        float field as float64, integer and bool fields as int64/bool, string fields as object
        arrays, nested fields as ``a.b``. Sequence fields are left out.

    Raises
    ------
    MissingTopicError
        If the recording has no channel ``topic`` (a :class:`RecordingError` and a
        ``KeyError``).
    RecordingError
        If the file cannot be read or is not a readable recording; the message names it.
    """
    columns: Dict[str, list] = {'log_time_ns': [], 'publish_time_ns': []}
    n = 0
    try:
        reader = McapReader(source, topics=[topic], strict=strict)
        for msg in reader:
            flat = _time_fields(flatten(msg.message))
            columns['log_time_ns'].append(msg.log_time_ns)
            columns['publish_time_ns'].append(msg.publish_time_ns)
            for key, value in flat.items():
                if isinstance(value, list):
                    continue
                columns.setdefault(key, [None] * n).append(value)
            n += 1
    except OSError as exc:
        raise RecordingError(f'cannot read {_describe(source)}: {exc.strerror or exc}') from None
    if topic not in reader.channels:
        raise MissingTopicError(f'{_describe(source)} has no topic {topic} '
                                f'(topics: {", ".join(sorted(reader.channels)) or "none"})')
    out: Dict[str, np.ndarray] = {}
    for key, values in columns.items():
        sample = next((v for v in values if v is not None), None)
        if isinstance(sample, bool):
            out[key] = np.asarray(values, dtype=bool)
        elif isinstance(sample, int):
            out[key] = np.asarray(values, dtype=np.int64 if max(values, default=0) < 2**63
                                  else np.uint64)
        elif isinstance(sample, float):
            out[key] = np.asarray(values, dtype=np.float64)
        else:
            out[key] = np.asarray(values, dtype=object)
    return out
