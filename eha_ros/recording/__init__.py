"""Recording tools for the actuator graph: MCAP files in rosbag2's layout, and the tools around
them.

* :mod:`~eha_ros.recording.definitions`: profile, encodings, errors, message definitions,
  type hashes, QoS, lost-message counting;
* :mod:`~eha_ros.recording.writer`: :class:`McapWriter`;
* :mod:`~eha_ros.recording.reader`: :class:`McapReader`, :func:`scan`, :func:`iter_decoded`;
* :mod:`~eha_ros.recording.arrays`: :func:`load_topic_arrays`, :func:`message_to_plain_data`.

* console scripts: ``eha-replay`` (republish a recording with its timing and ``/clock``),
  ``eha-echo`` (print a topic) and ``eha-compare`` (relative errors and plots of runs
  against a reference).

The graph's topic names, types and QoS are in :mod:`eha_ros.graph`; the ``recorder`` node,
writing one MCAP file per run, is :mod:`eha_ros.nodes.recorder`.
"""

from eha_ros.recording.arrays import load_topic_arrays
from eha_ros.recording.definitions import (CorruptError, NotMcapError, RecordingError,
                                           TruncatedError)
from eha_ros.recording.reader import iter_decoded, McapReader, RecordingInfo, scan
from eha_ros.recording.writer import McapWriter
from eha_ros.graph import TOPICS

__all__ = ['TOPICS', 'McapWriter', 'McapReader', 'RecordingInfo', 'scan', 'iter_decoded',
           'load_topic_arrays', 'RecordingError', 'NotMcapError', 'TruncatedError',
           'CorruptError']
