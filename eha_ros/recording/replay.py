"""``eha-replay``: republish a recording with its recorded timing, and ``/clock``.

Examples::

    eha-replay run1.mcap                         # every graph topic in the file, real time
    eha-replay run1.mcap --rate 0.5 --topics /eha/state /eha/command
    eha-replay run1.mcap --loop                  # until Ctrl-C

Messages are published in file order, as recorded (serialized CDR, not re-encoded), each at
its recorded log time relative to the first one, scaled by ``1/rate``. ``/clock`` follows the
recording so that nodes with ``use_sim_time`` run on it: where the file holds ``/clock`` and it
is replayed, its recorded messages are republished; otherwise a ``/clock`` message carrying the
recorded log time is published before each message whose log time moved on (``--no-clock``
turns that off). Publishers offer the QoS recorded for each topic (reliability and durability;
the graph's history depth).

The whole file is checked before anything is published: a missing, truncated, damaged or
non-MCAP file, a file holding none of the graph's topics, or a ``--topics`` entry that is not a
graph topic or has no messages in the file ends the command with one line on stderr and exit
status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Dict, List, Optional

import yaml

from eha_ros import graph
from eha_ros.recording.arrays import truncation_warning
from eha_ros.recording.definitions import RecordingError, TruncatedError
from eha_ros.recording.reader import McapReader, RecordingInfo, scan
from eha_ros.recording.stop import StopRequest

__all__ = ['main', 'topics_to_replay', 'ReplayError']

PROG = 'eha-replay'


class ReplayError(ValueError):
    """Bad input: the message is the one line printed."""


def topics_to_replay(info: RecordingInfo, requested: Optional[List[str]],
                     namespace: str = graph.NAMESPACE) -> Dict[str, str]:
    """Topics to replay (``topic -> type``): ``requested`` checked against the graph and the
    file, or every graph topic that has messages in the file.

    Raises
    ------
    ReplayError
        If a requested topic is not a graph topic or has no messages in the file, or the file
        holds none of the graph's topics.
    """
    known = graph.topics_in(namespace)
    in_file = {t: c.type_name for t, c in info.channels.items()
               if info.message_counts.get(t, 0) > 0}
    if requested:
        out = {}
        for topic in requested:
            if topic not in known:
                raise ReplayError(f'unknown topic {topic!r}: the graph has '
                                  f'{", ".join(sorted(known))}')
            if topic not in in_file:
                raise ReplayError(f'the file has no messages on {topic} (it has '
                                  f'{", ".join(sorted(in_file)) or "none"})')
            out[topic] = in_file[topic]
        return out
    out = {t: ty for t, ty in in_file.items() if t in known}
    if not out:
        raise ReplayError(f'the file holds none of the graph topics '
                          f'({", ".join(sorted(known))}); it has '
                          f'{", ".join(sorted(in_file)) or "no messages"}')
    return out


def _publisher_qos(info: RecordingInfo, topic: str):
    """Reliability and durability every recorded publisher offered; the graph's depth."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    qos = graph.graph_qos()
    try:
        profiles = yaml.safe_load(
            info.channels[topic].metadata.get('offered_qos_profiles', '')) or []
    except yaml.YAMLError:
        profiles = []
    if profiles:
        if all(str(p.get('reliability')) == 'best_effort' for p in profiles):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if all(str(p.get('durability')) == 'transient_local' for p in profiles):
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
    return qos


def main(argv: Optional[List[str]] = None) -> int:
    """Console script ``eha-replay``; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog=PROG, description='Republish a recording with its recorded timing and /clock.')
    parser.add_argument('file', metavar='FILE.mcap')
    parser.add_argument('--rate', type=float, default=1.0, metavar='R',
                        help='playback speed factor (default 1: recorded timing)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='topics to replay (default: every graph topic in the file)')
    parser.add_argument('--loop', action='store_true', help='start again at the end')
    parser.add_argument('--no-clock', action='store_true',
                        help='publish no /clock unless it is a replayed topic')
    parser.add_argument('--namespace', default=graph.NAMESPACE,
                        help=f'namespace of the actuator topics (default {graph.NAMESPACE})')
    parser.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                        help='wait up to S seconds for every topic to have a subscriber')
    args = parser.parse_args(argv)
    if not args.rate > 0:
        print(f'{PROG}: error: --rate must be > 0, got {args.rate}', file=sys.stderr)
        return 2
    try:
        try:
            info = scan(args.file, strict=True)
        except TruncatedError as exc:  # a killed recorder's file: replay what it holds
            info = scan(args.file)
            print(truncation_warning(PROG, args.file, str(exc),
                                     sum(info.message_counts.values()), 'messages'),
                  file=sys.stderr)
        selected = topics_to_replay(info, args.topics, args.namespace)
    except (RecordingError, ReplayError) as exc:
        print(f'{PROG}: error: {" ".join(str(exc).split())}', file=sys.stderr)
        return 2
    except OSError as exc:
        print(f'{PROG}: error: cannot read {args.file}: {exc.strerror or exc}', file=sys.stderr)
        return 2

    import rclpy
    from rclpy.duration import Duration
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock

    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopRequest()
    try:
        node = rclpy.create_node('eha_replay')
        publishers = {topic: node.create_publisher(graph.message_class(type_name), topic,
                                                   _publisher_qos(info, topic))
                      for topic, type_name in selected.items()}
        synth_clock = (node.create_publisher(Clock, graph.TOPIC_CLOCK, graph.graph_qos())
                       if graph.TOPIC_CLOCK not in selected and not args.no_clock else None)
        if args.wait_for_subscribers > 0:
            deadline = time.monotonic() + args.wait_for_subscribers
            waiting = list(publishers.values())
            while waiting and time.monotonic() < deadline and not stop.requested:
                waiting = [p for p in waiting if p.get_subscription_count() == 0]
                time.sleep(0.02)
            if waiting:
                names = ', '.join(p.topic_name for p in waiting)
                print(f'{PROG}: warning: no subscriber on {names} after '
                      f'{args.wait_for_subscribers} s; replaying anyway', file=sys.stderr)

        total = 0
        began = time.monotonic()
        while not stop.requested:
            start = time.monotonic()
            first_log = last_clock = None
            for msg in McapReader(args.file, topics=list(selected), decode=False,
                                  strict=info.complete):
                if stop.requested:
                    break
                if first_log is None:
                    first_log = msg.log_time_ns
                due = start + (msg.log_time_ns - first_log) / 1e9 / args.rate
                while not stop.requested and (left := due - time.monotonic()) > 0:
                    time.sleep(min(left, 0.1))
                if synth_clock is not None and msg.log_time_ns != last_clock:
                    clock = Clock()
                    clock.clock.sec, clock.clock.nanosec = divmod(msg.log_time_ns,
                                                                  1_000_000_000)
                    synth_clock.publish(clock)
                    last_clock = msg.log_time_ns
                publishers[msg.topic].publish(msg.data)
                total += 1
            if not args.loop:
                break
        for publisher in list(publishers.values()) + ([synth_clock] if synth_clock else []):
            publisher.wait_for_all_acked(Duration(seconds=2.0))
        print(f'{PROG}: replayed {total} messages on {len(selected)} topics in '
              f'{time.monotonic() - began:.2f} s', file=sys.stderr)
        return 0
    except RecordingError as exc:
        print(f'{PROG}: error: {" ".join(str(exc).split())}', file=sys.stderr)
        return 2
    finally:
        rclpy.try_shutdown()
        stop.restore()


if __name__ == '__main__':
    sys.exit(main())
