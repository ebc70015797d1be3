"""Read recordings sequentially, without their summary section, so that a truncated file
yields every message up to its last complete chunk (see :mod:`eha_ros.recording.writer`).

Messages are decoded from the schemas in the file (``mcap_ros2``): no ``rclpy`` needed.
"""

from __future__ import annotations

import io
import json
import os
import struct
from typing import Any, Dict, Iterable, Iterator, NamedTuple, Optional

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
import yaml

from eha_ros.recording.definitions import (CorruptError, describe_source as _describe,
                                           MCAP_MAGIC, NotMcapError, ROSBAG2_METADATA_NAME,
                                           RUN_METADATA_NAME, TruncatedError)

__all__ = ['RecordedMessage', 'ChannelInfo', 'RecordingInfo', 'McapReader', 'scan',
           'iter_decoded']


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


class McapReader:
    """Read the messages of a recording in file order (see the module docstring): an iterator
    of :class:`RecordedMessage`.

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

    def _stop(self, exc_type, problem: str):
        """Reading ends at ``problem`` (of the source, which the message names first)."""
        self.problem = f'{_describe(self._source)}: {problem}'
        if self.strict:
            raise exc_type(self.problem)

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
                    self._stop(TruncatedError, 'file ends within its MCAP magic bytes '
                               '(truncated)')
                    return
                what = 'empty file' if not magic else 'no MCAP magic bytes at the start'
                raise NotMcapError(f'{_describe(self._source)}: not an MCAP file ({what})')
            offset = len(MCAP_MAGIC)
            while True:
                head = stream.read(9)
                if len(head) < 9:
                    self._stop(TruncatedError, f'file ends at byte {offset + len(head)} '
                               'before its footer (truncated)')
                    return
                opcode, length = struct.unpack('<BQ', head)
                if size is not None and offset + 9 + length > size:
                    self._stop(TruncatedError, f'record at byte {offset} runs past the end '
                               'of the file (truncated)')
                    return
                if length > 1 << 34:
                    self._stop(CorruptError,
                               f'record at byte {offset} claims {length} bytes (corrupt)')
                    return
                body = stream.read(length)
                if len(body) < length:
                    self._stop(TruncatedError,
                               f'record at byte {offset} is cut short (truncated)')
                    return
                reader = _RECORD_READERS.get(opcode)
                record = None
                if reader is not None:
                    try:
                        record = reader(ReadDataStream(io.BytesIO(body)))
                    except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
                        self._stop(CorruptError, f'damaged {Opcode(opcode).name.lower()} '
                                   f'record at byte {offset} ({exc or type(exc).__name__})')
                        return
                offset += 9 + length
                if record is not None:
                    yield offset, record
                if isinstance(record, Footer):
                    if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                        self._stop(TruncatedError, 'file ends without its closing magic '
                                   'bytes (truncated)')
                        return
                    self.complete = True
                    return
        finally:
            if owned:
                stream.close()

    def _messages(self) -> Iterator[RecordedMessage]:
        schemas: Dict[int, Schema] = {}
        by_id: Dict[int, ChannelInfo] = {}
        self.channels = {}
        self.metadata = {}

        def handle(records):
            """The messages of ``records``; their schemas and channels are taken in."""
            for rec in records:
                if isinstance(rec, Schema):
                    schemas.setdefault(rec.id, rec)
                elif isinstance(rec, Channel):
                    if rec.topic not in self.channels:  # a topic's first channel names it
                        schema = schemas.get(rec.schema_id) or Schema(0, b'', '', '')
                        self.channels[rec.topic] = ChannelInfo(
                            rec.id, rec.topic, schema.name, rec.message_encoding,
                            dict(rec.metadata), schema.encoding,
                            schema.data.decode('utf-8', 'replace'))
                    by_id.setdefault(rec.id, self.channels[rec.topic])
                elif isinstance(rec, Message):
                    yield rec

        for offset, record in self._records():
            if isinstance(record, Chunk):
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                except Exception as exc:  # zstd/lz4 errors, CRC mismatch, EndOfFile
                    self._stop(CorruptError, f'damaged chunk ending at byte {offset} ({exc})')
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
                    self._stop(CorruptError, f'message on unknown channel {msg.channel_id}')
                    return
                if self._topics is not None and channel.topic not in self._topics:
                    continue
                decoded = None
                if self._decode:
                    try:
                        decoded = self._decoder(schemas, channel)(msg.data)
                    except Exception as exc:
                        self._stop(CorruptError, f'cannot decode a {channel.type_name} '
                                   f'message on {channel.topic} ({exc})')
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
