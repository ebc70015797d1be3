"""The harness's own rclpy node (:class:`Collector`): it subscribes to every graph topic,
keeps what arrives as columns of numbers, counts what the publishers' sequence numbers say
was lost, takes part in the start-up handshake and hands the run's :class:`GraphResult`
back; :func:`evaluate_reports` says what the handshake still waits for."""

from __future__ import annotations

from array import array
import time

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node

from eha_ros.graph import (QOS_DEPTH, RUN_ENDED, SNAPSHOT_FIELDS, TIMING_SUFFIX, TOPIC_COMMAND,
                           TOPIC_DIAGNOSTICS, TOPIC_EVENTS, TOPIC_HEALTH, TOPIC_SERVOVALVE,
                           TOPIC_STATE, WATCHDOG_SUFFIX, graph_qos, topic_qos)
from eha_ros.msg import (ActuatorCommand, ActuatorState, GraphEvent, HealthStatus,
                         ServovalveCommand)
from eha_ros.nodes.common import stamp_to_ns, take_waiting
from eha_ros.nodes.handshake import evaluate, Handshake
from eha_ros.recording.definitions import SequenceGapCounter

from .config import COLLECTOR, TICKING_NODES
from .result import GraphResult, missing_ticks

STATE_FIELDS = SNAPSHOT_FIELDS + ('sim_time_s', 'supply_pressure_measured_pa',
                                  'return_pressure_measured_pa', 'fluid_temperature_measured_k')
#: Integer fields of the state kept as they are (a flag as 0 or 1).
_STATE_COUNTS = ('tick', 'status', 'valve_test_point', 'valve_test_point_end',
                 'valve_test_procedure', 'command_age_ticks')
_STATE_INTS = ('stamp_ns',) + _STATE_COUNTS + ('safe_action',)


class Collector:
    """The harness's node: subscribes to every graph topic, counts what arrives and what the
    publishers' sequence numbers say was lost, and takes part in the start-up handshake.

    The data subscriptions belong to a second node that no executor spins: :meth:`poll` takes
    their messages with their sequence numbers (rclpy's ``EventsExecutor`` cannot hand a
    callback the message info), which also costs less than an executor pass per message. Each
    keeps ``QOS_DEPTH`` samples, a second at 1 kHz, so polling every few milliseconds loses
    nothing."""

    #: Poll at least this often (s).
    POLL_S = 0.005

    def __init__(self, context):
        self.node = Node(COLLECTOR, context=context, start_parameter_services=False)
        self.data_node = Node(COLLECTOR + '_data', context=context,
                              start_parameter_services=False)
        # columns of plain numbers, not messages: a run's worth of messages kept as objects
        # would make every full garbage collection of this process (the graph's own in one
        # process) traverse them
        self.state_cols = {f: array('d') for f in STATE_FIELDS + ('arrival_s',)}
        self.state_cols.update({f: array('q') for f in _STATE_INTS})
        self.command_cols = {'stamp_ns': array('q'), 'position_setpoint_m': array('d')}
        self.current_cols = {'stamp_ns': array('q'), 'current_command_a': array('d'),
                             'arrival_s': array('d'), 'state_timeout': array('q')}
        self.health = []
        self.events, self.diagnostics = [], {}
        self.counters = {}
        self.handshake = Handshake(self.node)
        self._subs = []
        self._last_poll = 0.0
        self._watchdog_changes = self._watchdog_trips = 0

        cols, fields = self.state_cols, STATE_FIELDS + _STATE_COUNTS

        def on_state(msg, now):
            for f in fields:
                cols[f].append(getattr(msg, f))
            cols['arrival_s'].append(now)
            cols['stamp_ns'].append(stamp_to_ns(msg.header.stamp))
            before = cols['safe_action'][-1] if cols['safe_action'] else 0
            if msg.safe_action != before:
                self._watchdog_changes += 1   # the plant published a trip or a resumption
                self._watchdog_trips += not before
            cols['safe_action'].append(msg.safe_action)

        def on_command(msg, now):
            self.command_cols['stamp_ns'].append(stamp_to_ns(msg.header.stamp))
            self.command_cols['position_setpoint_m'].append(msg.position_setpoint_m)

        def on_current(msg, now):
            self.current_cols['stamp_ns'].append(stamp_to_ns(msg.header.stamp))
            self.current_cols['current_command_a'].append(msg.current_command_a)
            self.current_cols['arrival_s'].append(now)
            self.current_cols['state_timeout'].append(int(msg.state_timeout))

        def on_diagnostics(msg, now):
            for st in msg.status:
                self.diagnostics[st.name] = {
                    'level': int.from_bytes(st.level, 'little') if isinstance(st.level, bytes)
                    else int(st.level), 'message': st.message,
                    'values': {kv.key: kv.value for kv in st.values}}

        qos = graph_qos(QOS_DEPTH)
        for cls, topic, callback in (
                (ActuatorState, TOPIC_STATE, on_state),
                (ActuatorCommand, TOPIC_COMMAND, on_command),
                (ServovalveCommand, TOPIC_SERVOVALVE, on_current),
                (HealthStatus, TOPIC_HEALTH, lambda m, _: self.health.append(m)),
                (DiagnosticArray, TOPIC_DIAGNOSTICS, on_diagnostics)):
            sub = self.data_node.create_subscription(
                cls, topic, lambda m: None, qos,
                event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
            self.counters[topic] = SequenceGapCounter()
            self._subs.append((sub, cls, self.counters[topic], callback))
            self.handshake.watch(sub, topic)
        self.node.create_subscription(GraphEvent, TOPIC_EVENTS, self._on_event,
                                      topic_qos(TOPIC_EVENTS))

    def poll(self, force: bool = False) -> None:
        """Take every message waiting on the data subscriptions (at most every ``POLL_S``
        unless ``force``)."""
        now = time.monotonic()
        if not force and now - self._last_poll < self.POLL_S:
            return
        self._last_poll = now
        # receipt times: the middleware's (system clock), on the monotonic clock
        offset_ns = time.time_ns() - time.monotonic_ns()
        for sub, cls, counter, callback in self._subs:
            for msg, info in take_waiting(sub, cls):
                gid = info.get('publisher_gid')
                counter.add(info.get('publication_sequence_number'),
                            bytes(gid['data']) if gid else None)
                received = info.get('received_timestamp')
                callback(msg, (received - offset_ns) * 1e-9 if received else now)

    def destroy(self) -> None:
        self.data_node.destroy_node()
        self.node.destroy_node()

    def _on_event(self, msg):
        self.events.append({
            'stamp_ns': stamp_to_ns(msg.header.stamp),
            'tick_index': int(msg.tick_index), 'node': msg.node, 'source': msg.source,
            'scheduled_time_s': float(msg.scheduled_time_s),
            'changes': dict(zip(msg.parameter_names, (float(v) for v in msg.parameter_values)))})

    def events_in_flight(self, config) -> int:
        """How many of the plant's events and statuses its states show it has published have
        not arrived: a watchdog trip or resumption (the states' ``safe_action`` changed), a
        scheduled change (a state stamped a tick past its time), and the command watchdog's
        ``/diagnostics`` status after the last trip or resumption (its trip count and action
        in force).  Each topic is reliable but apart from the states: a sample lost on a
        loaded machine comes again only at the writer's next heartbeat (seconds), after the
        states that followed it."""
        if not self.n_states:
            return 0
        period_ns = round(1e9 / config.rate_hz)
        last = self.last_stamp_ns
        scheduled = {t_s for t_s, node, _ in config.all_events()
                     if node == 'servovalve_plant' and round(t_s * 1e9) + period_ns <= last}
        seen = [e for e in self.events if e['node'] == 'servovalve_plant']
        status = self.diagnostics.get('servovalve_plant' + WATCHDOG_SUFFIX, {}).get('values', {})
        trips, shown = self._watchdog_trips, int(status.get('Trips since startup', 0))
        in_force = self.state_cols['safe_action'][-1] != 0
        behind = trips and (shown < trips or shown == trips and in_force
                            != (status.get('Action in force', 'none') != 'none'))
        return (max(0, self._watchdog_changes - sum(e['source'] == 'watchdog' for e in seen))
                + max(0, len(scheduled) - sum(e['source'] == 'schedule' for e in seen))
                + int(bool(behind)))

    @property
    def n_states(self) -> int:
        return len(self.state_cols['tick'])

    @property
    def last_stamp_ns(self) -> int:
        return self.state_cols['stamp_ns'][-1]

    @property
    def last_status(self) -> int:
        return self.state_cols['status'][-1]

    def final_answers_in(self) -> bool:
        """Lockstep: the command and the current command of the last state's tick arrived."""
        if not self.n_states:
            return True
        last = self.last_stamp_ns
        # a plant running on stale commands (a silent or dead controller) gets no answer
        unanswered = self.state_cols['command_age_ticks'][-1] > 0
        return ((unanswered or last in self.current_cols['stamp_ns'][-3:])
                and last in self.command_cols['stamp_ns'][-3:])

    def behind(self, recorded: dict) -> dict:
        """``{topic: (recorded, received here)}`` of the data topics (states, position and
        current commands) of which the recorder's ``~/status`` counts, ``recorded``, are short
        of what the collector received."""
        return {t: (recorded[t], self.counters[t].received)
                for t in (TOPIC_STATE, TOPIC_COMMAND, TOPIC_SERVOVALVE)
                if t in recorded and recorded[t] < self.counters[t].received}

    def timing_ended(self) -> bool:
        """Every ticking node's final timing report (``RUN_ENDED``) arrived: the timing of the
        whole run, also of one shorter than the reports' window."""
        return all(self.diagnostics.get(n + TIMING_SUFFIX, {}).get('values', {}).get(RUN_ENDED)
                   == '1' for n in TICKING_NODES)

    def result(self, config, t0: float) -> 'GraphResult':
        """What arrived; ``t0``: when the nodes were launched (``time.monotonic``)."""
        start = self.handshake.start_monotonic_ns() * 1e-9 if self.handshake.started else t0
        arrivals = self.state_cols['arrival_s']
        wall = max(0.0, (arrivals[-1] if len(arrivals) else time.monotonic()) - start)

        def columns(cols):
            """Arrays; in lockstep a tick the plant re-sent (and the controller's repeated
            answer) carries the same content: the first of each stamp is kept."""
            out = {k: np.array(v, dtype=np.float64 if v.typecode == 'd' else np.int64)
                   for k, v in cols.items()}
            if config.mode == 'lockstep' and out['stamp_ns'].size:
                _, first = np.unique(out['stamp_ns'], return_index=True)
                keep = np.sort(first)
                out = {k: v[keep] for k, v in out.items()}
            return out
        state = columns(self.state_cols)
        state['valve_test_point_end'] = state['valve_test_point_end'].astype(bool)
        resent = self.n_states - state['tick'].size
        command = columns(self.command_cols)
        servo = columns(self.current_cols)
        missing = missing_ticks(config, state['stamp_ns'], command['stamp_ns'], servo['stamp_ns'])
        return GraphResult(state, command, servo, list(self.health), wall, config, resent,
                           diagnostics=dict(self.diagnostics), events=list(self.events),
                           discovery_s=max(0.0, start - t0),
                           messages={t: c.received for t, c in self.counters.items()},
                           lost={t: c.lost for t, c in self.counters.items()},
                           missed_at_start={t: c.missed_at_start
                                            for t, c in self.counters.items()},
                           missing=missing)


def evaluate_reports(collector, config) -> str:
    """What the handshake still waits for, from the reports the collector has seen."""
    reports = dict(collector.handshake.reports)
    reports[COLLECTOR] = collector.handshake.counts()
    return evaluate(reports, config.nodes()) or 'every endpoint matched, but no start arrived'
