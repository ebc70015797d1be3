"""Launch-free harness: start the node graph, run a scenario to completion, stop every node
cleanly and return what was published.

Two ways to start the graph:

* ``processes=True`` - each node is its installed console script in its own process (as
  ``ros2 run`` would start it), with ``--ros-args -p name:=value`` parameters;
* ``processes=False`` - all nodes in this process on one executor.

Either way a collector node in this process records ``/eha/state``, ``/eha/command``,
``/eha/servovalve_command``, ``/eha/health``, ``/diagnostics`` and ``/eha/events``, and counts
what the publishers' sequence numbers say it missed.  The graph starts only when every node's
endpoints, the collector's included, have matched their peers (the start-up handshake,
:mod:`eha_ros.nodes.handshake`).  Example::

    from eha_ros.harness import GraphConfig, GraphRun, run_graph
    result = run_graph(GraphConfig(scenario='step_0p1', model='hf', mode='lockstep'))
    result.state['jack_position_m']
    with GraphRun(GraphConfig(scenario='step_0p1')) as run:  # the same in steps
        run.pids             # {node: pid} of the node processes
        result = run.wait()  # the nodes are stopped, the recording (if any) complete

In the tests, the ``eha_graph`` fixture (``test/conftest.py``) does the same in an isolated
ROS domain.
"""

from __future__ import annotations

from array import array
import dataclasses
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ['GraphConfig', 'GraphResult', 'GraphError', 'GraphConfigError', 'GraphDataLoss',
           'GraphFault', 'GraphRun', 'run_graph', 'declared_parameters', 'COLLECTOR']

STATE_FIELDS = ('jack_position_m', 'jack_position_measured_m', 'jack_velocity_m_s',
                'spool_position_m', 'flapper_position_m', 'p1_pa', 'p2_pa', 'p12_pa',
                'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n', 'sim_time_s',
                'supply_pressure_measured_pa', 'return_pressure_measured_pa',
                'fluid_temperature_measured_k')
_STATE_INTS = ('stamp_ns', 'tick', 'status', 'valve_test_point', 'valve_test_point_end',
               'valve_test_procedure', 'command_age_ticks', 'safe_action')

#: The harness's own node, which collects what the graph publishes.
COLLECTOR = 'eha_harness_collector'

#: After a stop request, how long node processes get to end on their own before the harness
#: signals them (s): a second SIGINT could hit a recorder after it restored its handlers.
_GRACE_S = 3.0

#: How long the harness waits, past the plant's own handshake timeout counted from the plant's
#: first report, for the start (s): the plant's own watchdog fires first and names the cause.
_START_MARGIN_S = 15.0
#: How long a node process may take to come up and report at all (s): imports and kernel
#: compilation on a loaded machine take tens of seconds; one silent for this long is stuck.
_REPORT_DEADLINE_S = 180.0

#: Real-time settings ``GraphConfig.rt`` gives each ticking node.
TICKING_NODES = ('command_generator', 'controller', 'servovalve_plant')


class GraphError(RuntimeError):
    """The graph did not start, stalled, or a node failed."""


class GraphConfigError(GraphError, ValueError):
    """A :class:`GraphConfig` asks for something no node has (an unknown node, parameter or
    event target): refused before anything starts."""


class GraphDataLoss(GraphError):
    """A lockstep run ended with messages missing; ``result`` holds what arrived."""

    def __init__(self, message: str, result: 'GraphResult'):
        super().__init__(message)
        self.result = result


class GraphFault(GraphDataLoss):
    """A node died or hung mid-run: the rest were stopped cleanly (the recording closed
    with everything up to the fault); ``result`` holds what arrived, its ``fault`` says which
    node, when and how, and it is not :attr:`~GraphResult.complete`."""


#: How long the plant may publish no state, once the graph has started, before the harness
#: calls it hung (s): realtime; in lockstep the plant's own wait for a missing command
#: (``command_wait_s``) comes first.
HEARTBEAT_S = 1.0
#: After a node other than the plant fails mid-run, how much simulated time the harness goes
#: on collecting before it stops the rest (s): long enough for the plant's command watchdog
#: (20 ms by default) to act, so that the result and the recording show the safe action; at
#: most ``FAULT_GRACE_WALL_S`` of wall time (a lockstep plant waits ``command_wait_s``), and
#: on until the events the states show were published have arrived
#: (:meth:`_Collector.events_in_flight`).
FAULT_GRACE_S = 0.3
FAULT_GRACE_WALL_S = 5.0


@dataclasses.dataclass
class GraphConfig:
    """What to run.  ``plant`` holds extra plant parameters (wear), ``health`` starts the
    health monitor (``health_params`` for its parameters).  ``events`` are ``(t_s, node,
    {parameter: value})`` with node ``servovalve_plant`` (wear, degradation, load) or
    ``controller`` (gains): handed to the node before the run and applied at the first tick
    whose time is at least ``t_s``, in either mode, after the scenario's own events.
    ``record``: an MCAP file the ``recorder`` node writes every graph topic to (it must not
    exist).  ``foxglove``: ``[HOST:]PORT`` the ``foxglove_bridge`` node serves every graph
    topic on, live (:mod:`eha_ros.nodes.foxglove_bridge`).  ``node_params``: ``{node:
    {parameter: value}}`` applied last, over what the fields above set (e.g. from a ROS
    params file, ``config/graph.yaml``).  ``rt``: the ticking nodes
    get the real-time settings :data:`eha_ros.realtime.RT_DEFAULTS`, the listeners (recorder,
    health monitor, and the harness's own process for the run)
    :data:`eha_ros.realtime.RT_LISTENER_DEFAULTS`.  The graph starts when
    every node's endpoints have matched (:mod:`eha_ros.nodes.handshake`), at most
    ``handshake_timeout_s`` after the nodes were started.  ``trace`` (realtime): an MCAP file
    (it must not exist) for the timing trace of every tick of every node with a tick loop (the
    plant, the command generator, a ``trigger: timer`` controller), each late episode with its
    evidence and cause (:mod:`eha_ros.recording.trace`); :attr:`GraphResult.trace` has the
    late ticks by cause.

    A parameter no node declares, an unknown node or an event parameter the node cannot change
    while running is refused (:class:`GraphConfigError`) before anything starts."""

    scenario: str = 'step_0p1'
    model: str = 'hf'
    mode: str = 'lockstep'
    duration_s: float | None = None
    rate_hz: float = 1000.0
    dt_s: float = 1e-6
    integrator: str = 'explicit'
    seed: int = 0
    plant: dict = dataclasses.field(default_factory=dict)
    health: bool = False
    health_params: dict = dataclasses.field(default_factory=dict)
    params_file: str = ''
    events: list = dataclasses.field(default_factory=list)
    record: str = ''
    node_params: dict = dataclasses.field(default_factory=dict)
    rt: bool = False
    handshake_timeout_s: float = 60.0
    trace: str = ''
    foxglove: str = ''

    def resolved_duration(self) -> float:
        if self.duration_s is not None:
            return float(self.duration_s)
        from eha_ros.physics import get_scenario
        return get_scenario(self.scenario).duration_s

    def nodes(self) -> list:
        """The graph's nodes (the harness's collector included), as the handshake names them."""
        out = ['command_generator', 'controller', 'servovalve_plant']
        if self.health:
            out.append('health_monitor')
        if self.record:
            out.append('recorder')
        if self.foxglove:
            out.append('foxglove_bridge')
        return out + [COLLECTOR]

    def all_events(self) -> list:
        """The scenario's events, then ``events``: ``[(t_s, node, {parameter: value})]``."""
        from eha_ros.physics import get_scenario
        return list(getattr(get_scenario(self.scenario), 'events', ())) + list(self.events)

    def node_parameters(self) -> dict:
        """``node -> {parameter: value}``.

        Raises
        ------
        GraphConfigError
            For an unknown node, parameter or event target (see the class docstring).
        """
        from eha_ros.physics import get_scenario, ParameterError
        from eha_ros.physics.events import Event, format_event, node_events
        sim = self.mode == 'lockstep'
        common = {'mode': self.mode, 'rate_hz': float(self.rate_hz)}
        sc = get_scenario(self.scenario)
        test = ({'valve_test': True,
                 'valve_test_flows_m3_s': [float(q) for q in sc.valve_test_flows_m3_s],
                 'valve_test_procedure': sc.valve_test_procedure}
                if sc.valve_test else {})
        if sc.preflight_check:
            test['preflight_check'] = True
        try:
            checked = node_events('events', self.all_events())
        except ParameterError as exc:
            raise GraphConfigError(str(exc)) from None
        events = {}
        for t_s, node, changes in checked:
            events.setdefault(node, []).append(format_event(Event(t_s, changes)))
        out = {
            'command_generator': dict(common, scenario=self.scenario, use_sim_time=sim),
            'controller': dict(common, params_file=self.params_file, use_sim_time=sim),
            'servovalve_plant': dict(common, model=self.model, dt_s=float(self.dt_s),
                                     integrator=str(self.integrator),
                                     seed=int(self.seed), params_file=self.params_file,
                                     duration_s=self.resolved_duration(),
                                     handshake_nodes=self.nodes(),
                                     handshake_timeout_s=float(self.handshake_timeout_s),
                                     **dict(test, **self.plant)),
        }
        for node, texts in events.items():
            out[node]['events'] = texts
        if self.health:
            out['health_monitor'] = dict(params_file=self.params_file, use_sim_time=sim,
                                         **self.health_params)
        elif self.health_params:
            raise GraphConfigError('health_params given without health=True (no health '
                                   'monitor runs)')
        if self.record:
            out['recorder'] = dict(output=str(Path(self.record).resolve()))
        if self.rt:
            from eha_ros.realtime import RT_DEFAULTS, RT_LISTENER_DEFAULTS
            plant_cpu, other_cpus = rt_cpus()
            for node in out:
                rt = RT_DEFAULTS if node in TICKING_NODES else RT_LISTENER_DEFAULTS
                cpus = (plant_cpu if node == 'servovalve_plant' else other_cpus
                        if node in TICKING_NODES else ())
                out[node].update(thread_priority=int(rt.thread_priority),
                                 cpu_affinity=list(cpus) or [-1],
                                 lock_memory=bool(rt.lock_memory))
            # the threads beside a tick loop (executor, middleware) at the listeners'
            # priority: one at normal priority that holds the GIL can be preempted by any
            # busy process while the loop waits for the GIL (the trace showed 24 ms waits
            # with no CPU time in the process's other threads)
            for node in self.traced_nodes(out):
                if self.mode == 'realtime':
                    out[node]['executor_priority'] = int(RT_LISTENER_DEFAULTS.thread_priority)
        if self.foxglove:  # at normal priority (not --rt's): a viewer never competes with it
            from eha_ros.foxglove.core import parse_endpoint
            try:
                host, port = parse_endpoint(self.foxglove)
            except ValueError as exc:
                raise GraphConfigError(f'foxglove: {exc}') from None
            from eha_ros.graph import NODES
            out['foxglove_bridge'] = dict(host=host, port=port, mode=self.mode,
                                          parameter_nodes=[n for n in out if n in NODES])
        for node, values in self.node_params.items():
            if node not in out:
                known = ', '.join(out)
                raise GraphConfigError(f'node_params: no node {node!r} in this graph '
                                       f'(nodes: {known})')
            out[node].update(values)
        _check_declared(out)
        return out

    def traced_nodes(self, params: dict) -> list:
        """The nodes of ``params`` (:meth:`node_parameters`) that run a tick loop."""
        return [n for n in ('command_generator', 'servovalve_plant') if n in params] + (
            ['controller'] if params.get('controller', {}).get('trigger') == 'timer' else [])

    def with_trace_files(self, params: dict, directory: Path) -> dict:
        """``params`` with each traced node's ``trace_file`` in ``directory`` and room for
        the run (its duration and 5 s more)."""
        if not self.trace:
            return params
        if self.mode != 'realtime':
            raise GraphConfigError('trace: a lockstep run has no wall-clock schedule to be '
                                   'late on; trace a realtime run')
        ticks = int(math.ceil(self.resolved_duration() * self.rate_hz)) + int(5 * self.rate_hz)
        for node in self.traced_nodes(params):
            params[node].setdefault('trace_file', str(directory / f'trace_{node}.npz'))
            params[node].setdefault('trace_ticks', ticks)
        return params


def rt_cpus() -> tuple:
    """``--rt``'s CPU layout: ``(the plant's CPUs, the other ticking nodes')``. The plant - the
    node whose lateness is the rig's - gets the last CPU this process may use to itself among
    the ticking nodes; the command generator and the controller share the rest. The listeners
    (collector, recorder, health monitor) are not pinned: below the ticking nodes' priority
    they take the idle time of any CPU. On one CPU nobody is pinned."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return (), ()
    return (cpus[-1],), tuple(cpus[:-1])


def rt_pinning_warning(cpus=None, total: int | None = None) -> str | None:
    """One warning line when ``--rt`` meets a harness pinned by hand to one CPU of several
    (``taskset -c N``; ``cpus``/``total`` default to this process's affinity and the
    machine's CPU count), else ``None``.  Every node process inherits that mask, so
    :func:`rt_cpus` has one CPU to share and pins nobody apart: the whole graph runs on that
    CPU, its tick loops at SCHED_FIFO above the listeners, and the collector, lowest, can
    lose messages (``taskset -c 1 eha-graph --mode realtime --rt --duration 5``: one run lost
    1,551 of 5,001 states, another none; on CPU 0, 74 commands).  With every thread of a
    ticking node at SCHED_FIFO, as before the tick loops, the collector never ran at all."""
    cpus = sorted(os.sched_getaffinity(0) if cpus is None else cpus)
    total = os.cpu_count() if total is None else total
    if len(cpus) != 1 or not total or total < 2:
        return None
    return (f'--rt with this process pinned to CPU {cpus[0]} alone of {total} (taskset?): '
            'every node inherits that CPU, so the whole graph shares it at SCHED_FIFO and the '
            'listeners can lose messages; pin it to two CPUs or more, or not at all')


def declared_parameters() -> dict:
    """Every node's declared parameter names, ``{node: set}``, from the installed
    ``config/graph.yaml`` (which a test keeps equal to what the nodes declare)."""
    import yaml

    from eha_ros.physics.params import config_dir
    data = yaml.safe_load((config_dir() / 'graph.yaml').read_text(encoding='utf-8'))
    return {str(node).strip('/'): set(section['ros__parameters']) | {'use_sim_time'}
            for node, section in data.items()}


def _check_declared(params: dict) -> None:
    from eha_ros.graph import undeclared_message
    declared = declared_parameters()
    for node, values in params.items():
        for name in values:
            if name not in declared.get(node, ()):
                raise GraphConfigError(undeclared_message(node, name, declared.get(node, ())))


@dataclasses.dataclass
class GraphResult:
    """Arrays of what the collector received, in arrival order (``arrival_s``: the
    middleware's receipt time of states and current commands, on the monotonic clock);
    ``health`` is a list of HealthStatus
    messages; ``events``: every parameter change that took effect (``/eha/events``, as
    dicts).  ``wall_s`` runs from the graph's synchronised start to the last state;
    ``discovery_s`` from the nodes' launch to that start.  In lockstep, ticks the plant
    re-sent (``resent_ticks`` of them) appear once.  ``interrupted``: the run was stopped
    (``stop``) before the plant reached its duration; ``diagnostics``: the last
    ``DiagnosticStatus`` of each name seen on ``/diagnostics`` (``name -> {'level', 'message',
    'values'}``), e.g. each node's timing.

    What arrived and what did not: ``messages`` (per topic, re-sent ticks included), ``lost``
    (per topic, gaps in the publishers' sequence numbers), ``missed_at_start`` (per topic,
    published before the collector's subscription matched: the handshake makes these 0), and
    ``missing`` (lockstep: the ticks, from 0 to the last state, without a state, a position
    command or a current command; realtime: the ticks between the first and the last state
    without a state). ``fault``: a node that died or hung mid-run (``{'node', 'how',
    'wall_s', 'sim_s'}``: how - its exit status, the signal that ended it, or how long it was
    silent; when - wall seconds since the start and the last state's simulated time), else
    None. :attr:`complete` is true when there is no fault and all of these are empty or zero.
    The plant's command watchdog is in the states: ``command_age_ticks`` (a tick that ran on
    a stale command) and ``safe_action`` (``ActuatorState.SAFE_*``)."""

    state: dict
    command: dict
    servovalve: dict
    health: list
    wall_s: float
    config: GraphConfig
    resent_ticks: int = 0
    interrupted: bool = False
    diagnostics: dict = dataclasses.field(default_factory=dict)
    events: list = dataclasses.field(default_factory=list)
    discovery_s: float = 0.0
    messages: dict = dataclasses.field(default_factory=dict)
    lost: dict = dataclasses.field(default_factory=dict)
    missed_at_start: dict = dataclasses.field(default_factory=dict)
    missing: dict = dataclasses.field(default_factory=dict)
    fault: dict | None = None
    trace: dict | None = None

    @property
    def sim_s(self) -> float:
        t = self.state['sim_time_s']
        return float(t[-1]) if t.size else 0.0

    @property
    def complete(self) -> bool:
        """No fault, and nothing lost, missed at the start or missing."""
        return not (self.fault or self.stopped or any(self.lost.values())
                    or any(self.missed_at_start.values())
                    or any(len(v) for v in self.missing.values()))

    @property
    def stopped(self) -> bool:
        """The plant's command watchdog stopped it (its last state: ``STATUS_STOPPED``)."""
        from eha_ros.graph import STATUS_STOPPED
        status = self.state.get('status')
        return bool(status is not None and status.size and status[-1] == STATUS_STOPPED)

    @property
    def stale_ticks(self) -> int:
        """States whose tick ran on a stale current command (``command_age_ticks`` > 0)."""
        age = self.state.get('command_age_ticks')
        return int(np.count_nonzero(age)) if age is not None else 0

    def loss_report(self) -> str:
        """One line: the fault and what did not arrive (empty when :attr:`complete`)."""
        parts = [describe_fault(self.fault)] if self.fault else []
        if self.stopped:
            parts.append(f'the plant was stopped by its command watchdog at t = '
                         f'{self.sim_s:.6g} s')
        for what, ticks in self.missing.items():
            if len(ticks):
                parts.append(f'{len(ticks)} ticks without {what} (first: tick {ticks[0]})')
        for name, counts in (('lost', self.lost), ('missed at the start', self.missed_at_start)):
            for topic, n in counts.items():
                if n:
                    parts.append(f'{topic}: {n} {name}')
        return '; '.join(parts)


def _ros_arg(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value if value else "''"
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, str) for v in value):
            return '[' + ', '.join(_quote(v) for v in value) + ']'
        if value and all(isinstance(v, bool) for v in value):
            return '[' + ', '.join(_ros_arg(v) for v in value) + ']'
        if value and all(isinstance(v, int) for v in value):
            return '[' + ', '.join(str(v) for v in value) + ']'
        return '[' + ', '.join(f'{float(v):.17e}' for v in value) + ']'
    return repr(value)


def _quote(text: str) -> str:
    """A string array entry for ``-p name:=[...]`` (YAML flow sequence): quoted, so that
    ``:``, ``,`` and ``=`` inside it stay text."""
    return "'" + text.replace("'", "''") + "'"


class _Collector:
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
        from rclpy.event_handler import SubscriptionEventCallbacks
        from rclpy.node import Node

        from diagnostic_msgs.msg import DiagnosticArray
        from eha_ros.graph import (QOS_DEPTH, TOPIC_COMMAND, TOPIC_DIAGNOSTICS, TOPIC_EVENTS,
                                   TOPIC_HEALTH, TOPIC_SERVOVALVE, TOPIC_STATE, graph_qos,
                                   topic_qos)
        from eha_ros.msg import (ActuatorCommand, ActuatorState, GraphEvent, HealthStatus,
                                 ServovalveCommand)
        from eha_ros.nodes.handshake import Handshake
        from eha_ros.recording.definitions import SequenceGapCounter
        from eha_ros.nodes.common import stamp_to_ns
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
        self._watchdog_changes = 0

        cols = self.state_cols

        def on_state(msg, now):
            for f in STATE_FIELDS:
                cols[f].append(getattr(msg, f))
            cols['arrival_s'].append(now)
            cols['stamp_ns'].append(stamp_to_ns(msg.header.stamp))
            cols['tick'].append(msg.tick)
            cols['status'].append(msg.status)
            cols['valve_test_point'].append(msg.valve_test_point)
            cols['valve_test_point_end'].append(int(msg.valve_test_point_end))
            cols['valve_test_procedure'].append(msg.valve_test_procedure)
            cols['command_age_ticks'].append(msg.command_age_ticks)
            if msg.safe_action != (cols['safe_action'][-1] if cols['safe_action'] else 0):
                self._watchdog_changes += 1   # the plant published a trip or a resumption
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
        from eha_ros.nodes.common import take_waiting
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
        from eha_ros.nodes.common import stamp_to_ns
        self.events.append({
            'stamp_ns': stamp_to_ns(msg.header.stamp),
            'tick_index': int(msg.tick_index), 'node': msg.node, 'source': msg.source,
            'scheduled_time_s': float(msg.scheduled_time_s),
            'changes': dict(zip(msg.parameter_names, (float(v) for v in msg.parameter_values)))})

    def events_in_flight(self, config) -> int:
        """How many of the plant's events its states show it has published have not arrived:
        a watchdog trip or resumption (the states' ``safe_action`` changed) and a scheduled
        change (a state stamped a tick past its time).  ``/eha/events`` is reliable but apart
        from the states: a sample lost on a loaded machine comes again only at the writer's
        next heartbeat (seconds), after the states that followed it."""
        if not self.n_states:
            return 0
        period_ns = round(1e9 / config.rate_hz)
        last = self.last_stamp_ns
        scheduled = {t_s for t_s, node, _ in config.all_events()
                     if node == 'servovalve_plant' and round(t_s * 1e9) + period_ns <= last}
        seen = [e for e in self.events if e['node'] == 'servovalve_plant']
        return (max(0, self._watchdog_changes - sum(e['source'] == 'watchdog' for e in seen))
                + max(0, len(scheduled) - sum(e['source'] == 'schedule' for e in seen)))

    @property
    def n_states(self) -> int:
        return len(self.state_cols['tick'])

    @property
    def last_stamp_ns(self) -> int:
        return self.state_cols['stamp_ns'][-1]

    @property
    def last_status(self) -> int:
        return self.state_cols['status'][-1]

    def final_answers_in(self, config) -> bool:
        """Lockstep: the command and the current command of the last state's tick arrived."""
        if not self.n_states:
            return True
        last = self.last_stamp_ns
        # a plant running on stale commands (a silent or dead controller) gets no answer
        unanswered = self.state_cols['command_age_ticks'][-1] > 0
        return ((unanswered or last in self.current_cols['stamp_ns'][-3:])
                and last in self.command_cols['stamp_ns'][-3:])

    @property
    def last_arrival_s(self) -> float:
        """``time.monotonic`` of the last state's receipt (0 before any)."""
        arrivals = self.state_cols['arrival_s']
        return arrivals[-1] if len(arrivals) else 0.0

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
        missing = _missing_ticks(config, state['stamp_ns'], command['stamp_ns'],
                                 servo['stamp_ns'])
        return GraphResult(state, command, servo, list(self.health), wall, config, resent,
                           diagnostics=dict(self.diagnostics), events=list(self.events),
                           discovery_s=max(0.0, start - t0),
                           messages={t: c.received for t, c in self.counters.items()},
                           lost={t: c.lost for t, c in self.counters.items()},
                           missed_at_start={t: c.missed_at_start
                                            for t, c in self.counters.items()},
                           missing=missing)


def _missing_ticks(config, state_ns, command_ns, servo_ns) -> dict:
    """Ticks without a state (both modes: between the first and the last state; lockstep:
    from tick 0) and, in lockstep, without a position or a current command."""
    period = round(1e9 / config.rate_hz)
    if not state_ns.size:
        return {}
    have = np.unique(state_ns // period)
    first = 0 if config.mode == 'lockstep' else int(have[0])
    expected = np.arange(first, int(have[-1]) + 1)
    out = {'state': np.setdiff1d(expected, have).tolist()}
    if config.mode == 'lockstep':
        out['command'] = np.setdiff1d(expected, np.unique(command_ns // period)).tolist()
        out['current command'] = np.setdiff1d(expected, np.unique(servo_ns // period)).tolist()
    return out


class GraphRun:
    """A run of the graph as a context manager (see the module docstring): entering starts the
    nodes, each after its ``delays`` entry, and the collector; :meth:`wait` runs the scenario
    to its end and returns the :class:`GraphResult`; leaving stops every node and restores
    this process, also on an exception.

    ``env`` (e.g. from :func:`eha_ros.isolation.ros_environment`) sets ``ROS_DOMAIN_ID`` and
    ``ROS_LOG_DIR``; default: the current environment.  ``stop``: a callable checked every
    50 ms; when it returns true the run ends early (``GraphResult.interrupted``) and every node
    is stopped as after a complete run.  ``on_start(pids)``: called once the nodes are started,
    with :attr:`pids`.  ``delays``: ``{node: seconds}`` to launch a node (or the collector,
    :data:`COLLECTOR`) that long after the others, e.g. to test late discovery; with
    ``delay_after_start``, that long after the graph's start (seen by an observer node), e.g.
    to show what a listener left out of the handshake misses.

    Raises :class:`GraphConfigError` (from the constructor: nothing starts) for an unknown
    node, parameter or event target; :class:`GraphError` when a node exits early, the start-up
    handshake does not complete or the run stalls for ``timeout_s``; :class:`GraphDataLoss`
    (from :meth:`wait`, the result attached) for a lockstep run that is not complete.
    """

    def __init__(self, config: GraphConfig | None = None, processes: bool = True,
                 env: dict | None = None, timeout_s: float = 300.0, log_dir: str | None = None,
                 stop=None, on_start=None, delays: dict | None = None,
                 delay_after_start: bool = False):
        import rclpy
        self.config = config = config or GraphConfig()
        self.env = dict(os.environ if env is None else env)
        self.duration_ns = round(config.resolved_duration() * 1e9)
        self.params = config.node_parameters()
        if config.record and Path(config.record).exists():
            raise GraphError(f'{config.record} exists: refusing to overwrite it')
        if config.trace and Path(config.trace).exists():
            raise GraphError(f'{config.trace} exists: refusing to overwrite it')
        self.delays = dict(delays or {})
        unknown = set(self.delays) - set(self.params) - {COLLECTOR}
        if unknown:
            raise GraphConfigError(f'delays: no node {sorted(unknown)[0]!r} in this graph')
        self.processes, self.timeout_s, self.stop = processes, timeout_s, stop
        self.on_start, self.delay_after_start = on_start, delay_after_start
        self.log_dir = Path(log_dir or tempfile.mkdtemp(prefix='eha_graph_'))
        self.params = config.with_trace_files(self.params, self.log_dir)
        self.procs, self.nodes = {}, []  # node processes: name -> (Popen, log); nodes here
        self.context = rclpy.Context()
        self.executor = self.collector = self.observer = None
        self.interrupted = False  # the run was stopped (``stop``) before its end
        self.fault = None  # a node that died or hung mid-run (GraphResult.fault)

    @property
    def pids(self) -> dict:
        """``{name: pid}`` of the node processes started so far."""
        return {name: proc.pid for name, (proc, _) in self.procs.items()}

    def __enter__(self) -> 'GraphRun':
        try:
            self._open()
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._close()

    def _open(self) -> None:
        """Start this process's ROS context, then the nodes (and the collector) due now."""
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        from eha_ros.nodes.common import make_executor
        self._saved_env = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_LOG_DIR')}
        os.environ.update({k: self.env[k] for k in self._saved_env if k in self.env})
        self._cpus_before = os.sched_getaffinity(0)
        # no rclpy signal handlers: SIGINT reaches the caller (``stop``, KeyboardInterrupt)
        rclpy.init(context=self.context, domain_id=int(self.env.get('ROS_DOMAIN_ID', '0')),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.executor = make_executor(self.context)
        if self.config.rt:  # the collector: a listener that other work must not starve
            from eha_ros.realtime import apply_realtime, RT_LISTENER_DEFAULTS
            pinned = rt_pinning_warning(self._cpus_before)
            if pinned:
                print(f'{COLLECTOR}: warning: {pinned}', file=sys.stderr)
            for line in apply_realtime(RT_LISTENER_DEFAULTS):
                print(f'{COLLECTOR}: warning: {line}', file=sys.stderr)
        self.t0 = time.monotonic()
        self._pending = sorted(((self.delays.get(name, 0.0), name)
                                for name in list(self.params) + [COLLECTOR]), key=lambda x: x[0])
        if self.delay_after_start and self.delays:
            from rclpy.node import Node

            from eha_ros.nodes.handshake import Handshake
            self.observer = Node(COLLECTOR + '_observer', context=self.context,
                                 start_parameter_services=False)
            self.observer.handshake = Handshake(self.observer)
            self.nodes.append(self.observer)
            self.executor.add_node(self.observer)
        while self._pending and self._pending[0][0] <= 0:
            self._launch(self._pending.pop(0)[1])
        if self.on_start is not None:
            self.on_start(self.pids)
        self._last_progress, self._last_count = time.monotonic(), 0
        self._start_deadline = self.t0 + _REPORT_DEADLINE_S
        self._coordinator_seen = False
        plant = self.params['servovalve_plant']
        # one process: the plant shares this process's executor (and its GIL with the health
        # monitor's estimates), so its silence is this process's, not a hung node's
        self._heartbeat_s = (None if not self.processes else HEARTBEAT_S
                             if self.config.mode == 'realtime'
                             else float(plant.get('command_wait_s', 10.0)) + HEARTBEAT_S)

    def _due(self, delay: float) -> bool:
        """Whether a node delayed by ``delay`` s falls due (after the start with an observer)."""
        if self.observer is None:
            return time.monotonic() - self.t0 >= delay
        handshake = self.observer.handshake
        return handshake.started and time.monotonic_ns() >= (handshake.start_monotonic_ns()
                                                             + delay * 1e9)

    def _launch(self, name: str) -> None:
        """Start ``name`` in this process or (the recorder and the bridge always) as its
        console script."""
        from rclpy.parameter import Parameter

        from eha_ros.nodes.common import refuse_undeclared
        if name == COLLECTOR:
            self.collector = _Collector(self.context)
            self.executor.add_node(self.collector.node)
        elif self.processes or name in ('recorder', 'foxglove_bridge'):
            cmd = [str(Path(sys.executable).parent / name), '--ros-args'] + [
                a for k, v in self.params[name].items() for a in ('-p', f'{k}:={_ros_arg(v)}')]
            out = open(self.log_dir / f'{name}.log', 'wb')
            self.procs[name] = (subprocess.Popen(cmd, env=self.env, stdout=out,
                                                 stderr=subprocess.STDOUT, cwd=self.log_dir,
                                                 preexec_fn=_stop_with_parent), out)
        else:
            node = _node_class(name)(context=self.context, parameter_overrides=[
                Parameter(k, value=v) for k, v in self.params[name].items()])
            refuse_undeclared(node)
            self.nodes.append(node)
            self.executor.add_node(node)

    def wait(self) -> GraphResult:
        """Run until the plant has simulated its duration (or diverged, or ``stop``), let the
        last messages arrive, stop the node processes; returns what the collector received."""
        while not self._step():
            pass
        if self.fault is None:
            self._drain()
        elif self.fault['node'] != 'servovalve_plant' and self.collector.n_states:
            until_ns = min(self.duration_ns,
                           self.collector.last_stamp_ns + round(FAULT_GRACE_S * 1e9))
            end = time.monotonic() + FAULT_GRACE_WALL_S
            c = self.collector
            while time.monotonic() < end and (c.last_stamp_ns < until_ns
                                              or c.events_in_flight(self.config)):
                self.executor.spin_once(timeout_sec=_Collector.POLL_S)
                self.collector.poll(force=True)
        result = self.collector.result(self.config, self.t0)
        result.interrupted = self.interrupted
        result.fault = self.fault
        failure = self._stop_processes()
        if failure is not None:
            raise GraphError(failure)
        if self.config.trace:
            result.trace = self._write_trace()
        if self.fault is not None:
            raise GraphFault(f'{describe_fault(self.fault)} (logs in {self.log_dir})', result)
        if self.config.mode == 'lockstep' and not self.interrupted and not result.complete:
            raise GraphDataLoss(f'lockstep run incomplete: {result.loss_report()}', result)
        return result

    def _step(self) -> bool:
        """One pass of the run: spin, take the collector's messages, launch the nodes that fell
        due; true once the run has ended.  Raises GraphError for a failed node or a stall."""
        from eha_ros.graph import STATUS_DIVERGED, STATUS_STOPPED
        self.executor.spin_once(timeout_sec=_Collector.POLL_S)
        collector = self.collector
        if collector is not None:
            collector.poll()
        while self._pending and self._due(self._pending[0][0]):
            self._launch(self._pending.pop(0)[1])
        if self.stop is not None and self.stop():
            self.interrupted = True
            return True
        n_states = collector.n_states if collector is not None else 0
        if n_states and (collector.last_stamp_ns >= self.duration_ns
                         or collector.last_status in (STATUS_DIVERGED, STATUS_STOPPED)):
            return True  # the end, diverged, or stopped by its watchdog: the plant has stopped
        if self._node_ended():
            return True
        self._check_progress(n_states)
        return self.fault is not None

    def _node_ended(self) -> bool:
        """True when a node ended on a stop request (a terminal's Ctrl-C reached it before
        ``stop`` saw it); raises GraphError for a node that failed (refused: GraphConfigError)."""
        fatal = next((n.fatal for n in self.nodes if getattr(n, 'fatal', None)), None)
        if fatal:
            raise GraphError(fatal)
        exited = [name for name, (proc, _) in self.procs.items() if proc.poll() is not None]
        if exited and self.stop is not None and self.stop():
            self.interrupted = True
            return True
        if exited:
            name, proc = exited[0], self.procs[exited[0]][0]
            if self.collector is not None and self.collector.handshake.started:
                self._fault(name, _how_it_ended(proc.returncode))   # mid-run
                return True
            error = GraphConfigError if proc.returncode == 2 else GraphError  # 2: refused
            raise error(_exit_message(name, proc.returncode, self.log_dir))
        return False

    def _fault(self, node: str, how: str) -> None:
        """Record that ``node`` failed mid-run (:attr:`GraphResult.fault`)."""
        c = self.collector
        start = c.handshake.start_monotonic_ns() * 1e-9
        sim = c.state_cols['sim_time_s']
        self.fault = {'node': node, 'how': how,
                      'wall_s': round(max(0.0, time.monotonic() - start), 3),
                      'sim_s': float(sim[-1]) if len(sim) else 0.0}

    def _check_progress(self, n_states: int) -> None:
        """Raise GraphError for a handshake not complete in time or a stall of ``timeout_s``."""
        now = time.monotonic()
        if self.collector is None or not self.collector.handshake.started:
            self._last_progress = now
            if not self._coordinator_seen and self.collector is not None:
                from eha_ros.nodes.handshake import COORDINATOR
                if COORDINATOR in self.collector.handshake.reports:
                    # the plant is up and counting its own timeout: wait for its verdict, not
                    # for the time its process took to come up
                    self._coordinator_seen = True
                    self._start_deadline = (now + self.config.handshake_timeout_s
                                            + _START_MARGIN_S)
            if now > self._start_deadline:
                problem = (evaluate_reports(self.collector, self.config)
                           if self.collector is not None else 'the collector was never created')
                raise GraphError(f'start-up handshake incomplete after {now - self.t0:.0f} s: '
                                 f'{problem} (logs in {self.log_dir})')
        elif n_states != self._last_count:
            self._last_count, self._last_progress = n_states, now
        elif self._heartbeat_s is not None and now - max(
                self._last_progress, self.collector.handshake.start_monotonic_ns() * 1e-9
        ) > self._heartbeat_s:
            self._fault('servovalve_plant', f'no state for {self._heartbeat_s:g} s (hung)')
        elif now - self._last_progress > self.timeout_s:
            raise GraphError(f'no plant state for {self.timeout_s:g} s (after {self._last_count} '
                             f'states): the graph stalled (logs in {self.log_dir})')

    def _drain(self) -> None:
        """Let the last tick's messages arrive: in lockstep until its command and current
        command are in; until the plant's events its states announce are in; with the health
        monitor until it is idle (it estimates on a worker thread) and its messages are in.
        At most 10 s."""
        collector, config = self.collector, self.config
        end = time.monotonic() + 0.2
        cap = time.monotonic() + 10.0
        n_health = -1
        while time.monotonic() < cap:
            self.executor.spin_once(timeout_sec=0.02)
            collector.poll(force=True)
            if time.monotonic() < end:
                continue
            if config.mode == 'lockstep' and not collector.final_answers_in(config):
                continue
            if collector.events_in_flight(config):
                continue
            busy = any(getattr(n, '_pending', 0) for n in self.nodes)
            if not config.health or (not busy and len(collector.health) == n_health):
                break
            n_health = len(collector.health)
            end = time.monotonic() + 0.3

    def _stop_processes(self) -> str | None:
        """Stop the node processes (SIGINT; killed after 15 s); returns why the recorder failed."""
        if self.interrupted:  # a terminal's Ctrl-C reached the nodes too: let them stop alone
            end = time.monotonic() + _GRACE_S
            while time.monotonic() < end and any(p.poll() is None for p, _ in self.procs.values()):
                time.sleep(0.05)
        hung = self.fault['node'] if self.fault and 'hung' in self.fault['how'] else None
        for name, (proc, _) in self.procs.items():
            if proc.poll() is None:  # a hung node cannot stop itself
                proc.send_signal(signal.SIGKILL if name == hung else signal.SIGINT)
        for proc, out in self.procs.values():
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            out.close()
        rec = self.procs.get('recorder')
        if rec is not None and rec[0].returncode != 0:
            return (f'recorder exited with status {rec[0].returncode}: '
                    + ' | '.join(_log_lines(self.log_dir / 'recorder.log')[-3:]))

    def _write_trace(self) -> dict:
        """Gather the nodes' timing traces (in this process: stop their loops first) into
        ``config.trace``; returns ``{node: {'ticks', 'dropped', 'complete', 'shares'}}``, or
        ``{node: {'missing': why}}`` for a node that left none (one killed mid-run)."""
        from eha_ros.recording.trace import load_node_trace, summarise, write_trace
        for node in self.nodes:
            getattr(node, 'close', lambda: None)()
        traces, out = {}, {}
        for node in self.config.traced_nodes(self.params):
            path = Path(self.params[node]['trace_file'])
            if not path.is_file():
                out[node] = {'missing': f'no trace: {node} did not shut down cleanly'}
                continue
            traces[node] = summarise(load_node_trace(path))
            t = traces[node]
            out[node] = {'ticks': len(t['ticks']['tick']), 'dropped': t['dropped'],
                         'complete': t['complete'], 'shares': t['shares']}
        write_trace(self.config.trace, traces, time.time_ns() - time.monotonic_ns())
        return out

    def _close(self) -> None:
        """Stop every node, end the ROS context, restore the environment and scheduling."""
        import rclpy
        self._stop_processes()
        for node in self.nodes:  # none without an executor
            self.executor.remove_node(node)
            getattr(node, 'close', lambda: None)()
            node.destroy_node()
        if self.collector is not None:
            self.collector.destroy()
        if self.executor is not None:
            self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)
        if self.config.rt:
            from eha_ros.realtime import normal_scheduling
            normal_scheduling(self._cpus_before)
        os.environ.update({k: v for k, v in self._saved_env.items() if v is not None})
        for k in (k for k, v in self._saved_env.items() if v is None):
            os.environ.pop(k, None)


def run_graph(config: GraphConfig | None = None, processes: bool = True, env: dict | None = None,
              timeout_s: float = 300.0, log_dir: str | None = None, stop=None,
              on_start=None, delays: dict | None = None,
              delay_after_start: bool = False) -> GraphResult:
    """Run ``config`` until the plant has simulated its duration: :class:`GraphRun` (which
    describes the arguments and what it raises) in one call."""
    with GraphRun(config, processes, env, timeout_s, log_dir, stop, on_start, delays,
                  delay_after_start) as run:
        return run.wait()


def _node_class(name: str):
    from eha_ros.nodes.command_generator import CommandGenerator
    from eha_ros.nodes.controller import Controller
    from eha_ros.nodes.health_monitor import HealthMonitor
    from eha_ros.nodes.servovalve_plant import ServovalvePlant
    return {'command_generator': CommandGenerator, 'controller': Controller,
            'servovalve_plant': ServovalvePlant, 'health_monitor': HealthMonitor}[name]


def evaluate_reports(collector, config) -> str:
    """What the handshake still waits for, from the reports the collector has seen."""
    from eha_ros.nodes.handshake import evaluate
    reports = dict(collector.handshake.reports)
    reports[COLLECTOR] = collector.handshake.counts()
    return evaluate(reports, config.nodes()) or 'every endpoint matched, but no start arrived'


def _exit_message(name: str, code: int, log_dir: Path) -> str:
    """One line for a node process that ended early: its own error line where it printed
    one (a refused parameter, a handshake that timed out), else its log's tail."""
    log = log_dir / f'{name}.log'
    lines = _log_lines(log)
    own = [line for line in lines if line.startswith(f'{name}: error:')]
    return own[-1] if own else (f'node {name} {_how_it_ended(code)} before the run '
                                f'completed (log: {log}): ' + ' | '.join(lines[-3:]))


def _libc_prctl():
    try:
        import ctypes
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


#: ``prctl`` (Linux), resolved here: the child between fork and exec must not load anything.
_PRCTL = _libc_prctl()


def _stop_with_parent() -> None:
    """In a node process before it starts (Linux): SIGINT when the harness's thread that
    started it dies, even by SIGKILL, so that no node outlives the run and the recorder
    still closes its file.  Elsewhere: nothing."""
    if _PRCTL is not None:
        _PRCTL(1, 2)  # PR_SET_PDEATHSIG, SIGINT


def describe_fault(fault: dict) -> str:
    """One line: which node failed mid-run, how and when (:attr:`GraphResult.fault`)."""
    return (f"node {fault['node']} failed mid-run: {fault['how']}, {fault['wall_s']:.3f} s "
            f"after the start (last state at t = {fault['sim_s']:.6g} s)")


def _how_it_ended(code: int) -> str:
    """A process's exit status in words: the signal that ended it, or its status."""
    if code < 0:
        try:
            return f'killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'killed by signal {-code}'
    return f'exited with status {code}'


def _log_lines(path: Path) -> list:
    try:
        return path.read_text(errors='replace').strip().splitlines()
    except OSError:
        return []
