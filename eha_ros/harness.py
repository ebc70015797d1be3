"""Launch-free harness: start the node graph, run a scenario to completion, stop every node
cleanly and return what was published.

Two ways to start the graph:

* ``processes=True`` - each node is its installed console script in its own process (as
  ``ros2 run`` would start it), with ``--ros-args -p name:=value`` parameters;
* ``processes=False`` - all nodes in this process on one executor.

Either way a collector node in this process records ``/eha/state``, ``/eha/command``,
``/eha/servovalve_command`` and ``/eha/health``.  Example::

    from eha_ros.harness import GraphConfig, run_graph
    result = run_graph(GraphConfig(scenario='step_0p1', model='hf', mode='lockstep'))
    result.state['jack_position_m']

In the tests, the ``eha_graph`` fixture (``test/conftest.py``) does the same in an isolated
ROS domain.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ['GraphConfig', 'GraphResult', 'GraphError', 'run_graph']

STATE_FIELDS = ('jack_position_m', 'jack_position_measured_m', 'jack_velocity_m_s',
                'spool_position_m', 'flapper_position_m', 'p1_pa', 'p2_pa', 'p12_pa',
                'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n', 'sim_time_s')


#: After a stop request, how long node processes get to end on their own before the harness
#: signals them (s): a second SIGINT could hit a recorder after it restored its handlers.
_GRACE_S = 3.0


class GraphError(RuntimeError):
    """The graph did not start, stalled, or a node failed."""


@dataclasses.dataclass
class GraphConfig:
    """What to run.  ``plant`` holds extra plant parameters (wear), ``health`` starts the
    health monitor (``health_params`` for its parameters); in lockstep the plant waits for the
    controller, the harness's collector, the health monitor and ``recorders`` more state
    subscribers before its first tick, so nobody misses it.  ``events`` are
    ``(t_s, node_name, {parameter: value})``: set once the plant's state passes ``t_s`` (run-time
    degradation).  ``record``: an MCAP file the ``recorder`` node writes every graph topic to
    (it must not exist).  ``node_params``: ``{node: {parameter: value}}`` applied last, over
    what the fields above set (e.g. from a ROS params file, ``config/graph.yaml``)."""

    scenario: str = 'step_0p1'
    model: str = 'hf'
    mode: str = 'lockstep'
    duration_s: float | None = None
    rate_hz: float = 1000.0
    dt_s: float = 1e-6
    seed: int = 0
    plant: dict = dataclasses.field(default_factory=dict)
    health: bool = False
    health_params: dict = dataclasses.field(default_factory=dict)
    params_file: str = ''
    recorders: int = 0
    events: list = dataclasses.field(default_factory=list)
    record: str = ''
    node_params: dict = dataclasses.field(default_factory=dict)

    def resolved_duration(self) -> float:
        if self.duration_s is not None:
            return float(self.duration_s)
        from eha_ros.physics import get_scenario
        return get_scenario(self.scenario).duration_s

    def node_parameters(self) -> dict:
        """``node -> {parameter: value}``."""
        sim = self.mode == 'lockstep'
        common = {'mode': self.mode, 'rate_hz': float(self.rate_hz)}
        from eha_ros.physics import get_scenario
        sc = get_scenario(self.scenario)
        test = ({'valve_test': True,
                 'valve_test_flows_m3_s': [float(q) for q in sc.valve_test_flows_m3_s]}
                if sc.valve_test else {})
        if sc.preflight_check:
            test['preflight_check'] = True
        # state readers: controller, collector, health monitor, recorders; /clock readers: the
        # command generator (its own subscription and its sim-time one), the controller's and
        # the health monitor's sim time, recorders
        readers = 2 + int(self.health) + self.recorders + int(bool(self.record))
        out = {
            'command_generator': dict(common, scenario=self.scenario, use_sim_time=sim),
            'controller': dict(common, params_file=self.params_file, use_sim_time=sim),
            'servovalve_plant': dict(common, model=self.model, dt_s=float(self.dt_s),
                                     seed=int(self.seed), params_file=self.params_file,
                                     duration_s=self.resolved_duration(),
                                     start_subscribers=readers,
                                     start_clock_subscribers=readers + 1,
                                     **dict(test, **self.plant)),
        }
        if self.health:
            out['health_monitor'] = dict(params_file=self.params_file, use_sim_time=sim,
                                         **self.health_params)
        if self.record:
            out['recorder'] = dict(output=str(Path(self.record).resolve()))
        for node, values in self.node_params.items():
            if node in out:
                out[node].update(values)
        return out


@dataclasses.dataclass
class GraphResult:
    """Arrays of what the collector received, in arrival order (``arrival_s``: monotonic
    receipt time of states and current commands); ``health`` is a list of HealthStatus
    messages; ``wall_s`` from start-up to the last state.  In lockstep, ticks the plant
    re-sent (``resent_ticks`` of them) appear once.  ``interrupted``: the run was stopped
    (``stop``) before the plant reached its duration; ``diagnostics``: the last
    ``DiagnosticStatus`` of each name seen on ``/diagnostics`` (``name -> {'level', 'message',
    'values'}``), e.g. each node's timing."""

    state: dict
    command: dict
    servovalve: dict
    health: list
    wall_s: float
    config: GraphConfig
    resent_ticks: int = 0
    interrupted: bool = False
    diagnostics: dict = dataclasses.field(default_factory=dict)

    @property
    def sim_s(self) -> float:
        t = self.state['sim_time_s']
        return float(t[-1]) if t.size else 0.0


def _ros_arg(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value if value else "''"
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, str) for v in value):
            return '[' + ', '.join(value) + ']'
        if value and all(isinstance(v, bool) for v in value):
            return '[' + ', '.join(_ros_arg(v) for v in value) + ']'
        if value and all(isinstance(v, int) for v in value):
            return '[' + ', '.join(str(v) for v in value) + ']'
        return '[' + ', '.join(f'{float(v):.17e}' for v in value) + ']'
    return repr(value)


class _Collector:
    def __init__(self, context, qos):
        from rclpy.node import Node

        from eha_ros.msg import ActuatorCommand, ActuatorState, HealthStatus, ServovalveCommand
        from eha_ros.graph import (TOPIC_COMMAND, TOPIC_DIAGNOSTICS, TOPIC_HEALTH,
                                   TOPIC_SERVOVALVE, TOPIC_STATE)
        from eha_ros.nodes.common import subscribe
        self.node = Node('eha_harness_collector', context=context,
                         start_parameter_services=False)
        self.states, self.commands, self.currents, self.health = [], [], [], []
        self.state_arrival, self.current_arrival = [], []

        def on_state(msg):
            self.state_arrival.append(time.monotonic())
            self.states.append(msg)

        def on_current(msg):
            self.current_arrival.append(time.monotonic())
            self.currents.append(msg)
        subscribe(self.node, ActuatorState, TOPIC_STATE, on_state)
        subscribe(self.node, ActuatorCommand, TOPIC_COMMAND, self.commands.append)
        subscribe(self.node, ServovalveCommand, TOPIC_SERVOVALVE, on_current)
        subscribe(self.node, HealthStatus, TOPIC_HEALTH, self.health.append)
        self.diagnostics = {}

        def on_diagnostics(msg):
            for st in msg.status:
                self.diagnostics[st.name] = {
                    'level': int.from_bytes(st.level, 'little') if isinstance(st.level, bytes)
                    else int(st.level), 'message': st.message,
                    'values': {kv.key: kv.value for kv in st.values}}
        from diagnostic_msgs.msg import DiagnosticArray
        subscribe(self.node, DiagnosticArray, TOPIC_DIAGNOSTICS, on_diagnostics)

    def set_parameters(self, executor, target: str, values: dict, timeout_s: float = 10.0):
        """Set parameters of node ``target`` through its parameter service."""
        from rclpy.parameter import Parameter
        from rclpy.parameter_client import AsyncParameterClient
        client = AsyncParameterClient(self.node, target)
        if not client.wait_for_services(timeout_sec=timeout_s):
            raise GraphError(f'node {target} offers no parameter service')
        future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        end = time.monotonic() + timeout_s
        while not future.done() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        if not future.done():
            raise GraphError(f'setting {sorted(values)} on {target} timed out')
        for result in future.result().results:
            if not result.successful:
                raise GraphError(f'{target} refused {sorted(values)}: {result.reason}')

    def result(self, config, wall):
        def stamps(msgs):
            return np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
                             for m in msgs], dtype=np.int64)

        def first_per_stamp(msgs, arrivals):
            """In lockstep a tick the plant re-sends (and the controller's repeated answer)
            carries the same content: keep the first of each stamp."""
            if config.mode != 'lockstep':
                return msgs, arrivals
            seen, keep_m, keep_a = set(), [], []
            for m, a in zip(msgs, arrivals):
                key = (m.header.stamp.sec, m.header.stamp.nanosec)
                if key not in seen:
                    seen.add(key)
                    keep_m.append(m)
                    keep_a.append(a)
            return keep_m, keep_a
        self.resent = len(self.states)
        self.states, self.state_arrival = first_per_stamp(self.states, self.state_arrival)
        self.resent -= len(self.states)
        self.currents, self.current_arrival = first_per_stamp(self.currents,
                                                              self.current_arrival)
        self.commands, _ = first_per_stamp(self.commands, [None] * len(self.commands))
        state = {f: np.array([getattr(m, f) for m in self.states]) for f in STATE_FIELDS}
        state['stamp_ns'] = stamps(self.states)
        state['tick'] = np.array([m.tick for m in self.states], dtype=np.int64)
        state['status'] = np.array([m.status for m in self.states], dtype=np.int64)
        state['valve_test_point'] = np.array([m.valve_test_point for m in self.states],
                                             dtype=np.int64)
        state['valve_test_point_end'] = np.array([m.valve_test_point_end for m in self.states],
                                                 dtype=bool)
        state['arrival_s'] = np.array(self.state_arrival)
        command = {'stamp_ns': stamps(self.commands),
                   'position_setpoint_m': np.array([m.position_setpoint_m
                                                    for m in self.commands])}
        servo = {'stamp_ns': stamps(self.currents),
                 'current_command_a': np.array([m.current_command_a for m in self.currents]),
                 'arrival_s': np.array(self.current_arrival)}
        return GraphResult(state, command, servo, list(self.health), wall, config,
                           self.resent, diagnostics=dict(self.diagnostics))


def run_graph(config: GraphConfig | None = None, processes: bool = True, env: dict | None = None,
              timeout_s: float = 300.0, log_dir: str | None = None, stop=None,
              on_start=None) -> GraphResult:
    """Run ``config`` until the plant has simulated its duration; see the module docstring.

    ``env`` (e.g. from :func:`eha_ros.isolation.ros_environment`) sets ``ROS_DOMAIN_ID`` and
    ``ROS_LOG_DIR``; default: the current environment.  ``stop``: a callable checked every
    50 ms; when it returns true the run ends early (``GraphResult.interrupted``) and every node
    is stopped as after a complete run.  ``on_start(pids)``: called once the nodes are started,
    with ``{name: pid}`` of the node processes.  Raises :class:`GraphError` when a node exits
    early or the run stalls for ``timeout_s``.
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from eha_ros.graph import STATUS_DIVERGED
    from eha_ros.nodes.common import QOS, make_executor

    config = config or GraphConfig()
    env = dict(os.environ if env is None else env)
    duration_ns = round(config.resolved_duration() * 1e9)
    params = config.node_parameters()
    if config.record and Path(config.record).exists():
        raise GraphError(f'{config.record} exists: refusing to overwrite it')
    domain = int(env.get('ROS_DOMAIN_ID', '0'))
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix='eha_graph_'))
    saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_LOG_DIR')}
    procs, nodes = {}, []
    context = rclpy.Context()
    executor = collector = None
    failure = None  # why a node failed, raised once everything is stopped
    interrupted = False
    os.environ.update({k: env[k] for k in saved if k in env})
    try:
        # no rclpy signal handlers: SIGINT reaches the caller (``stop``, KeyboardInterrupt)
        rclpy.init(context=context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        executor = make_executor(context)
        collector = _Collector(context, QOS)
        executor.add_node(collector.node)
        t0 = time.monotonic()
        bindir = Path(sys.executable).parent
        if 'recorder' in params:  # a process of its own in either mode
            params = dict(params)
            p = params.pop('recorder')
            cmd = [str(bindir / 'recorder'), '--ros-args'] + [
                a for k, v in p.items() for a in ('-p', f'{k}:={_ros_arg(v)}')]
            out = open(log_dir / 'recorder.log', 'wb')
            procs['recorder'] = (subprocess.Popen(cmd, env=env, stdout=out,
                                                  stderr=subprocess.STDOUT, cwd=log_dir), out)
        if processes:
            for name, p in params.items():
                cmd = [str(bindir / name), '--ros-args']
                for k, v in p.items():
                    cmd += ['-p', f'{k}:={_ros_arg(v)}']
                out = open(log_dir / f'{name}.log', 'wb')
                procs[name] = (subprocess.Popen(cmd, env=env, stdout=out,
                                                stderr=subprocess.STDOUT, cwd=log_dir), out)
        else:
            from rclpy.parameter import Parameter

            from eha_ros.nodes.command_generator import CommandGenerator
            from eha_ros.nodes.controller import Controller
            from eha_ros.nodes.health_monitor import HealthMonitor
            from eha_ros.nodes.servovalve_plant import ServovalvePlant
            classes = {'command_generator': CommandGenerator, 'controller': Controller,
                       'servovalve_plant': ServovalvePlant, 'health_monitor': HealthMonitor}
            for name, p in params.items():
                overrides = [Parameter(k, value=v) for k, v in p.items()]
                node = classes[name](context=context, parameter_overrides=overrides)
                nodes.append(node)
                executor.add_node(node)
        if on_start is not None:
            on_start({name: proc.pid for name, (proc, _) in procs.items()})
        last_progress, last_count = time.monotonic(), 0
        events = sorted(config.events, key=lambda e: e[0])
        while True:
            executor.spin_once(timeout_sec=0.05)
            if stop is not None and stop():
                interrupted = True
                break
            states = collector.states
            while events and states and states[-1].sim_time_s >= events[0][0]:
                _, target, values = events.pop(0)
                collector.set_parameters(executor, target, values)
            if states and (states[-1].header.stamp.sec * 1_000_000_000
                           + states[-1].header.stamp.nanosec) >= duration_ns:
                break
            if states and states[-1].status == STATUS_DIVERGED:
                break  # diverged: the plant has stopped
            exited = [name for name, (proc, _) in procs.items() if proc.poll() is not None]
            if exited and stop is not None and stop():
                interrupted = True  # the Ctrl-C reached a node before this loop saw it
                break
            if exited:
                name, proc = exited[0], procs[exited[0]][0]
                raise GraphError(f'node {name} exited with status {proc.returncode} '
                                 f'before the run completed (log: {log_dir / name}.log): '
                                 + _tail(log_dir / f'{name}.log'))
            if len(states) != last_count:
                last_count, last_progress = len(states), time.monotonic()
            elif time.monotonic() - last_progress > timeout_s:
                raise GraphError(f'no plant state for {timeout_s:g} s (after {last_count} '
                                 f'states): the graph stalled (logs in {log_dir})')
        # let the last tick's messages (health, commands) arrive; the health monitor
        # estimates on a worker thread: wait until it is idle and its messages are in
        end = time.monotonic() + 0.2
        cap = time.monotonic() + 10.0
        n_health = -1
        while time.monotonic() < cap:
            executor.spin_once(timeout_sec=0.02)
            if time.monotonic() < end:
                continue
            busy = any(getattr(n, '_pending', 0) for n in nodes)
            if not config.health or (not busy and len(collector.health) == n_health):
                break
            n_health = len(collector.health)
            end = time.monotonic() + 0.3
        result = collector.result(config, time.monotonic() - t0)
        result.interrupted = interrupted
    finally:
        if interrupted:  # a terminal's Ctrl-C reached the nodes too: let them stop on their own
            end = time.monotonic() + _GRACE_S
            while time.monotonic() < end and any(p.poll() is None for p, _ in procs.values()):
                time.sleep(0.05)
        for name, (proc, out) in procs.items():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for name, (proc, out) in procs.items():
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            out.close()
        rec = procs.get('recorder')
        if rec is not None and rec[0].returncode != 0:
            failure = (f'recorder exited with status {rec[0].returncode}: '
                       + _tail(log_dir / 'recorder.log'))
        for node in nodes:
            if executor is not None:
                executor.remove_node(node)
            close = getattr(node, 'close', None)
            if close:
                close()
            node.destroy_node()
        if collector is not None:
            collector.node.destroy_node()
        if executor is not None:
            executor.shutdown()
        rclpy.try_shutdown(context=context)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    if failure is not None:  # reached only when the run itself succeeded
        raise GraphError(failure)
    return result


def _tail(path: Path, n: int = 3) -> str:
    try:
        lines = path.read_text(errors='replace').strip().splitlines()
    except OSError:
        return ''
    return ' | '.join(lines[-n:])
