"""Recorded messages as plain data: nested dicts, flat ``{'a.b': value}`` rows, and one topic
of a recording as numpy arrays for analysis (no ``rclpy`` needed)."""

from __future__ import annotations

import sys
from typing import Any, Dict

import numpy as np

from eha_ros.recording.definitions import (describe_source as _describe, MissingTopicError,
                                           RecordingError, TruncatedError)
from eha_ros.recording.reader import McapReader

__all__ = ['message_to_plain_data', 'flatten', 'load_topic_arrays', 'load_for_tool',
           'truncation_warning']


def message_to_plain_data(msg) -> Any:
    """A message (rclpy or decoded from a recording) as nested dicts and lists of plain values.

    Floats stay floats, integers ints (also ``byte`` fields, which rclpy gives as ``bytes``);
    sequences and arrays become lists.
    """
    if hasattr(type(msg), 'get_fields_and_field_types'):  # an rclpy message
        out = {}
        for name, field_type in msg.get_fields_and_field_types().items():
            value = getattr(msg, name)
            if field_type == 'octet' and isinstance(value, bytes):  # rclpy: b'\x01' for a byte
                value = value[0]
            out[name] = message_to_plain_data(value)
        return out
    if hasattr(msg, '__slots__'):  # a message decoded from a recording (mcap_ros2)
        return {name: message_to_plain_data(getattr(msg, name)) for name in msg.__slots__}
    if isinstance(msg, (bytes, bytearray)):
        return list(msg)
    if isinstance(msg, np.ndarray):
        return [message_to_plain_data(v) for v in msg.tolist()]
    if isinstance(msg, (list, tuple)) or type(msg).__name__ == 'array':
        return [v[0] if isinstance(v, bytes) and len(v) == 1 else message_to_plain_data(v)
                for v in msg]
    return msg.item() if isinstance(msg, np.generic) else msg


def flatten(msg) -> Dict[str, Any]:
    """Scalar fields of a message as ``{'a.b.c': value}`` (sequences as lists, in one key)."""
    out: Dict[str, Any] = {}

    def walk(value, key):
        if isinstance(value, dict):
            for name, item in value.items():
                walk(item, f'{key}.{name}' if key else name)
        else:
            out[key] = value

    walk(message_to_plain_data(msg), '')
    return out


def _time_fields(flat: Dict[str, Any]) -> Dict[str, Any]:
    """Fold ``x.sec``/``x.nanosec`` pairs into ``x_ns``; ``header.stamp`` becomes ``stamp_ns``
    and ``header.frame_id`` is dropped."""
    out: Dict[str, Any] = {}
    for key, value in flat.items():
        if key == 'header.frame_id' or (key.endswith('.nanosec') and key[:-8] + '.sec' in flat):
            continue
        if key.endswith('.sec') and key[:-4] + '.nanosec' in flat:
            base = key[:-4]
            ns = int(value) * 1_000_000_000 + int(flat[base + '.nanosec'])
            out['stamp_ns' if base == 'header.stamp' else base.replace('.', '_') + '_ns'] = ns
        else:
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
    try:
        reader = McapReader(source, topics=[topic], strict=strict)
        for n, msg in enumerate(reader):
            flat = _time_fields(flatten(msg.message))
            columns['log_time_ns'].append(msg.log_time_ns)
            columns['publish_time_ns'].append(msg.publish_time_ns)
            for key, value in flat.items():
                if not isinstance(value, list):  # sequence fields are left out
                    columns.setdefault(key, [None] * n).append(value)
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


def truncation_warning(prog: str, source, problem: str, count: int, what: str) -> str:
    """The offline tools' one line for a truncated recording: what it holds, how to repair it."""
    return (f'{prog}: warning: {" ".join(str(problem).split())}; using the {count} {what} '
            f'before it (to repair the file: eha-recover {_describe(source)} -o FIXED.mcap)')


def load_for_tool(source, topic: str, prog: str) -> Dict[str, np.ndarray]:
    """:func:`load_topic_arrays` as the offline tools use it: a damaged file raises, a
    truncated one (a killed recorder's) is read up to its last complete chunk with one
    warning line on stderr naming the count of messages recovered and ``eha-recover``."""
    try:
        return load_topic_arrays(source, topic, strict=True)
    except TruncatedError as exc:
        arrays = load_topic_arrays(source, topic, strict=False)
        print(truncation_warning(prog, source, str(exc), int(arrays['log_time_ns'].size),
                                 f'{topic} messages'), file=sys.stderr)
        return arrays
