"""Recording tools for the actuator graph: MCAP files in rosbag2's layout, and the tools around
them.

* :mod:`~eha_ros.recording.topics`: the graph's topic names, types, rates and QoS (no ROS
  imports);
* :mod:`~eha_ros.recording.mcap_io`: :class:`McapWriter`, :class:`McapReader`,
  :func:`scan` and :func:`load_topic_arrays` (no ROS imports);
* console scripts: ``recorder`` (node writing one MCAP file per run), ``eha-replay``
  (republish a recording with its timing and ``/clock``), ``eha-echo`` (print a topic) and
  ``eha-compare`` (relative errors and plots of runs against a reference).
"""

from eha_ros.recording.mcap_io import (CorruptError, iter_decoded, load_topic_arrays,
                                       McapReader, McapWriter, NotMcapError, RecordingError,
                                       RecordingInfo, scan, TruncatedError)
from eha_ros.recording.topics import TOPICS

__all__ = ['TOPICS', 'McapWriter', 'McapReader', 'RecordingInfo', 'scan', 'iter_decoded',
           'load_topic_arrays', 'RecordingError', 'NotMcapError', 'TruncatedError',
           'CorruptError']
