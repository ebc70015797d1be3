"""Helpers for tests of the messages: distinctive sample messages and cross-process round trips.

Isolated environments for ROS 2 processes are in :mod:`eha_ros.isolation`.

The module is also a small command-line tool that tests start as separate processes::

    python -m eha_ros.testing pub [--timeout S]   # publish sample_message() of every type
    python -m eha_ros.testing sub [--timeout S]   # print the first message of every type as JSON

Start these with a working directory outside the source tree (``python -m`` puts the working
directory first on ``sys.path``, and the source tree has no generated ``eha_ros.msg``).
"""

import argparse
from contextlib import suppress
import json
import math
import os
import signal
import struct
import sys
import threading
import time
from typing import Dict

from eha_ros import graph


class SignalAfter:
    """Fault injection for a :class:`eha_ros.harness.GraphRun`, as its ``stop`` callable
    (which never stops the run): ``sig`` to node process ``victim`` once the harness has
    received ``after`` states, and SIGCONT ``cont_after_s`` later if given; ``sent_at``: the
    ``time.monotonic`` of the signal (None before it)."""

    def __init__(self, run, victim: str, sig: int, after: int,
                 cont_after_s: float | None = None):
        self.run, self.victim, self.sig, self.after = run, victim, sig, after
        self.cont_after_s = cont_after_s
        self.sent_at = None
        self._continued = False

    def __call__(self) -> bool:
        c = self.run.collector
        if self.sent_at is None and c is not None and c.n_states >= self.after:
            os.kill(self.run.pids[self.victim], self.sig)
            self.sent_at = time.monotonic()
        if (self.cont_after_s is not None and self.sent_at is not None and not self._continued
                and time.monotonic() >= self.sent_at + self.cont_after_s):
            os.kill(self.run.pids[self.victim], signal.SIGCONT)
            self._continued = True
        return False


#: The package's message types, in ``eha_ros.msg``.
MESSAGE_TYPES = ('ActuatorCommand', 'ServovalveCommand', 'ActuatorState', 'HealthStatus',
                 'GraphEvent')

#: Topic prefix used by the ``pub``/``sub`` commands; one topic per message type.
TOPIC_PREFIX = '/eha_ros_test'


# --- sample messages ------------------------------------------------------------------------

def message_class(name: str) -> type:
    """Return the class ``eha_ros.msg.<name>`` (or ``pkg/msg/Name``, ``pkg/Name``)."""
    return graph.message_class(name if '/' in name else f'eha_ros/msg/{name}')


def _float32(value: float) -> float:
    return struct.unpack('<f', struct.pack('<f', value))[0]


_INT_LIMITS = {'octet': (0, 255), 'char': (0, 255),
               **{f'int{b}': (-2 ** (b - 1), 2 ** (b - 1) - 1) for b in (8, 16, 32, 64)},
               **{f'uint{b}': (0, 2 ** b - 1) for b in (8, 16, 32, 64)}}


def _sample_value(cls: type, name: str, type_name: str, index: int):
    """A distinctive, non-default value for one field (see :func:`sample_message`)."""
    if type_name.startswith('sequence<') or '[' in type_name:
        inner = type_name.split('<', 1)[1].rstrip('>').split(',')[0] \
            if type_name.startswith('sequence<') else type_name.split('[')[0]
        size = int(type_name.split('[')[1].rstrip(']')) if '[' in type_name else 3
        return [_sample_value(cls, name, inner, index + k) for k in range(size)]
    if '/' in type_name:
        return sample_message(message_class(type_name), seed=index)
    if type_name in ('double', 'float'):
        # Irrational mantissas over several decades, alternating sign: every bit matters.
        value = (-1) ** index * math.pi * (index + 1) * 10.0 ** (index % 7 - 3)
        return _float32(value) if type_name == 'float' else value
    if type_name in ('string', 'wstring') or type_name.startswith(('string<', 'wstring<')):
        return f'{name} #{index}: Δp·Q ✓'
    if type_name == 'boolean':
        return True
    if type_name in _INT_LIMITS:
        group = {n: getattr(cls, n) for n in dir(cls) if n.startswith(name.upper() + '_')
                 and n.isupper() and not callable(getattr(cls, n))}
        if group:
            return max(group.values())  # a named constant, and not the default (0)
        if name == 'sec':
            return 1_700_000_000 + index  # keep a valid time
        if name == 'nanosec':
            return 999_999_937 - index
        low, high = _INT_LIMITS[type_name]
        if low == 0:  # high and distinct; wraps only where a narrow type runs out (uint8[])
            return high - index if index <= high else high - index % (high // 2)
        return low + index + 1
    raise NotImplementedError(f'no sample value for {cls.__name__}.{name} of type {type_name}')


def sample_message(cls: type, seed: int = 0):
    """Return an instance of ``cls`` with a distinctive non-default value in every field.

    Floats use irrational mantissas (so a lost bit shows), integers sit at the top of their
    range (sign and high bits), fields with ``<FIELD>_*`` constants take the largest constant,
    strings hold non-ASCII UTF-8, nested messages (``header``) are filled the same way. The
    result is deterministic: two processes build equal messages.
    """
    msg = cls()
    for index, (name, type_name) in enumerate(cls.get_fields_and_field_types().items()):
        setattr(msg, name, _sample_value(cls, name, type_name, seed + index + 1))
    return msg


def message_to_bitwise_json(msg) -> dict:
    """Convert a message to JSON-compatible data that compares floats bit for bit.

    Floats become ``float.hex()`` strings, nested messages nested dicts, arrays lists.
    """
    def convert(value):
        if hasattr(value, 'get_fields_and_field_types'):
            return {k: convert(getattr(value, k)) for k in value.get_fields_and_field_types()}
        if isinstance(value, float):
            return value.hex()
        if isinstance(value, (bool, int, str)):
            return value
        if hasattr(value, 'tolist'):
            return convert(value.tolist())
        if isinstance(value, (list, tuple)):
            return [convert(v) for v in value]
        if hasattr(value, 'item'):  # numpy scalar
            return convert(value.item())
        raise TypeError(f'cannot convert {type(value).__name__}')

    return {'type': type(msg).__name__, 'fields': convert(msg)}


def topic_name(type_name: str) -> str:
    """Topic the ``pub``/``sub`` commands use for a message type."""
    snake = ''.join('_' + c.lower() if c.isupper() else c for c in type_name).lstrip('_')
    return f'{TOPIC_PREFIX}/{snake}'


# --- pub / sub commands ---------------------------------------------------------------------

def _qos():
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def run_publisher(timeout_s: float, period_s: float = 0.05) -> int:
    """Publish :func:`sample_message` of every type until stdin closes or ``timeout_s``.

    First waits (at most ``timeout_s``) until every publisher has matched a subscriber.
    Returns the exit status: 0, or 2 when no subscriber matched.
    """
    import rclpy

    stop = threading.Event()

    def watch_stdin():
        with suppress(OSError, ValueError):
            while sys.stdin.read(1):
                pass
        stop.set()

    threading.Thread(target=watch_stdin, daemon=True).start()
    rclpy.init()
    try:
        node = rclpy.create_node('eha_ros_test_publisher')
        publishers = [(node.create_publisher(message_class(t), topic_name(t), _qos()),
                       sample_message(message_class(t))) for t in MESSAGE_TYPES]
        deadline = time.monotonic() + timeout_s
        while any(p.get_subscription_count() == 0 for p, _ in publishers):
            if time.monotonic() > deadline or stop.is_set():
                print(f'no subscriber matched within {timeout_s} s', file=sys.stderr)
                return 2
            rclpy.spin_once(node, timeout_sec=0.02)
        while not stop.is_set() and time.monotonic() < deadline:
            for publisher, msg in publishers:
                publisher.publish(msg)
            stop.wait(period_s)
        return 0
    finally:
        rclpy.try_shutdown()


def run_subscriber(timeout_s: float) -> int:
    """Print, as one JSON line, the first message received of every type.

    The JSON object maps type name to :func:`message_to_bitwise_json`, plus ``eha_ros_file`` (where
    ``eha_ros`` was imported from). Returns 0, or 1 when some type was not received in time.
    """
    import rclpy

    import eha_ros

    received: Dict[str, dict] = {}
    rclpy.init()
    try:
        node = rclpy.create_node('eha_ros_test_subscriber')
        for type_name in MESSAGE_TYPES:
            def callback(msg, type_name=type_name):
                received.setdefault(type_name, message_to_bitwise_json(msg))
            node.create_subscription(message_class(type_name), topic_name(type_name),
                                     callback, _qos())
        deadline = time.monotonic() + timeout_s
        while len(received) < len(MESSAGE_TYPES) and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        rclpy.try_shutdown()
    print(json.dumps({'messages': received, 'eha_ros_file': eha_ros.__file__}), flush=True)
    missing = sorted(set(MESSAGE_TYPES) - set(received))
    if missing:
        print(f'not received within {timeout_s} s: {", ".join(missing)}', file=sys.stderr)
        return 1
    return 0


def main(argv=None) -> int:
    """Command line; see the module docstring."""
    parser = argparse.ArgumentParser(prog='python -m eha_ros.testing')
    parser.add_argument('command', choices=('pub', 'sub'))
    parser.add_argument('--timeout', type=float, default=20.0, help='seconds (default 20)')
    args = parser.parse_args(argv)
    return run_publisher(args.timeout) if args.command == 'pub' else run_subscriber(args.timeout)


if __name__ == '__main__':
    sys.exit(main())
