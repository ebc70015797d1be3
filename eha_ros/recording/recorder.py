"""``recorder``: record the actuator graph's topics into one MCAP file per run.

Examples::

    recorder -o run1.mcap                             # every graph topic until Ctrl-C
    recorder -o run1.mcap --topics /eha/state /eha/command --duration 10
    recorder --ros-args -p output:=run1.mcap -p topics:='[/eha/state]'

Every topic is subscribed to as serialized CDR (no deserialization) and written as-is, in
rosbag2's MCAP layout (see :mod:`eha_ros.recording.mcap_io`); each topic's channel is created
when its first message arrives, with the QoS its publishers offer. Lost messages are counted
per topic from the publishers' sequence numbers (``publication_sequence_number`` of the message
info: DDS numbers the samples of each publisher 1, 2, 3, ...; a jump is a loss) and stored in
the file's ``eha_ros`` metadata record at close. SIGINT or SIGTERM (or ``--duration``) end the
run: the messages already received are written and the file is closed with its metadata,
summary and footer. A recorder killed outright leaves a file readable up to its last chunk
(chunks are written at least every ``flush_interval_s``).

Parameters (``--ros-args -p name:=value``; the command-line options override them):

===================  ==========================================================  ===========
``output``           MCAP file to create (never overwritten); ``''``: a new       ``''``
                     ``eha_<date>-<time>.mcap`` in the working directory
``topics``           topics to record, each a graph topic                         all
``namespace``        namespace of the actuator's topics                           ``/eha``
``queue_depth``      subscription history depth (samples)                         1000
``chunk_size``       uncompressed bytes per MCAP chunk                            1048576
``compression``      ``auto``, ``zstd``, ``lz4`` or ``none``                      ``auto``
``flush_interval_s`` longest time a received message stays in memory, s           1.0
``duration_s``       stop after this long, s (0: until SIGINT/SIGTERM)            0.0
``batch_period_s``   pause after taking messages so the next take finds a batch,  0.005
                     s (the history holds ``queue_depth`` per topic)
===================  ==========================================================  ===========

Exit status: 0 after a clean stop, 2 on a usage error (unknown topic, existing output, bad
parameter), with one line on stderr.
"""

from __future__ import annotations

import argparse
import datetime
import os
from pathlib import Path
import socket
import sys
import time
from typing import Dict, List, Optional, Sequence

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from eha_ros import graph
from eha_ros.recording.definitions import qos_profile_dict, SequenceGapCounter
from eha_ros.recording.stop import StopRequest
from eha_ros.recording.writer import McapWriter

__all__ = ['Recorder', 'RecorderError', 'main']

NODE_NAME = 'recorder'
LOSS_DETECTION = 'publication_sequence_number'
#: After a stop request, keep taking messages until none arrived for this long (s).
_DRAIN_QUIET_S = 0.1
_DRAIN_MAX_S = 2.0


#: The recorder's parameters: ``name -> (default, description)`` (the module docstring's table).
RECORDER_PARAMETERS = {
    'output': ('', "MCAP file to create (never overwritten); '': eha_<date>-<time>.mcap"),
    'topics': (list(graph.TOPICS), 'topics to record, each a graph topic (moved to namespace)'),
    'namespace': (graph.NAMESPACE, "namespace of the actuator's topics"),
    'queue_depth': (1000, 'subscription history depth [samples]'),
    'chunk_size': (1 << 20, 'uncompressed bytes per MCAP chunk [B]'),
    'compression': ('auto', 'chunk compression: auto, zstd, lz4 or none'),
    'flush_interval_s': (1.0, 'longest time a received message stays in memory [s]'),
    'duration_s': (0.0, 'stop after this long [s] (0: until SIGINT/SIGTERM)'),
    'batch_period_s': (0.005, 'pause after taking messages so the next take finds a batch [s]'),
}


class RecorderError(ValueError):
    """A usage error: unknown topic, existing output file, bad parameter."""


def default_output() -> str:
    """``eha_<YYYYmmdd>-<HHMMSS>.mcap`` (local time)."""
    return datetime.datetime.now().strftime('eha_%Y%m%d-%H%M%S.mcap')


def resolve_topics(requested: Sequence[str], namespace: str = graph.NAMESPACE) -> Dict[str, str]:
    """Validate requested topic names against the graph; returns ``topic -> type``.

    Raises
    ------
    RecorderError
        If a topic is not one of the graph's (with its namespace), or none is requested.
    """
    known = graph.topics_in(namespace)
    if not requested:
        raise RecorderError('no topics to record (parameter topics is empty)')
    out: Dict[str, str] = {}
    for name in requested:
        name = name.strip()
        if name not in known:
            raise RecorderError(f'unknown topic {name!r}: the graph has '
                                f'{", ".join(sorted(known))}')
        out[name] = known[name]
    return out


def check_output(path: str) -> Path:
    """The output path, refused where it exists or its folder does not."""
    out = Path(path)
    if out.exists():
        raise RecorderError(f'output {str(out)!r} exists; refusing to overwrite it')
    parent = out.parent if str(out.parent) else Path('.')
    if not parent.is_dir():
        raise RecorderError(f'output folder {str(parent)!r} does not exist')
    return out


class _TopicState:
    __slots__ = ('topic', 'type_name', 'cls', 'subscription', 'counter', 'registered',
                 'sequence_numbers')

    def __init__(self, topic: str, type_name: str, cls: type):
        self.topic = topic
        self.type_name = type_name
        self.cls = cls
        self.subscription = None
        self.counter = SequenceGapCounter()
        self.registered = False
        self.sequence_numbers = True


class Recorder(Node):
    """Subscribes to the graph's topics as raw CDR and writes them to an MCAP file."""

    def __init__(self, *, parameter_overrides: Optional[list] = None, **kwargs):
        super().__init__(NODE_NAME, parameter_overrides=parameter_overrides or [],
                         **kwargs)
        value = {name: self.declare_parameter(
            name, default, ParameterDescriptor(description=text)).value
            for name, (default, text) in RECORDER_PARAMETERS.items()}
        self.output = value['output'] or default_output()
        namespace = value['namespace']
        requested = value['topics']
        if list(requested) == list(graph.TOPICS):  # the default: every topic, in namespace
            requested = list(graph.topics_in(namespace))
        queue_depth = int(value['queue_depth'])
        chunk_size = int(value['chunk_size'])
        compression = value['compression']
        flush_interval_s = float(value['flush_interval_s'])
        self.duration_s = float(value['duration_s'])
        self.batch_period_s = float(value['batch_period_s'])
        if not 0.0 <= self.batch_period_s <= 0.1:
            raise RecorderError(f'batch_period_s must be in [0, 0.1], got '
                                f'{self.batch_period_s}')
        if queue_depth < 1:
            raise RecorderError(f'queue_depth must be >= 1, got {queue_depth}')
        if chunk_size < 1:
            raise RecorderError(f'chunk_size must be >= 1, got {chunk_size}')
        if flush_interval_s <= 0:
            raise RecorderError(f'flush_interval_s must be > 0, got {flush_interval_s}')
        if compression not in ('auto', 'zstd', 'lz4', 'none'):
            raise RecorderError(f'compression must be auto, zstd, lz4 or none, got '
                                f'{compression!r}')
        wanted = resolve_topics(list(requested or []), namespace)
        states = []
        for topic, type_name in wanted.items():
            try:
                states.append(_TopicState(topic, type_name, graph.message_class(type_name)))
            except ValueError as exc:
                raise RecorderError(str(exc)) from None
        path = check_output(self.output)

        self.started_ns = time.time_ns()
        self.writer = McapWriter(path, chunk_size=chunk_size, compression=compression,
                                 flush_interval_s=flush_interval_s)
        self.writer.progress = self._progress
        self.last_message_monotonic = time.monotonic()
        self.received = 0
        self._states: Dict[str, _TopicState] = {}
        qos = graph.graph_qos(depth=queue_depth)
        for state in states:
            self._states[state.topic] = state
            state.subscription = self.create_subscription(
                state.cls, state.topic, self._callback(state), qos, raw=True)
        self.get_logger().info(
            f'recording {len(states)} topics to {path}: '
            f'{", ".join(s.topic for s in states)}')

    def _callback(self, state: _TopicState):
        def on_message(data: bytes, info) -> None:
            self._record(state, data, info)
            # Take what else is waiting now: far cheaper than one executor pass each.
            handle = state.subscription.handle
            while True:
                with handle:
                    taken = handle.take_message(state.cls, True)
                if taken is None:
                    return
                self._record(state, taken[0], taken[1])
        return on_message

    def _register(self, state: _TopicState) -> None:
        profiles = []
        try:
            profiles = [qos_profile_dict(p.qos_profile)
                        for p in self.get_publishers_info_by_topic(state.topic)]
        except Exception:  # graph query failed: fall back to the nominal QoS
            profiles = []
        self.writer.add_topic(state.topic, state.type_name,
                              offered_qos_profiles=profiles or None)
        state.registered = True

    def _record(self, state: _TopicState, data: bytes, info) -> None:
        if not state.registered:
            self._register(state)
        sequence = info.get('publication_sequence_number')
        gid = info.get('publisher_gid')
        publisher = bytes(gid['data']) if gid else None
        if sequence is None:
            state.sequence_numbers = False
        state.counter.add(sequence, publisher)
        log_ns = info.get('received_timestamp') or time.time_ns()
        self.writer.write(state.topic, data, log_time_ns=log_ns,
                          publish_time_ns=info.get('source_timestamp') or log_ns,
                          sequence=sequence or 0)
        self.received += 1
        self.last_message_monotonic = time.monotonic()

    def lost_counts(self) -> Dict[str, int]:
        return {t: s.counter.lost for t, s in self._states.items()}

    def _run_info(self) -> dict:
        return {
            'node': self.get_fully_qualified_name(),
            'host': socket.gethostname(),
            'argv': sys.argv,
            'started_ns': self.started_ns,
            'rmw_implementation': os.environ.get('RMW_IMPLEMENTATION', ''),
            'ros_domain_id': os.environ.get('ROS_DOMAIN_ID', '0'),
            'loss_detection': {t: LOSS_DETECTION if s.sequence_numbers else 'unavailable'
                               for t, s in self._states.items()},
            'missed_at_start': {t: s.counter.missed_at_start
                                for t, s in self._states.items()},
            'publishers': {t: s.counter.publishers for t, s in self._states.items()},
        }

    def _progress(self) -> dict:
        """What a killed recorder's file keeps (after each chunk): losses so far, run info."""
        return {'lost': self.lost_counts(), 'recorded': dict(self.writer.message_counts),
                'run': dict(self._run_info(), progress_ns=time.time_ns())}

    def close(self) -> None:
        """Register silent topics, store lost counts and run info, close the file."""
        if self.writer.closed:
            return
        for state in self._states.values():
            if not state.registered:
                self._register(state)
        stopped_ns = time.time_ns()
        self.writer.lost_counts = self.lost_counts()
        self.writer.run_info.update(self._run_info(), stopped_ns=stopped_ns)
        self.writer.close()
        log = self.get_logger()
        counts = self.writer.message_counts
        lost = self.writer.lost_counts
        log.info(f'wrote {self.output}: {sum(counts.values())} messages, '
                 f'{sum(lost.values())} lost, '
                 f'{(stopped_ns - self.started_ns) / 1e9:.1f} s')
        for topic in self._states:
            state = self._states[topic]
            note = '' if state.sequence_numbers else ' (loss detection unavailable)'
            log.info(f'  {topic}: {counts.get(topic, 0)} recorded, '
                     f'{lost.get(topic, 0)} lost{note}')


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='recorder', description='Record the actuator graph into an MCAP file.')
    parser.add_argument('-o', '--output', help='MCAP file to create (never overwritten)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='topics to record (default: every graph topic)')
    parser.add_argument('--duration', type=float, metavar='S',
                        help='stop after S seconds (default: until SIGINT/SIGTERM)')
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Console script ``recorder``; returns the exit status."""
    argv = list(sys.argv if argv is None else argv)
    args = _parser().parse_args(remove_ros_args(argv)[1:])
    overrides = []
    if args.output is not None:
        overrides.append(Parameter('output', value=args.output))
    if args.topics is not None:
        overrides.append(Parameter('topics', value=list(args.topics)))
    if args.duration is not None:
        overrides.append(Parameter('duration_s', value=float(args.duration)))

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopRequest()
    node = None
    try:
        try:
            node = Recorder(parameter_overrides=overrides)
        except (RecorderError, ParameterException, ValueError, FileExistsError) as exc:
            print(f'recorder: error: {" ".join(str(exc).split())}', file=sys.stderr)
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = (time.monotonic() + node.duration_s) if node.duration_s > 0 else None
        while not stop.requested and rclpy.ok():
            before = node.received
            executor.spin_once(timeout_sec=0.1)
            if deadline is not None and time.monotonic() >= deadline:
                break
            if node.received != before and node.batch_period_s > 0:
                # Let messages gather: each callback then takes a batch (less CPU per message).
                time.sleep(node.batch_period_s)
        # Write what has already arrived before closing the file.
        drain_end = time.monotonic() + _DRAIN_MAX_S
        while rclpy.ok() and time.monotonic() < drain_end:
            executor.spin_once(timeout_sec=0.02)
            if time.monotonic() - node.last_message_monotonic > _DRAIN_QUIET_S:
                break
        return 0
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()


if __name__ == '__main__':
    sys.exit(main())
