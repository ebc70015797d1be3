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

The implementation is split by role: :mod:`~eha_ros.recording.definitions` (profile,
encodings, errors, message definitions, type hashes, QoS, lost-message counting),
:mod:`~eha_ros.recording.writer` (:class:`McapWriter`), :mod:`~eha_ros.recording.reader`
(:class:`McapReader`, :func:`scan`, :func:`iter_decoded`) and
:mod:`~eha_ros.recording.arrays` (:func:`load_topic_arrays`, :func:`message_to_dict`,
:func:`flatten`). This module re-exports their public names.
"""

from eha_ros.recording.arrays import flatten, load_topic_arrays, message_to_dict
from eha_ros.recording.definitions import (CorruptError, count_sequence_gaps, MCAP_MAGIC,
                                           MESSAGE_ENCODING, message_definition,
                                           MissingTopicError, NotMcapError, PROFILE,
                                           qos_profile_dict, qos_profiles_yaml, RecordingError,
                                           ROSBAG2_METADATA_NAME, ROSBAG2_METADATA_VERSION,
                                           RUN_METADATA_NAME, SCHEMA_ENCODING,
                                           SequenceGapCounter, TruncatedError, type_hash)
from eha_ros.recording.reader import (ChannelInfo, iter_decoded, McapReader, RecordedMessage,
                                      RecordingInfo, scan)
from eha_ros.recording.writer import McapWriter

__all__ = ['PROFILE', 'SCHEMA_ENCODING', 'MESSAGE_ENCODING', 'RUN_METADATA_NAME',
           'ROSBAG2_METADATA_NAME', 'ROSBAG2_METADATA_VERSION', 'MCAP_MAGIC', 'RecordingError',
           'NotMcapError', 'TruncatedError', 'CorruptError', 'MissingTopicError',
           'message_definition', 'type_hash', 'qos_profile_dict', 'qos_profiles_yaml',
           'McapWriter', 'RecordedMessage', 'ChannelInfo', 'RecordingInfo', 'McapReader', 'scan',
           'iter_decoded', 'load_topic_arrays', 'message_to_dict', 'flatten',
           'count_sequence_gaps', 'SequenceGapCounter']
