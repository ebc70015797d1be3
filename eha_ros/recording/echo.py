"""``eha-echo``: print the messages of a topic, as YAML documents or CSV rows.

Examples::

    eha-echo /eha/state                      # YAML documents separated by ---, until Ctrl-C
    eha-echo /eha/state --csv --count 1000 > state.csv
    eha-echo /eha/health --timeout 30        # wait up to 30 s for the topic to appear

The topic's type is taken from the graph (``get_topic_names_and_types``), waiting up to
``--timeout`` seconds for the topic to appear. The subscription is reliable when every
publisher of the topic is, else best effort. CSV rows hold every field flattened
(``header.stamp.sec``, ...); a sequence field is one cell in JSON. A topic that does not
appear in time, or carries several types, ends the command with one line on stderr and exit
status 2.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from typing import List, Optional

import yaml

from eha_ros.graph import message_class
from eha_ros.recording.arrays import flatten, message_to_plain_data
from eha_ros.recording.stop import StopRequest

__all__ = ['main', 'format_yaml', 'csv_row']

PROG = 'eha-echo'


def format_yaml(msg) -> str:
    """One message as a YAML document (field order kept), ending in ``---``."""
    return yaml.safe_dump(message_to_plain_data(msg), sort_keys=False, allow_unicode=True,
                          default_flow_style=False, width=1 << 16) + '---'


def csv_row(msg) -> dict:
    """One message as ``{flattened field: cell}``; sequences as JSON."""
    return {key: json.dumps(value) if isinstance(value, list) else value
            for key, value in flatten(msg).items()}


def main(argv: Optional[List[str]] = None) -> int:
    """Console script ``eha-echo``; returns the exit status."""
    parser = argparse.ArgumentParser(prog=PROG, description='Print the messages of a topic.')
    parser.add_argument('topic', metavar='TOPIC')
    parser.add_argument('--csv', action='store_true', help='CSV rows instead of YAML')
    parser.add_argument('--count', type=int, metavar='N', help='exit after N messages')
    parser.add_argument('--timeout', type=float, default=5.0, metavar='S',
                        help='seconds to wait for the topic to appear (default 5)')
    args = parser.parse_args(argv)
    if args.count is not None and args.count < 1:
        print(f'{PROG}: error: --count must be >= 1, got {args.count}', file=sys.stderr)
        return 2
    topic = args.topic if args.topic.startswith('/') else '/' + args.topic

    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopRequest()
    try:
        node = rclpy.create_node('eha_echo')
        deadline = time.monotonic() + max(0.0, args.timeout)
        types: List[str] = []
        while not stop.requested:
            types = dict(node.get_topic_names_and_types()).get(topic, [])
            if types or time.monotonic() >= deadline:
                break
            rclpy.spin_once(node, timeout_sec=0.1)
        if stop.requested:
            return 0
        if not types:
            print(f'{PROG}: error: topic {topic} did not appear within {args.timeout:g} s',
                  file=sys.stderr)
            return 2
        if len(types) > 1:
            print(f'{PROG}: error: topic {topic} carries several types: {", ".join(types)}',
                  file=sys.stderr)
            return 2
        try:
            cls = message_class(types[0])
        except ValueError as exc:
            print(f'{PROG}: error: {exc}', file=sys.stderr)
            return 2
        qos = QoSProfile(depth=100)
        publishers = node.get_publishers_info_by_topic(topic)
        if publishers and not all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                  for p in publishers):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if publishers and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                              for p in publishers):  # latched (/eha/events): its history too
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL

        state = {'count': 0, 'writer': None}

        def on_message(msg) -> None:
            if args.count is not None and state['count'] >= args.count:
                return
            if args.csv:
                row = csv_row(msg)
                if state['writer'] is None:
                    state['writer'] = csv.DictWriter(sys.stdout, fieldnames=list(row),
                                                     extrasaction='ignore', lineterminator='\n')
                    state['writer'].writeheader()
                state['writer'].writerow(row)
            else:
                print(format_yaml(msg))
            sys.stdout.flush()
            state['count'] += 1

        node.create_subscription(cls, topic, on_message, qos)
        while not stop.requested and (args.count is None or state['count'] < args.count):
            rclpy.spin_once(node, timeout_sec=0.1)
        return 0
    except BrokenPipeError:  # e.g. piped into `head`
        sys.stderr.close()
        return 0
    finally:
        rclpy.try_shutdown()
        stop.restore()


if __name__ == '__main__':
    sys.exit(main())
