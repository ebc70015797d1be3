"""Recording tools for the actuator graph: MCAP files in rosbag2's layout, and the tools around
them.

* :mod:`~eha_ros.recording.definitions`: profile, encodings, errors, message definitions,
  type hashes, QoS, lost-message counting;
* :mod:`~eha_ros.recording.writer`: :class:`McapWriter`;
* :mod:`~eha_ros.recording.reader`: :class:`McapReader`, :func:`scan`, :func:`iter_decoded`;
* :mod:`~eha_ros.recording.arrays`: :func:`load_topic_arrays`, :func:`message_to_dict`;
* :mod:`~eha_ros.recording.mcap_io`: all of the above in one namespace (no ROS imports).

The graph's topic names, types and QoS are in :mod:`eha_ros.graph`.
* console scripts: ``recorder`` (node writing one MCAP file per run), ``eha-replay``
  (republish a recording with its timing and ``/clock``), ``eha-echo`` (print a topic) and
  ``eha-compare`` (relative errors and plots of runs against a reference).
"""

from eha_ros.recording.mcap_io import (CorruptError, iter_decoded, load_topic_arrays,
                                       McapReader, McapWriter, NotMcapError, RecordingError,
                                       RecordingInfo, scan, TruncatedError)
from eha_ros.graph import TOPICS

__all__ = ['TOPICS', 'McapWriter', 'McapReader', 'RecordingInfo', 'scan', 'iter_decoded',
           'load_topic_arrays', 'RecordingError', 'NotMcapError', 'TruncatedError',
           'CorruptError']
