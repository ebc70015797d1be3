"""The start-up handshake: the graph's first tick waits until every endpoint of every node has
matched every peer, counted on both sides, and every ticking node starts its clock at one
common start time.

A reliable, volatile DDS writer sends a sample only to the readers it has matched, and a
reader receives only from the writers it has matched; discovery completes on the two sides at
different moments (one side can lag by seconds on a busy machine). So a message published
before *both* sides of a pair matched is lost for that reader, and nothing reports it. Each
node therefore reports, on the latched ``/eha/handshake`` topic, how many peers each of its
endpoints has matched on its own side (``Publisher.get_subscription_count``,
``Subscription.get_publisher_count``); the plant (the coordinator, ``servovalve_plant``) collects
the reports of the nodes named in its ``handshake_nodes`` parameter and starts when, on every
graph topic, every writer has matched every reader among those nodes and every reader every
writer (:func:`evaluate`). It then publishes its own report with the start time; every node
takes that as the graph's start: the plant's first tick (lockstep) or the common instant at
which the plant, the command generator and a timer-driven controller start their clocks
(realtime), ``start_delay_s`` after the decision so that every node has it in time.

A handshake that does not complete within ``handshake_timeout_s`` fails with one line naming
the node, the endpoint and the topic that never matched (or the node that never reported).

Reports are ``diagnostic_msgs/DiagnosticStatus`` (readable with any ROS tool): ``name`` the
node, ``hardware_id`` its full name, one key-value per endpoint, ``'pub <topic>'`` or
``'sub <topic>'`` with its matched count; the coordinator's start report adds
``start_time_ns`` (system clock), ``mode``, ``nodes`` and ``discovery_s``. Latched topics
(``/eha/events``, the handshake itself) deliver their history to late readers and are not
part of the count.
"""

from __future__ import annotations

import time
from typing import Callable, Dict, Iterable, Optional

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.publisher import Publisher

from eha_ros.graph import is_latched, TOPIC_HANDSHAKE, topic_qos

__all__ = ['COORDINATOR', 'Handshake', 'StartCoordinator', 'evaluate']

#: The node that decides the start (it owns the simulation clock).
COORDINATOR = 'servovalve_plant'

#: Reports a node's handshake reader keeps until it takes them.
READER_DEPTH = 1000

#: How often a node polls its endpoints' matched counts before the start (s).
POLL_S = 0.01


def evaluate(reports: Dict[str, Dict[str, int]], nodes: Iterable[str]) -> Optional[str]:
    """Whether the graph of ``nodes`` may start, from their reports ``{node: {'pub <topic>' |
    'sub <topic>': matched count}}``: None when, on every topic, every writer has matched at
    least as many readers as the nodes have readers of it and every reader at least as many
    writers; else one line naming the first node, endpoint and topic short of its peers (or
    the first node that has not reported)."""
    nodes = list(nodes)
    for node in nodes:
        if node not in reports:
            return f'{node} has not reported (not started, or not discovered yet)'
    ends: Dict[str, Dict[str, list]] = {'pub': {}, 'sub': {}}
    for node in nodes:
        for key, count in reports[node].items():
            kind, _, topic = key.partition(' ')
            if kind in ends:
                ends[kind].setdefault(topic, []).append((node, int(count)))
    for kind, other, what in (('pub', 'sub', 'readers'), ('sub', 'pub', 'writers')):
        for topic, own in sorted(ends[kind].items()):
            peers = ends[other].get(topic, [])
            for node, count in own:
                if count < len(peers):
                    names = ', '.join(n for n, _ in peers)
                    endpoint = 'publisher of' if kind == 'pub' else 'subscription to'
                    return (f"{node}'s {endpoint} {topic} has matched {count} of its "
                            f'{len(peers)} {what} ({names})')
    return None


class Handshake:
    """One node's side of the handshake: report the matched counts of the endpoints given to
    :meth:`watch` whenever they change, until the graph starts; ``on_start(start_ns, mode)`` is
    called once, when the coordinator's start report arrives (``start_ns``: system clock)."""

    def __init__(self, node: Node, on_start: Optional[Callable[[int, str], None]] = None):
        from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
        self.node = node
        self.name = node.get_name()
        self.on_start = on_start
        self.start_ns: Optional[int] = None
        self.mode = ''
        self.reports: Dict[str, Dict[str, int]] = {}
        self.created_monotonic_ns = time.monotonic_ns()
        self._endpoints = []
        self._last = None
        # a writer keeps its last report for late readers; a reader keeps every node's (the
        # topic has one instance: a reader history of 1 would keep one report of all writers)
        self._pub = node.create_publisher(
            DiagnosticStatus, TOPIC_HANDSHAKE, topic_qos(TOPIC_HANDSHAKE, depth=1),
            event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))
        self._sub = node.create_subscription(
            DiagnosticStatus, TOPIC_HANDSHAKE, self._on_report,
            topic_qos(TOPIC_HANDSHAKE, depth=READER_DEPTH),
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        self._timer = node.create_timer(POLL_S, self._poll,
                                        clock=RosClock(clock_type=ClockType.STEADY_TIME))

    @property
    def started(self) -> bool:
        return self.start_ns is not None

    def watch(self, entity, topic: str) -> None:
        """Count ``entity`` (a publisher or a subscription on ``topic``) in the handshake;
        latched topics are left out (their readers get the history)."""
        if is_latched(topic):
            return
        kind = 'pub' if isinstance(entity, Publisher) else 'sub'
        self._endpoints.append((kind, topic, entity))

    def counts(self) -> Dict[str, int]:
        """``{'pub <topic>' | 'sub <topic>': matched count}`` of the watched endpoints (the
        smallest where a node has several on one topic)."""
        out: Dict[str, int] = {}
        for kind, topic, entity in self._endpoints:
            n = (entity.get_subscription_count() if kind == 'pub'
                 else entity.get_publisher_count())
            key = f'{kind} {topic}'
            out[key] = min(n, out.get(key, n))
        return out

    def _report(self, counts: Dict[str, int], message: str = 'matched endpoints',
                extra: Optional[Dict[str, str]] = None) -> None:
        msg = DiagnosticStatus(name=self.name, message=message,
                               hardware_id=self.node.get_fully_qualified_name())
        msg.level = DiagnosticStatus.OK
        msg.values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
        msg.values += [KeyValue(key=k, value=str(v)) for k, v in (extra or {}).items()]
        self._pub.publish(msg)

    def _poll(self) -> None:
        if self.started:
            return
        counts = self.counts()
        if counts != self._last:
            self._last = counts
            self._report(counts)

    def _on_report(self, msg: DiagnosticStatus) -> None:
        values = {kv.key: kv.value for kv in msg.values}
        self.reports[msg.name] = {k: int(v) for k, v in values.items()
                                  if k.startswith(('pub ', 'sub '))}
        if msg.name == COORDINATOR and 'start_time_ns' in values and not self.started:
            self._begin(int(values['start_time_ns']), values.get('mode', ''))

    def _begin(self, start_ns: int, mode: str) -> None:
        self.start_ns = start_ns
        self.mode = mode
        self._timer.cancel()
        if self.on_start is not None:
            self.on_start(start_ns, mode)

    def start_monotonic_ns(self) -> int:
        """The start time on this process's monotonic clock."""
        return time.monotonic_ns() + (self.start_ns - time.time_ns())


class StartCoordinator(Handshake):
    """The coordinator's side (the plant): waits for the reports of ``nodes`` (itself
    included) until :func:`evaluate` passes, then publishes the start, ``start_delay_s`` ahead
    in realtime (at once in lockstep). After ``timeout_s`` (0: never) without a start it sets
    ``error`` to one line saying what never matched; it logs what it waits for every
    ``log_every_s``."""

    def __init__(self, node: Node, nodes: Iterable[str], mode: str, timeout_s: float,
                 start_delay_s: float, on_start=None, log_every_s: float = 5.0):
        self.nodes = list(dict.fromkeys(list(nodes) + [node.get_name()]))
        self.start_monotonic_exact_ns: Optional[int] = None
        self.mode_name = mode
        self.timeout_s = float(timeout_s)
        self.start_delay_s = float(start_delay_s)
        self.error: Optional[str] = None
        self.problem: Optional[str] = None
        self._log_every_ns = round(log_every_s * 1e9)
        super().__init__(node, on_start)
        self._next_log_ns = self.created_monotonic_ns + self._log_every_ns

    def _poll(self) -> None:
        if self.started or self.error:
            return
        counts = self.counts()
        self.reports[self.name] = counts
        problem = evaluate(self.reports, self.nodes)
        now = time.monotonic_ns()
        if problem is None:
            delay = self.start_delay_s if self.mode_name == 'realtime' else 0.0
            start_mono = now + round(delay * 1e9)
            self.start_monotonic_exact_ns = start_mono
            start_ns = start_mono + (time.time_ns() - time.monotonic_ns())
            discovery = (now - self.created_monotonic_ns) * 1e-9
            self._report(counts, 'start', {'start_time_ns': start_ns, 'mode': self.mode_name,
                                           'nodes': ','.join(self.nodes),
                                           'discovery_s': f'{discovery:.3f}'})
            self.node.get_logger().info(f'handshake complete after {discovery:.2f} s '
                                        f'({", ".join(self.nodes)}): starting')
            self._begin(start_ns, self.mode_name)
            return
        if counts != self._last or problem != self.problem:
            self._last = counts
            self._report(counts, f'waiting: {problem}')
        self.problem = problem
        waited = (now - self.created_monotonic_ns) * 1e-9
        if self.timeout_s > 0 and waited > self.timeout_s:
            self.error = (f'start-up handshake incomplete after {self.timeout_s:g} s: '
                          f'{problem}')
            self._timer.cancel()
        elif now >= self._next_log_ns:
            self._next_log_ns = now + self._log_every_ns
            self.node.get_logger().info(f'waiting for the graph ({waited:.0f} s): {problem}')
