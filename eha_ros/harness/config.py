"""What a run is: :class:`GraphConfig` (the scenario, the mode, the nodes and each node's
parameters, checked against what the nodes declare before anything starts), the names the
graph's nodes go by, the harness's errors and ``--rt``'s CPU layout.  Free of ROS."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import yaml

from eha_ros.foxglove.core import parse_endpoint
from eha_ros.graph import NODES, undeclared_message
from eha_ros.physics import get_scenario, ParameterError
from eha_ros.physics.events import Event, format_event, node_events
from eha_ros.physics.params import config_dir
from eha_ros.realtime import RT_DEFAULTS, RT_LISTENER_DEFAULTS

#: The harness's own node, which collects what the graph publishes.
COLLECTOR = 'eha_harness_collector'

#: Real-time settings ``GraphConfig.rt`` gives each ticking node.
TICKING_NODES = ('command_generator', 'controller', 'servovalve_plant')


class GraphError(RuntimeError):
    """The graph did not start, stalled, or a node failed."""


class GraphConfigError(GraphError, ValueError):
    """A :class:`GraphConfig` asks for something no node has (an unknown node, parameter or
    event target): refused before anything starts."""


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
        return get_scenario(self.scenario).duration_s

    def nodes(self) -> list:
        """The graph's nodes (the harness's collector included), as the handshake names them."""
        optional = (('health_monitor', self.health), ('recorder', self.record),
                    ('foxglove_bridge', self.foxglove))
        return [*TICKING_NODES, *(node for node, runs in optional if runs), COLLECTOR]

    def all_events(self) -> list:
        """The scenario's events, then ``events``: ``[(t_s, node, {parameter: value})]``."""
        return list(getattr(get_scenario(self.scenario), 'events', ())) + list(self.events)

    def node_parameters(self) -> dict:
        """``node -> {parameter: value}``.

        Raises
        ------
        GraphConfigError
            For an unknown node, parameter or event target (see the class docstring).
        """
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
            'command_generator': dict(common, scenario=self.scenario, use_sim_time=sim,
                                      duration_s=self.resolved_duration()),
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
            try:
                host, port = parse_endpoint(self.foxglove)
            except ValueError as exc:
                raise GraphConfigError(f'foxglove: {exc}') from None
            out['foxglove_bridge'] = dict(host=host, port=port, mode=self.mode,
                                          parameter_nodes=[n for n in out if n in NODES])
        for node, values in self.node_params.items():
            if node not in out:
                raise GraphConfigError(f'node_params: no node {node!r} in this graph '
                                       f'(nodes: {", ".join(out)})')
            out[node].update(values)
        declared = declared_parameters()
        for node, values in out.items():
            for name in values:
                if name not in declared.get(node, ()):
                    raise GraphConfigError(undeclared_message(node, name,
                                                              declared.get(node, ())))
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
    data = yaml.safe_load((config_dir() / 'graph.yaml').read_text(encoding='utf-8'))
    return {str(node).strip('/'): set(section['ros__parameters']) | {'use_sim_time'}
            for node, section in data.items()}
