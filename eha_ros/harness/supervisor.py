"""Running the graph: :class:`GraphRun` starts each node (its console script in a process of
its own, or in this process on one executor) and the collector, watches the run for a node
that ends, hangs or stalls, stops every node cleanly and restores this process;
:func:`run_graph` is the same in one call."""

from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

from eha_ros.graph import STATUS_DIVERGED, STATUS_STOPPED
from eha_ros.nodes.command_generator import CommandGenerator
from eha_ros.nodes.common import make_executor, refuse_undeclared
from eha_ros.nodes.controller import Controller
from eha_ros.nodes.handshake import COORDINATOR, Handshake
from eha_ros.nodes.health_monitor import HealthMonitor
from eha_ros.nodes.servovalve_plant import ServovalvePlant
from eha_ros.realtime import apply_realtime, normal_scheduling, RT_LISTENER_DEFAULTS
from eha_ros.recording.trace import load_node_trace, summarise, write_trace

from .collector import Collector, evaluate_reports
from .config import COLLECTOR, GraphConfig, GraphConfigError, GraphError, rt_pinning_warning
from .result import describe_fault, GraphDataLoss, GraphFault, GraphResult

#: At the end of a run, how long the harness waits for the recorder to hold every state and
#: command the collector received before it stops the nodes (s).
RECORDER_WAIT_S = 10.0
#: After a stop request, how long node processes get to end on their own before the harness
#: signals them (s): a second SIGINT could hit a recorder after it restored its handlers.
_GRACE_S = 3.0

#: How long the harness waits, past the plant's own handshake timeout counted from the plant's
#: first report, for the start (s): the plant's own watchdog fires first and names the cause.
_START_MARGIN_S = 15.0
#: How long a node process may take to come up and report at all (s): imports and kernel
#: compilation on a loaded machine take tens of seconds; one silent for this long is stuck.
_REPORT_DEADLINE_S = 180.0

#: How long the plant may publish no state, once the graph has started, before the harness
#: calls it hung (s): realtime; in lockstep the plant's own wait for a missing command
#: (``command_wait_s``) comes first.
HEARTBEAT_S = 1.0
#: After a node other than the plant fails mid-run, how much simulated time the harness goes
#: on collecting before it stops the rest (s): long enough for the plant's command watchdog
#: (20 ms by default) to act, so that the result and the recording show the safe action; at
#: most ``FAULT_GRACE_WALL_S`` of wall time (a lockstep plant waits ``command_wait_s``), and
#: on until the events the states show were published have arrived
#: (:meth:`Collector.events_in_flight`).
FAULT_GRACE_S = 0.3
FAULT_GRACE_WALL_S = 5.0


def _ros_arg(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value if value else "''"
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, str) for v in value):
            # quoted YAML flow entries, so that ``:``, ``,`` and ``=`` inside stay text
            return '[' + ', '.join("'" + v.replace("'", "''") + "'" for v in value) + ']'
        if value and all(isinstance(v, bool) for v in value):
            return '[' + ', '.join(_ros_arg(v) for v in value) + ']'
        if value and all(isinstance(v, int) for v in value):
            return '[' + ', '.join(str(v) for v in value) + ']'
        return '[' + ', '.join(f'{float(v):.17e}' for v in value) + ']'
    return repr(value)


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
        self.config = config = config or GraphConfig()
        self.env = dict(os.environ if env is None else env)
        self.duration_ns = round(config.resolved_duration() * 1e9)
        self.params = config.node_parameters()
        for path in (config.record, config.trace):
            if path and Path(path).exists():
                raise GraphError(f'{path} exists: refusing to overwrite it')
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
        self._saved_env = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_LOG_DIR')}
        os.environ.update({k: self.env[k] for k in self._saved_env if k in self.env})
        self._cpus_before = os.sched_getaffinity(0)
        # no rclpy signal handlers: SIGINT reaches the caller (``stop``, KeyboardInterrupt)
        rclpy.init(context=self.context, domain_id=int(self.env.get('ROS_DOMAIN_ID', '0')),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.executor = make_executor(self.context)
        if self.config.rt:  # the collector: a listener that other work must not starve
            pinned = rt_pinning_warning(self._cpus_before)
            if pinned:
                print(f'{COLLECTOR}: warning: {pinned}', file=sys.stderr)
            for line in apply_realtime(RT_LISTENER_DEFAULTS):
                print(f'{COLLECTOR}: warning: {line}', file=sys.stderr)
        self.t0 = time.monotonic()
        self._pending = sorted(((self.delays.get(name, 0.0), name)
                                for name in list(self.params) + [COLLECTOR]), key=lambda x: x[0])
        if self.delay_after_start and self.delays:
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
        if name == COLLECTOR:
            self.collector = Collector(self.context)
            self.executor.add_node(self.collector.node)
        elif self.processes or name in ('recorder', 'foxglove_bridge'):
            cmd = [str(Path(sys.executable).parent / name), '--ros-args'] + [
                a for k, v in self.params[name].items() for a in ('-p', f'{k}:={_ros_arg(v)}')]
            out = open(self.log_dir / f'{name}.log', 'wb')
            self.procs[name] = (subprocess.Popen(cmd, env=self.env, stdout=out,
                                                 stderr=subprocess.STDOUT, cwd=self.log_dir,
                                                 preexec_fn=_stop_with_parent), out)
        else:
            node = NODE_CLASSES[name](context=self.context, parameter_overrides=[
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
                self.executor.spin_once(timeout_sec=Collector.POLL_S)
                self.collector.poll(force=True)
        result = self.collector.result(self.config, self.t0)
        result.interrupted = self.interrupted
        result.fault = self.fault
        recorder = self.procs.get('recorder')
        if (recorder is not None and recorder[0].poll() is None and self.fault is None
                and not self.interrupted):
            self._await_recorder()
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
        self.executor.spin_once(timeout_sec=Collector.POLL_S)
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
        command are in; until the plant's events its states announce are in; after a run to
        its end until every ticking node's final timing report is in; with the health monitor
        until it is idle (it estimates on a worker thread) and its messages are in.  At most
        10 s."""
        collector, config = self.collector, self.config
        to_end = not self.interrupted and collector.last_stamp_ns >= self.duration_ns
        end = time.monotonic() + 0.2
        cap = time.monotonic() + 10.0
        n_health = -1
        while time.monotonic() < cap:
            self.executor.spin_once(timeout_sec=0.02)
            collector.poll(force=True)
            if time.monotonic() < end:
                continue
            if config.mode == 'lockstep' and not collector.final_answers_in():
                continue
            if collector.events_in_flight(config) or (to_end and not collector.timing_ended()):
                continue
            busy = any(getattr(n, '_pending', 0) for n in self.nodes)
            if not config.health or (not busy and len(collector.health) == n_health):
                break
            n_health = len(collector.health)
            end = time.monotonic() + 0.3

    def _await_recorder(self) -> None:
        """Before the publishers stop (a reliable sample not yet delivered dies with its
        writer): wait until the recorder has received every state and command the collector
        received (its ``~/status``), at most ``RECORDER_WAIT_S``; a recorder still short then
        is said on stderr (the file's own counts show it)."""
        client = self.collector.node.create_client(Trigger, '/recorder/status')
        try:
            end = time.monotonic() + RECORDER_WAIT_S
            future, behind = None, None
            while time.monotonic() < end:
                if future is None and client.service_is_ready():
                    future = client.call_async(Trigger.Request())
                self.executor.spin_once(timeout_sec=0.02)
                if future is not None and future.done():
                    behind = self.collector.behind(json.loads(future.result().message))
                    if not behind:
                        return
                    future = None
            print(f'recorder: warning: after {RECORDER_WAIT_S:g} s, still short of what the '
                  f'harness received: {behind or "no answer on /recorder/status"}',
                  file=sys.stderr)
        finally:
            self.collector.node.destroy_client(client)

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
        for node in self.nodes:
            getattr(node, 'close', lambda: None)()
        traces, out = {}, {}
        for node in self.config.traced_nodes(self.params):
            path = Path(self.params[node]['trace_file'])
            if not path.is_file():
                out[node] = {'missing': f'no trace: {node} did not shut down cleanly'}
                continue
            t = traces[node] = summarise(load_node_trace(path))
            out[node] = {'ticks': len(t['ticks']['tick']), 'dropped': t['dropped'],
                         'complete': t['complete'], 'shares': t['shares']}
        write_trace(self.config.trace, traces, time.time_ns() - time.monotonic_ns())
        return out

    def _close(self) -> None:
        """Stop every node, end the ROS context, restore the environment and scheduling."""
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
            normal_scheduling(self._cpus_before)
        os.environ.update({k: v for k, v in self._saved_env.items() if v is not None})
        for k in (k for k, v in self._saved_env.items() if v is None):
            os.environ.pop(k, None)


def run_graph(config: GraphConfig | None = None, **options) -> GraphResult:
    """Run ``config`` until the plant has simulated its duration: :class:`GraphRun` (which
    describes the ``options`` and what it raises) in one call."""
    with GraphRun(config, **options) as run:
        return run.wait()


#: The graph's node classes, by their names (:data:`eha_ros.graph.NODES`).
NODE_CLASSES = {'command_generator': CommandGenerator, 'controller': Controller,
                'servovalve_plant': ServovalvePlant, 'health_monitor': HealthMonitor}


def _exit_message(name: str, code: int, log_dir: Path) -> str:
    """One line for a node process that ended early: its own error line where it printed
    one (a refused parameter, a handshake that timed out), else its log's tail."""
    log = log_dir / f'{name}.log'
    lines = _log_lines(log)
    own = [line for line in lines if line.startswith(f'{name}: error:')]
    return own[-1] if own else (f'node {name} {_how_it_ended(code)} before the run '
                                f'completed (log: {log}): ' + ' | '.join(lines[-3:]))


#: ``prctl`` (Linux), resolved here: the child between fork and exec must not load anything.
try:
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):
    _PRCTL = None


def _stop_with_parent() -> None:
    """In a node process before it starts (Linux): SIGINT when the harness's thread that
    started it dies, even by SIGKILL, so that no node outlives the run and the recorder
    still closes its file.  Elsewhere: nothing."""
    if _PRCTL is not None:
        _PRCTL(1, 2)  # PR_SET_PDEATHSIG, SIGINT


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
