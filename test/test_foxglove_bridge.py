"""The live view end to end: the graph with its ``foxglove_bridge`` node, watched by a client
built on Foxglove's own libraries (``test/foxglove_client``: ``@foxglove/ws-protocol`` over
``ws``, CDR decoded by ``@foxglove/rosmsg2-serialization`` from the channel's ``ros2msg``
schema).  ``make test`` installs that client with ``npm ci``; these tests fail (never skip)
where it is missing.

- Nothing lost: in lockstep, with the start-up handshake waiting for the client, every message
  of every full-rate channel reaches it, and its decoded values equal the same run's MCAP
  recording, field for field, in order per topic (exact: JSON carries doubles losslessly).
- A late joiner gets the latched history (``/eha/events``, the handshake) and, from its first
  state, every state with no gap in the plant's ticks.
- Parameters: the client lists the plant's parameters, sets a wear parameter live (the change
  is on ``/eha/events`` as ``live`` and in the states), and a misspelt name is refused with the
  nearest declared name while nothing changes.
- A slow client (its socket unread for 2 s in a realtime run) costs the graph nothing (the
  harness's loss report is complete); the bridge counts its drops per channel on
  ``/diagnostics`` and tells the client with a warning status.
"""

import json
import math
import re
from pathlib import Path
import shutil
import socket
import subprocess
import threading
import time

import pytest

from eha_ros import graph
from eha_ros.harness import GraphConfig, run_graph
from eha_ros.nodes.handshake import COORDINATOR
from eha_ros.physics import default_params, simulate
from eha_ros.recording.arrays import message_to_plain_data
from eha_ros.recording.reader import iter_decoded

ROOT = Path(__file__).resolve().parents[1]
CLIENT_DIR = ROOT / 'test' / 'foxglove_client'
CLIENT = CLIENT_DIR / 'client.mjs'
#: A client that has not connected this long after the bridge bound its port is stuck.
CONNECT_TIMEOUT_S = 60.0
#: Full-rate channels (not the decimated ones).
FULL_RATE = tuple(graph.TOPICS) + (graph.TOPIC_HANDSHAKE,)


def node_binary() -> str:
    """The ``node`` executable and an installed client, else a failure saying what to run."""
    node = shutil.which('node')
    if node is None:
        pytest.fail('node (Node.js >= 18) is not on PATH: the live-view tests need it (README)')
    version = subprocess.run([node, '--version'], capture_output=True, text=True).stdout
    if int(version.lstrip('v').split('.')[0]) < 18:
        pytest.fail(f'node {version.strip()} is older than 18, which the test client needs')
    if not (CLIENT_DIR / 'node_modules' / '@foxglove' / 'ws-protocol').is_dir():
        pytest.fail(f'the Foxglove test client is not installed: run `make node-client` '
                    f'(npm ci in {CLIENT_DIR})')
    return node


def read_lines(path: Path) -> list:
    """The client's JSON lines (a last line cut by a kill is left out)."""
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def plain(value):
    """A recorded value as the client writes it: NaN and infinities as strings."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return 'NaN' if math.isnan(value) else ('Infinity' if value > 0 else '-Infinity')
    return value


class LiveRun:
    """The graph (``eha_graph``'s :func:`run_graph`) on a thread of its own, with the bridge
    on a free port; :meth:`client` starts the Node client against it once the port is known;
    :meth:`join` returns the harness's result and the client's lines."""

    def __init__(self, env: dict, tmp_path: Path, config: GraphConfig, bridge_params=None,
                 timeout_s: float = 120.0):
        self.env, self.tmp = env, tmp_path
        self.port_file = tmp_path / 'bridge.port'
        params = dict(config.node_params)
        params['foxglove_bridge'] = dict(port_file=str(self.port_file), **(bridge_params or {}))
        config.foxglove = '127.0.0.1:0'
        config.node_params = params
        self.result = None
        self.error = None
        self.clients = []

        def run():
            try:
                self.result = run_graph(config, processes=True, env=env, timeout_s=timeout_s,
                                        log_dir=env.get('ROS_LOG_DIR'))
            except BaseException as exc:  # handed to join()
                self.error = exc
        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def port(self) -> int:
        end = time.monotonic() + CONNECT_TIMEOUT_S
        while time.monotonic() < end:
            if self.port_file.is_file():
                return int(self.port_file.read_text())
            if not self.thread.is_alive():
                raise AssertionError(f'the graph ended before the bridge served: {self.error}')
            time.sleep(0.02)
        raise AssertionError(f'the bridge wrote no port within {CONNECT_TIMEOUT_S:g} s')

    def client(self, name: str, *args, pass_fds=()) -> Path:
        out = self.tmp / f'{name}.jsonl'
        url = f'ws://127.0.0.1:{self.port()}'
        proc = subprocess.Popen([node_binary(), str(CLIENT), '--url', url, '--out', str(out),
                                 *args], cwd=CLIENT_DIR, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True, pass_fds=pass_fds)
        self.clients.append((proc, out))
        return out

    def join(self, timeout_s: float = 180.0):
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), f'the graph did not end within {timeout_s:g} s'
        lines = []
        for proc, out in self.clients:
            try:
                _, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
                raise AssertionError(f'the client did not end after the bridge closed: {err}')
            assert proc.returncode == 0, f'client exit {proc.returncode}: {err[-2000:]}'
            lines.append(read_lines(out))
        if self.error is not None:
            raise self.error
        return self.result, lines


def of_type(lines: list, kind: str) -> list:
    return [x for x in lines if x['type'] == kind]


def messages_by_topic(lines: list) -> dict:
    out: dict = {}
    for x in of_type(lines, 'message'):
        out.setdefault(x['topic'], []).append(x)
    return out


def recorded(path: Path) -> dict:
    """``topic -> [plain data]`` of an MCAP recording, in file order."""
    out: dict = {}
    for m in iter_decoded(str(path)):
        out.setdefault(m.topic, []).append(plain(message_to_plain_data(m.message)))
    return out


def test_the_client_gets_every_message_the_recording_holds(ros_env, tmp_path):
    node_binary()
    mcap = tmp_path / 'run.mcap'
    config = GraphConfig(mode='lockstep', duration_s=0.3, health=True, record=str(mcap),
                         health_params={'update_period_s': 0.1, 'window_s': 0.1})
    run = LiveRun(ros_env, tmp_path, config, {'wait_for_clients': 1})
    run.client('all', '--topics', 'all')
    result, (lines,) = run.join()
    assert result.complete, (result.lost, result.missing, result.fault)
    assert not of_type(lines, 'decodeError'), of_type(lines, 'decodeError')[:3]
    (info,) = of_type(lines, 'serverInfo')
    assert 'time' in info['capabilities'] and 'parameters' in info['capabilities']
    channels = {c['topic']: c for a in of_type(lines, 'advertise') for c in a['channels']}
    for topic in FULL_RATE:
        assert channels[topic]['encoding'] == 'cdr'
        assert channels[topic]['schemaEncoding'] == 'ros2msg'
    got = messages_by_topic(lines)
    want = recorded(mcap)
    ticks = len(result.state['tick'])
    assert ticks == 301 or ticks == 300, ticks
    for topic in (graph.TOPIC_STATE, graph.TOPIC_COMMAND, graph.TOPIC_SERVOVALVE,
                  graph.TOPIC_CLOCK, graph.TOPIC_HEALTH, graph.TOPIC_EVENTS):
        data = [m['data'] for m in got.get(topic, [])]
        assert len(data) == len(want.get(topic, [])), (topic, len(data), len(want.get(topic, [])))
        for k, (a, b) in enumerate(zip(data, want.get(topic, []))):
            assert a == b, f'{topic} message {k}: the client decoded {a}, the MCAP holds {b}'
    assert len(want[graph.TOPIC_STATE]) == ticks
    assert len(want[graph.TOPIC_HEALTH]) >= 1
    # /diagnostics has a publisher per node: the interleaving may differ between two
    # subscribers, so it compares as a multiset
    a = sorted(json.dumps(m['data'], sort_keys=True) for m in got[graph.TOPIC_DIAGNOSTICS])
    b = sorted(json.dumps(d, sort_keys=True) for d in want[graph.TOPIC_DIAGNOSTICS])
    assert a == b and len(a) > 0, (len(a), len(b))
    # the handshake is not recorded; the client has every node's reports and the start
    reports = [m['data'] for m in got[graph.TOPIC_HANDSHAKE]]
    assert set(config.nodes()) <= {r['name'] for r in reports}, {r['name'] for r in reports}
    assert any(r['name'] == COORDINATOR and 'start_time_ns' in {v['key'] for v in r['values']}
               for r in reports)
    # simulated time: the time capability runs to the last state's stamp
    times = [int(x['timestampNs']) for x in of_type(lines, 'time')]
    clock = [m['data']['clock'] for m in got[graph.TOPIC_CLOCK]]
    assert times == sorted(times) and len(times) == len(clock)
    assert times[-1] == clock[-1]['sec'] * 10 ** 9 + clock[-1]['nanosec']


def states_of(lines: list) -> list:
    return [m['data'] for m in messages_by_topic(lines).get(graph.TOPIC_STATE, [])]


def wait_for_state(run: LiveRun, lines: Path, sim_time_s: float) -> None:
    """Until the client writing ``lines`` has a state at ``sim_time_s`` or later."""
    end = time.monotonic() + CONNECT_TIMEOUT_S
    while not any(x['type'] == 'message' and x['topic'] == graph.TOPIC_STATE
                  and x['data']['sim_time_s'] >= sim_time_s
                  for x in (read_lines(lines) if lines.is_file() else [])):
        assert time.monotonic() < end and run.thread.is_alive(), \
            f'the run never reached {sim_time_s:g} s'
        time.sleep(0.05)


def test_a_late_joiner_gets_the_latched_history_then_every_state(ros_env, tmp_path):
    node_binary()
    # a scheduled wear change early in the run: an /eha/events message before the client is on
    config = GraphConfig(mode='realtime', duration_s=3.0,
                         events=[(0.05, 'servovalve_plant', {'radial_clearance_m': 2e-6})])
    run = LiveRun(ros_env, tmp_path, config)
    # the late client starts once a first one has seen the run at 0.5 s, well past the event
    early = run.client('early', '--topics', graph.TOPIC_STATE)
    wait_for_state(run, early, 0.5)
    run.client('late', '--topics', 'all')
    result, (_, lines) = run.join()
    assert result.complete, (result.lost, result.missing, result.fault)
    (event,) = [e for e in result.events if e['source'] == 'schedule']
    got = messages_by_topic(lines)
    events = [m['data'] for m in got[graph.TOPIC_EVENTS]]
    # the scheduled change, latched, exactly once; anything else on /eha/events (a realtime
    # watchdog's trips and resumptions under load) is what the graph published too
    scheduled = [e for e in events if e['source'] == 'schedule']
    assert [e['tick_index'] for e in scheduled] == [event['tick_index']]
    assert scheduled[0]['parameter_names'] == ['radial_clearance_m']
    published = {(e['source'], e['tick_index']) for e in result.events}
    assert {(e['source'], e['tick_index']) for e in events} <= published
    assert got[graph.TOPIC_HANDSHAKE], 'no latched handshake report reached the late client'
    states = states_of(lines)
    ticks = [s['tick'] for s in states]   # plant integration steps
    first = ticks[0]
    assert states[0]['sim_time_s'] > 0.4, 'the client was not late: the test proves nothing'
    # from its first state on, every state the plant published (the harness's, which has no
    # gap: result.complete), in order
    assert ticks == [int(t) for t in result.state['tick'] if t >= first]
    assert states[-1]['final_state'] is True


def test_parameters_are_listed_set_live_and_refused_by_the_nodes_rules(ros_env, tmp_path):
    node_binary()
    wear = 4.0e-6   # the nominal clearance is 2.5 um
    base = dict(mode='lockstep', scenario='sine_0p1_5pi')
    run = LiveRun(ros_env, tmp_path, GraphConfig(**base), {'wait_for_clients': 1})
    # a watcher holds the start until it is subscribed; the operator's client comes mid-run
    watcher = run.client('watcher', '--topics', 'all')
    wait_for_state(run, watcher, 0.1)
    run.client('params', '--topics', graph.TOPIC_STATE, '--get-params', 'all',
               '--set', f'servovalve_plant.radial_clearance_m={wear}',
               '--set', 'servovalve_plant.radial_clearence_m=3e-6',
               '--set', 'servovalve_plant.overlap_supply_m="wide"',
               '--set', 'servovalve_plant.overlap_return_m=0.5',
               '--set', 'no_such_node.gain=1.0')
    result, (_, lines) = run.join()
    assert result.complete, (result.lost, result.missing, result.fault)
    replies = {r.get('id'): r['parameters'] for r in of_type(lines, 'parameterValues')}
    listed = {p['name']: p['value'] for p in replies['get-params']}
    assert 'servovalve_plant.radial_clearance_m' in listed
    assert listed['servovalve_plant.radial_clearance_m'] != wear   # before the set
    assert {n.split('.')[0] for n in listed} == set(graph.NODES) - {'health_monitor'}, listed
    # only the valid set took effect; each other one is an error status with its reason
    assert [(p['name'], p['value']) for p in replies['set-params']] == [
        ('servovalve_plant.radial_clearance_m', wear)]
    errors = [s['message'] for s in of_type(lines, 'status') if s['level'] == 2]
    assert any('radial_clearence_m' in e and 'radial_clearance_m' in e for e in errors), errors
    assert any('overlap_supply_m' in e and 'type' in e for e in errors), errors
    assert any('overlap_return_m' in e and 'refused' in e for e in errors), errors
    assert any('no_such_node' in e for e in errors), errors
    assert len(errors) == 4, errors
    # the change is on /eha/events as live, applied at one tick
    (live,) = [e for e in result.events if e['source'] == 'live']
    assert live['node'] == 'servovalve_plant'
    assert live['changes'] == {'radial_clearance_m': wear}
    k = live['tick_index']
    assert 0 < k < len(result.state['tick']) - 1, k
    # ... and in the states: the physics loop with that change scheduled at tick k is the live
    # run, bit for bit (a lockstep graph is the physics loop, test_rig); without it, the
    # states differ after k

    def physics(events):
        return simulate(default_params(), base['scenario'], controller_period_s=1e-3,
                        record_dt_s=None, events=events)
    scheduled = physics([((k - 0.5) / 1000.0, {'radial_clearance_m': wear})])
    assert [e['tick'] for e in scheduled.events] == [k]
    untouched = physics([])
    n = result.state['tick'].size
    for field in ('p12_pa', 'spool_position_m', 'jack_position_m'):
        assert (result.state[field] == scheduled[field][:n]).all(), field
        assert (result.state[field][:k] == untouched[field][:k]).all(), field
        assert (result.state[field][k + 1:] != untouched[field][k + 1:n]).any(), field


def test_a_slow_client_costs_the_graph_nothing_and_its_drops_are_counted(ros_env, tmp_path):
    node_binary()
    config = GraphConfig(mode='realtime', duration_s=5.0)
    depth = 200
    run = LiveRun(ros_env, tmp_path, config, {'wait_for_clients': 1, 'client_queue_depth': depth,
                                              'send_buffer_b': 8192})
    # a socket with a small receive buffer: the kernel cannot absorb 2 s of the graph
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(('127.0.0.1', run.port()))
    try:
        run.client('slow', '--topics', 'all', '--socket-fd', str(sock.fileno()),
                   '--pause-after-s', '1.0', '--pause-s', '2.0',
                   '--pause-from-topic', graph.TOPIC_STATE, pass_fds=(sock.fileno(),))
    finally:
        sock.close()   # the client holds its own copy
    result, (lines,) = run.join()
    # the graph lost nothing
    assert result.complete, (result.lost, result.missing, result.fault)
    # the bridge counted its drops per channel on /diagnostics
    status = result.diagnostics['foxglove_bridge: clients']
    assert status['level'] == 1, status          # WARN
    dropped = {k: int(v) for k, v in status['values'].items() if ' dropped ' in k}
    assert dropped.get(f'client 1 dropped {graph.TOPIC_STATE}', 0) > 0, status['values']
    # the client saw it once it read again, and its last count accounts for every state
    kinds = [x['type'] for x in lines]
    assert 'paused' in kinds and 'resumed' in kinds
    resumed = kinds.index('resumed')
    warnings = [x for x in lines[resumed:] if x['type'] == 'status' and x.get('id') == 'dropped']
    assert warnings, 'the client was not told about its drops'
    last = warnings[-1]['message']
    told = dict((t, int(n)) for t, n in re.findall(r'(/[\w/]+): (\d+)', last))
    states = len(states_of(lines))
    assert states + told[graph.TOPIC_STATE] == len(result.state['tick']), (states, told)
