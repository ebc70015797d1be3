"""``recorder``: record the actuator graph's topics into one MCAP file per run.

Examples::

    recorder -o run1.mcap                             # every graph topic until Ctrl-C
    recorder -o run1.mcap --topics /eha/state /eha/command --duration 10
    recorder --ros-args -p output:=run1.mcap -p topics:='[/eha/state]'
    recorder -o run.mcap -x '^/clock$|/diagnostics'     # all but /clock and /diagnostics
    recorder -o run.mcap --max-bag-duration 60        # run_0.mcap, run_1.mcap, ... each 60 s
    recorder -o box.mcap --snapshot 10                # black box: box_0.mcap on a fault

Controls, as rosbag2's: ``--regex`` / ``--exclude-regex`` choose topics by pattern (on top
of ``topics``); ``--max-bag-size`` / ``--max-bag-duration`` split the recording into complete
files ``<stem>_0.mcap``, ``<stem>_1.mcap``, ... (the numbering rosbag2 gives a bag's files;
the size is checked against the bytes written out, so a file may exceed it by up to a chunk),
each with its own metadata and the losses of its own span; ``--snapshot S`` keeps only the
last S seconds in memory and writes them to the next numbered file when the ``~/snapshot``
service (``std_srvs/srv/Trigger``) is called, and by itself when ``/eha/health`` turns to
``LEVEL_ERROR``, so the moments before a fault are kept.  ``~/status`` (``Trigger``) answers
the messages received so far per topic, as JSON: the harness waits on it before it stops the
publishers, so a recorder that lags (a loaded machine) loses no tail of the run.

Every topic is subscribed to as serialized CDR (no deserialization) and written as-is, in
rosbag2's MCAP layout (see :mod:`eha_ros.recording.writer`); each topic's channel is created
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
``regex``            record only topics matching this regular expression          ``''``
``exclude_regex``    leave out topics matching this regular expression            ``''``
``max_bag_size_b``   split by size, bytes (0: no split)                           0
``max_bag_duration_s`` split by duration, s (0: no split)                         0.0
``snapshot_s``       snapshot mode: seconds kept in memory (0: record all)        0.0
``thread_priority``  SCHED_FIFO priority of every thread (0: normal)             0
``cpu_affinity``     CPUs to pin to (``[-1]``: no pinning)                       ``[-1]``
``lock_memory``      lock the process memory (``mlockall``)                      false
===================  ==========================================================  ===========

Exit status: 0 after a clean stop, 2 on a usage error (unknown topic, existing output, bad
parameter), with one line on stderr.
"""

from __future__ import annotations

import argparse
from collections import deque
import dataclasses
import datetime
import json
import os
from pathlib import Path
import re
import socket
import sys
import time
from typing import Dict, List, Optional, Sequence

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from eha_ros import graph
from eha_ros.physics import ParameterError
from eha_ros.recording.definitions import qos_profile_dict, SequenceGapCounter
from eha_ros.recording.stop import StopRequest
from eha_ros.recording.writer import McapWriter

from .common import (apply_realtime_settings, declare, declare_realtime, refuse_undeclared,
                     take_waiting, validator)
from .handshake import Handshake

__all__ = ['Recorder', 'RecorderError', 'main']

NODE_NAME = 'recorder'
LOSS_DETECTION = 'publication_sequence_number'
#: After a stop request, keep taking messages until none arrived for this long (s).
_DRAIN_QUIET_S = 0.1
_DRAIN_MAX_S = 2.0


#: Chunk compressions of ``compression``.
COMPRESSIONS = ('auto', 'zstd', 'lz4', 'none')


def declare_parameters(node: Node):
    """Declare the recorder's parameters (the module docstring's table) on ``node``; returns
    ``({name: value}, RealtimeSettings)``."""
    values = {name: declare(node, name, *spec) for name, *spec in (
        ('output', '', "MCAP file to create (never overwritten); '': eha_<date>-<time>.mcap"),
        ('topics', list(graph.TOPICS), 'topics to record, each a graph topic (moved to '
                                       'namespace)'),
        ('namespace', graph.NAMESPACE, "namespace of the actuator's topics"),
        ('queue_depth', 1000, 'subscription history depth [samples]'),
        ('chunk_size', 1 << 20, 'uncompressed bytes per MCAP chunk [B]'),
        ('compression', 'auto', 'chunk compression: auto, zstd, lz4 or none', None, None,
         COMPRESSIONS),
        ('flush_interval_s', 1.0, 'longest time a received message stays in memory [s]'),
        ('duration_s', 0.0, 'stop after this long [s] (0: until SIGINT/SIGTERM)'),
        ('batch_period_s', 0.005, 'pause after taking messages so the next take finds a batch '
                                  '[s]', 0.0, 0.1),
        ('regex', '', 'record only the topics matching this regular expression (empty: all)'),
        ('exclude_regex', '', 'leave out the topics matching this regular expression'),
        ('max_bag_size_b', 0, 'split: start the next file once one holds this many bytes [B] '
                              '(0: no split by size)'),
        ('max_bag_duration_s', 0.0, 'split: start the next file once one spans this long [s] '
                                    '(0: no split by duration)'),
        ('snapshot_s', 0.0, 'snapshot mode: keep the last snapshot_s [s] in memory and write '
                            'them on ~/snapshot or when /eha/health turns ERROR (0: record '
                            'all)'))}
    return values, declare_realtime(node)


def check_parameters(values: dict) -> None:
    """Refuse what the recorder cannot work with (ParameterError: one line)."""
    for name, lowest in (('queue_depth', 1), ('chunk_size', 1), ('max_bag_size_b', 0),
                         ('max_bag_duration_s', 0.0), ('snapshot_s', 0.0)):
        if values[name] < lowest:
            raise ParameterError(f'{name} must be >= {lowest:g}, got {values[name]}')
    if values['flush_interval_s'] <= 0:
        raise ParameterError(f'flush_interval_s must be > 0, got {values["flush_interval_s"]}')
    if values['compression'] not in COMPRESSIONS:
        raise ParameterError(f'compression must be one of {", ".join(COMPRESSIONS)}, got '
                             f'{values["compression"]!r}')
    if values['snapshot_s'] and (values['max_bag_size_b'] or values['max_bag_duration_s']):
        raise ParameterError('snapshot mode writes one file per snapshot: no split with it')


class RecorderError(ValueError):
    """A usage error: unknown topic, existing output file, bad parameter."""


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


def topics_matching(topics: Dict[str, str], regex: str = '',
                    exclude_regex: str = '') -> Dict[str, str]:
    """The topics matching ``regex`` (``re.search``; empty: all) and not ``exclude_regex``.

    Raises
    ------
    RecorderError
        If a pattern is not a regular expression, or no topic is left.
    """
    try:
        keep = re.compile(regex) if regex else None
        drop = re.compile(exclude_regex) if exclude_regex else None
    except re.error as exc:
        raise RecorderError(f'bad topic pattern: {exc}') from None
    out = {t: ty for t, ty in topics.items()
           if (keep is None or keep.search(t)) and not (drop is not None and drop.search(t))}
    if not out:
        raise RecorderError(f'no topic left to record (regex {regex!r}, exclude_regex '
                            f'{exclude_regex!r}, topics {", ".join(topics)})')
    return out


def check_output(path: str, numbered: bool = False) -> Path:
    """The output path, refused where it (or, ``numbered``, a ``<stem>_<n>`` file of it)
    exists or its folder does not."""
    out = Path(path)
    if out.exists():
        raise RecorderError(f'output {str(out)!r} exists; refusing to overwrite it')
    if numbered and out.parent.is_dir():
        taken = sorted(p.name for p in out.parent.glob(f'{out.stem}_*{out.suffix or ".mcap"}')
                       if p.stem[len(out.stem) + 1:].isdigit())
        if taken:
            raise RecorderError(f'{taken[0]} exists; refusing to overwrite it')
    if not out.parent.is_dir():
        raise RecorderError(f'output folder {str(out.parent)!r} does not exist')
    return out


@dataclasses.dataclass(slots=True)
class _TopicState:
    topic: str
    type_name: str
    cls: type
    subscription: object = None
    counter: SequenceGapCounter = dataclasses.field(default_factory=SequenceGapCounter)
    registered: bool = False
    sequence_numbers: bool = True


class Recorder(Node):
    """Subscribes to the graph's topics as raw CDR and writes them to an MCAP file."""

    def __init__(self, *, parameter_overrides: Optional[list] = None, **kwargs):
        super().__init__(NODE_NAME, parameter_overrides=parameter_overrides or [], **kwargs)
        values, realtime = declare_parameters(self)
        refuse_undeclared(self)  # before any file is created
        check_parameters(values)
        self.add_on_set_parameters_callback(validator(self._on_set))
        self._configure(values)
        states = self._topic_states(values)
        path = check_output(self.output, numbered=self.numbered)
        self.writer = None if self.snapshot_ns else self._open_writer()
        self._subscribe(states, values['namespace'], values['queue_depth'])
        apply_realtime_settings(self, realtime)
        what = (f'the last {self.snapshot_ns / 1e9:g} s of' if self.snapshot_ns else 'recording')
        self.get_logger().info(f'{what} {len(states)} topics to {path}: '
                               f'{", ".join(s.topic for s in states)}')

    def _on_set(self, changes: dict) -> None:
        """Every parameter is fixed for the recording."""
        if changes:
            raise ParameterError(f'{sorted(changes)[0]} cannot change while running')

    def _configure(self, values: dict) -> None:
        self.output = values['output'] or datetime.datetime.now().strftime(
            'eha_%Y%m%d-%H%M%S.mcap')  # local time
        self.duration_s = values['duration_s']
        self.batch_period_s = values['batch_period_s']
        self.max_bag_size_b = values['max_bag_size_b']
        self.max_bag_duration_ns = round(values['max_bag_duration_s'] * 1e9)
        self.snapshot_ns = round(values['snapshot_s'] * 1e9)
        self.numbered = bool(self.max_bag_size_b or self.max_bag_duration_ns or self.snapshot_ns)
        self._writer_args = {k: values[k] for k in ('chunk_size', 'compression',
                                                    'flush_interval_s')}
        self.files: List[str] = []
        self.started_ns = time.time_ns()
        self.last_message_monotonic = time.monotonic()
        self.received = 0
        self._states: Dict[str, _TopicState] = {}
        self._ring: deque = deque()  # snapshot mode: (state, data, log, publish, seq, publisher)
        self._health_level = graph.LEVEL_OK

    @staticmethod
    def _topic_states(values: dict) -> List[_TopicState]:
        """The topics to record: ``topics`` (default: all, in ``namespace``) that match."""
        requested, namespace = list(values['topics']), values['namespace']
        if requested == list(graph.TOPICS):
            requested = list(graph.topics_in(namespace))
        wanted = topics_matching(resolve_topics(requested, namespace), values['regex'],
                                 values['exclude_regex'])
        try:
            return [_TopicState(topic, type_name, graph.message_class(type_name))
                    for topic, type_name in wanted.items()]
        except ValueError as exc:
            raise RecorderError(str(exc)) from None

    def _subscribe(self, states: List[_TopicState], namespace: str, queue_depth: int) -> None:
        """Subscribe to ``states`` as raw CDR; ``~/status`` (snapshot mode: also the health;
        ``~/snapshot``)."""
        qos = graph.graph_qos(depth=queue_depth)
        # The start-up handshake (eha_ros.nodes.handshake): the graph starts only once every
        # subscription here has matched its publishers, so the recording misses no tick.
        self.handshake = Handshake(self)
        for state in states:
            self._states[state.topic] = state
            topic_qos = graph.topic_qos(state.topic) if graph.is_latched(state.topic) else qos
            state.subscription = self.create_subscription(
                state.cls, state.topic, self._callback(state), topic_qos, raw=True)
            self.handshake.watch(state.subscription, state.topic)
        from std_srvs.srv import Trigger
        self.create_service(Trigger, '~/status', self._on_status_request)
        if self.snapshot_ns:
            from eha_ros.msg import HealthStatus
            self.create_service(Trigger, '~/snapshot', self._on_snapshot_request)
            health = next(t for t, ty in graph.topics_in(namespace).items()
                          if ty == graph.TOPICS[graph.TOPIC_HEALTH])
            self.create_subscription(HealthStatus, health, self._on_health, qos)

    # files ---------------------------------------------------------------------------------
    def _next_path(self) -> Path:
        """The output, or (split, snapshot) its ``<stem>_<index>.mcap`` files, as rosbag2
        numbers a bag's files."""
        out = Path(self.output)
        if not self.numbered:
            return out
        return out.with_name(f'{out.stem}_{len(self.files)}{out.suffix or ".mcap"}')

    def _open_writer(self) -> McapWriter:
        path = self._next_path()
        writer = McapWriter(path, **self._writer_args)
        writer.progress = self._progress
        self.files.append(str(path))
        self._file_started_ns = None
        self._lost_at_open = {t: s.counter.lost for t, s in self._states.items()}
        for state in self._states.values():
            state.registered = False
        return writer

    def _split_due(self, log_ns: int) -> bool:
        if self._file_started_ns is None:
            self._file_started_ns = log_ns
            return False
        return (0 < self.max_bag_duration_ns <= log_ns - self._file_started_ns
                or 0 < self.max_bag_size_b <= self.writer.bytes_written())

    def _callback(self, state: _TopicState):
        def on_message(data: bytes, info) -> None:
            self._record(state, data, info)
            # Take what else is waiting now: far cheaper than one executor pass each.
            for taken_data, taken_info in take_waiting(state.subscription, state.cls, raw=True):
                self._record(state, taken_data, taken_info)
        return on_message

    def _register(self, state: _TopicState, writer: Optional[McapWriter] = None) -> None:
        try:
            profiles = [qos_profile_dict(p.qos_profile)
                        for p in self.get_publishers_info_by_topic(state.topic)]
        except Exception:  # graph query failed: fall back to the nominal QoS
            profiles = []
        (writer or self.writer).add_topic(state.topic, state.type_name,
                                          offered_qos_profiles=profiles or None)
        if writer is None:
            state.registered = True

    def _record(self, state: _TopicState, data: bytes, info) -> None:
        sequence = info.get('publication_sequence_number')
        gid = info.get('publisher_gid')
        publisher = bytes(gid['data']) if gid else None
        if sequence is None:
            state.sequence_numbers = False
        state.counter.add(sequence, publisher)
        log_ns = info.get('received_timestamp') or time.time_ns()
        publish_ns = info.get('source_timestamp') or log_ns
        self.received += 1
        self.last_message_monotonic = time.monotonic()
        if self.snapshot_ns:
            ring = self._ring
            ring.append((state, bytes(data), log_ns, publish_ns, sequence, publisher))
            while ring and ring[0][2] < log_ns - self.snapshot_ns:
                ring.popleft()
            return
        if self.numbered and self._split_due(log_ns):  # close the file, start the next one
            self._close_writer()
            self.writer = self._open_writer()
            self._file_started_ns = log_ns
        if not state.registered:
            self._register(state)
        self.writer.write(state.topic, data, log_time_ns=log_ns, publish_time_ns=publish_ns,
                          sequence=sequence or 0)

    # snapshot mode -------------------------------------------------------------------------
    def _on_health(self, msg) -> None:
        level = int(msg.level)
        if level == graph.LEVEL_ERROR and self._health_level != graph.LEVEL_ERROR:
            self.snapshot(f'health ERROR: {msg.message}')
        self._health_level = level

    def _on_status_request(self, request, response):
        """``~/status``: the messages received so far, ``{topic: count}`` as JSON (what a
        harness waits for before it stops the publishers)."""
        response.success = True
        response.message = json.dumps({t: s.counter.received for t, s in self._states.items()})
        return response

    def _on_snapshot_request(self, request, response):
        path = self.snapshot('requested on ~/snapshot')
        response.success = path is not None
        response.message = path or 'nothing to write: no message in the last snapshot_s'
        return response

    def snapshot(self, reason: str) -> Optional[str]:
        """Write the messages of the last ``snapshot_s`` to the next numbered file; returns
        its path (None when the buffer is empty)."""
        entries = list(self._ring)
        if not entries:
            return None
        path = self._next_path()
        writer = McapWriter(path, **self._writer_args)
        self.files.append(str(path))
        counters: Dict[str, SequenceGapCounter] = {}
        for state in self._states.values():
            self._register(state, writer)
        for state, data, log_ns, publish_ns, sequence, publisher in entries:
            counters.setdefault(state.topic, SequenceGapCounter()).add(sequence, publisher)
            writer.write(state.topic, data, log_time_ns=log_ns, publish_time_ns=publish_ns,
                         sequence=sequence or 0)
        writer.lost_counts = {t: c.lost for t, c in counters.items()}
        writer.run_info.update(self._run_info(), snapshot_reason=reason,
                               snapshot_s=self.snapshot_ns / 1e9, stopped_ns=time.time_ns())
        writer.close()
        self.get_logger().info(f'snapshot ({reason}): wrote {path}: {len(entries)} messages')
        return str(path)

    def lost_counts(self) -> Dict[str, int]:
        """Messages lost per topic in the file being written."""
        start = getattr(self, '_lost_at_open', {})
        return {t: s.counter.lost - start.get(t, 0) for t, s in self._states.items()}

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

    def _close_writer(self) -> None:
        """Register silent topics, store lost counts and run info, close the file."""
        for state in self._states.values():
            if not state.registered:
                self._register(state)
        self.writer.lost_counts = self.lost_counts()
        self.writer.run_info.update(self._run_info(), stopped_ns=time.time_ns(),
                                    file_index=len(self.files) - 1)
        self.writer.close()

    def close(self) -> None:
        """Close the file being written (snapshot mode: nothing is written at the end)."""
        if self.writer is None or self.writer.closed:
            return
        stopped_ns = time.time_ns()
        self._close_writer()
        log, counts, lost = self.get_logger(), self.writer.message_counts, self.writer.lost_counts
        where = self.files[-1] if len(self.files) == 1 else f'{len(self.files)} files'
        log.info(f'wrote {where}: {sum(counts.values())} messages, {sum(lost.values())} lost, '
                 f'{(stopped_ns - self.started_ns) / 1e9:.1f} s')
        for topic, state in self._states.items():
            note = '' if state.sequence_numbers else ' (loss detection unavailable)'
            log.info(f'  {topic}: {counts.get(topic, 0)} recorded, '
                     f'{lost.get(topic, 0)} lost{note}')


def main(argv: Optional[List[str]] = None) -> int:
    """Console script ``recorder``; returns the exit status."""
    argv = list(sys.argv if argv is None else argv)
    # the options, each stored under the name of the parameter it sets
    parser = argparse.ArgumentParser(
        prog='recorder', description='Record the actuator graph into an MCAP file.')
    parser.add_argument('-o', '--output', help='MCAP file to create (never overwritten)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='topics to record (default: every graph topic)')
    parser.add_argument('--duration', type=float, metavar='S', dest='duration_s',
                        help='stop after S seconds (default: until SIGINT/SIGTERM)')
    parser.add_argument('-e', '--regex', metavar='RE',
                        help='record only the topics matching RE')
    parser.add_argument('-x', '--exclude-regex', metavar='RE',
                        help='leave out the topics matching RE')
    parser.add_argument('-b', '--max-bag-size', type=int, metavar='BYTES', dest='max_bag_size_b',
                        help='split: next file <stem>_<n>.mcap once one holds BYTES')
    parser.add_argument('-d', '--max-bag-duration', type=float, metavar='S',
                        dest='max_bag_duration_s',
                        help='split: next file <stem>_<n>.mcap once one spans S seconds')
    parser.add_argument('--snapshot', type=float, metavar='S', dest='snapshot_s',
                        help='snapshot mode: keep the last S seconds, write them on the '
                             '~/snapshot service (std_srvs/Trigger) or when /eha/health '
                             'turns ERROR')
    args = parser.parse_args(remove_ros_args(argv)[1:])
    overrides = [Parameter(name, value=value) for name, value in vars(args).items()
                 if value is not None]

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
