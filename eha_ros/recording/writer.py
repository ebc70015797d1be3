"""Write a recording (:class:`McapWriter`) in the MCAP layout rosbag2's MCAP storage uses:

* profile ``ros2``; one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``:
  the type's ``.msg`` text and those of its dependencies, as
  :func:`~eha_ros.recording.definitions.message_definition` describes;
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

No ROS imports except in :meth:`McapWriter.write_message`, which serializes an rclpy message.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import time
from typing import Any, BinaryIO, Dict, Mapping, Optional, Sequence, Union

from mcap.writer import CompressionType, Writer
import yaml

from eha_ros.graph import normalize_type
from eha_ros.recording.definitions import (MESSAGE_RECORD_OVERHEAD, MESSAGE_ENCODING,
                                           message_definition, PROFILE,
                                           PROGRESS_METADATA_NAME, qos_profiles_yaml,
                                           ROSBAG2_METADATA_NAME, ROSBAG2_METADATA_VERSION,
                                           RUN_METADATA_NAME, SCHEMA_ENCODING, type_hash)

__all__ = ['McapWriter']


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
             'none': CompressionType.NONE}
    if name not in table:
        raise ValueError(f'unknown compression {name!r} (zstd, lz4, none or auto)')
    return table[name]


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
        self._owns_stream = isinstance(output, (str, os.PathLike))
        self.path: Optional[Path] = Path(output) if self._owns_stream else None
        self._stream = (open(self.path, 'wb' if overwrite else 'xb') if self._owns_stream
                        else output)
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
        #: Called after each flushed chunk: its ``{key: JSON-serialisable}`` is written as an
        #: ``eha_ros_progress`` metadata record (None: no such records).
        self.progress = None

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
        qos_yaml = (offered_qos_profiles if isinstance(offered_qos_profiles, str)
                    else qos_profiles_yaml(offered_qos_profiles))
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
        self._pending_bytes += len(data) + MESSAGE_RECORD_OVERHEAD
        if self._pending_bytes >= self._chunk_size or (
                self._flush_interval_s is not None
                and time.monotonic() - self._chunk_opened >= self._flush_interval_s):
            self.flush()

    def bytes_written(self) -> int:
        """Bytes of the file so far (chunks written out; the one being filled not counted)."""
        return self._stream.tell()

    def write_message(self, topic: str, msg, log_time_ns: int,
                      publish_time_ns: Optional[int] = None, sequence: int = 0) -> None:
        """Serialize an rclpy message (needs ``rclpy``) and :meth:`write` it; registers the
        topic with the message's type on first use."""
        from rclpy.serialization import serialize_message

        if topic not in self._channels:
            cls = type(msg)  # a generated rclpy message: its type is pkg/msg/Type
            self.add_topic(topic, f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}")
        self.write(topic, serialize_message(msg), log_time_ns, publish_time_ns, sequence)

    def flush(self) -> None:
        """Close the chunk in progress and write everything out (no ``fsync``)."""
        wrote = self._pending_bytes > 0
        if wrote:
            self.chunks_written += 1
        self._writer.flush()
        if wrote and self.progress is not None and not self.closed:
            self._writer.add_metadata(PROGRESS_METADATA_NAME, {
                k: json.dumps(v, sort_keys=True, default=str) for k, v in self.progress().items()})
            self._stream.flush()
        self._pending_bytes = 0
        self._chunk_opened = time.monotonic()

    def rosbag2_metadata(self) -> Dict[str, Any]:
        """The bag metadata rosbag2 stores in ``serialized_metadata`` (version 9 layout)."""
        start = self._first_log_ns or 0
        duration = (self._last_log_ns - start) if self._last_log_ns is not None else 0
        total = sum(self.message_counts.values())
        name = self.path.name if self.path is not None else ''
        topics = [{'topic_metadata': {'name': topic, 'type': meta['type'],
                                      'serialization_format': MESSAGE_ENCODING,
                                      'offered_qos_profiles': yaml.safe_load(meta['qos']) or [],
                                      'type_description_hash': meta['hash']},
                   'message_count': self.message_counts.get(topic, 0)}
                  for topic, meta in self._topic_meta.items()]
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
