"""Recording at the graph's rate: messages recorded and lost, recorder CPU, file size, replay
timing.

A synthetic publisher process stands in for the actuator graph: it publishes ``/eha/state``,
``/eha/command``, ``/eha/servovalve_command``, ``/diagnostics`` and ``/clock`` at 1 kHz and
``/eha/health`` at 10 Hz, with realistic contents (a full ActuatorState, a two-entry
DiagnosticArray), on the graph's QoS, on an absolute 1 ms schedule stamped with simulated time.
The ``recorder`` console script records everything; afterwards the first seconds of
``/eha/state`` are replayed with ``eha-replay`` to a subscriber that compares inter-arrival
times with the recorded spacing.

Prints one JSON object::

    python bench/recording.py [--duration 60] [--rate 1000] [--replay-seconds 10]
    python bench/recording.py --graph          # record the real graph instead
    python bench/recording.py --kill-trials 10 # SIGKILL the recorder, eha-recover, rosbags
    python bench/recording.py --smoke          # 1 s recorded, 0.5 s replayed: a check

``--graph``: the real node graph instead (each node its own process, realtime at 1 kHz, the
``sine_0p1_5pi`` command continued for the duration, health monitor on); published counts are
then what the publishers' sequence numbers account for (recorded + lost + missed at start), and
the lateness figures are the plant's state inter-arrival jitter at the harness.

Figures: per topic published / recorded / lost (sequence gaps) / missed at start; recorder CPU
(process CPU time over wall time while publishing, 1.0 = one core); file bytes per simulated
second; replay timing error p50/p99/max (|received inter-arrival - recorded spacing|, µs) and
the replayed messages received.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import platform
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = Path(__file__).resolve()
BIN = Path(sys.executable).parent
CLK_TCK = os.sysconf('SC_CLK_TCK')


# --- synthetic publisher (subprocess role) ----------------------------------------------------

def _publish(duration_s: float, rate_hz: float, wait_s: float) -> dict:
    """Publish the graph's topics on an absolute schedule; returns counts and lateness."""
    import rclpy
    from rclpy.duration import Duration
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rosgraph_msgs.msg import Clock

    from eha_ros.msg import ActuatorCommand, ActuatorState, HealthStatus, ServovalveCommand
    from eha_ros import graph

    rclpy.init()
    node = rclpy.create_node('bench_graph_publisher')
    qos = graph.graph_qos()
    pubs = {
        graph.TOPIC_STATE: node.create_publisher(ActuatorState, graph.TOPIC_STATE, qos),
        graph.TOPIC_COMMAND: node.create_publisher(ActuatorCommand, graph.TOPIC_COMMAND, qos),
        graph.TOPIC_SERVOVALVE: node.create_publisher(ServovalveCommand,
                                                      graph.TOPIC_SERVOVALVE, qos),
        graph.TOPIC_DIAGNOSTICS: node.create_publisher(DiagnosticArray,
                                                       graph.TOPIC_DIAGNOSTICS, qos),
        graph.TOPIC_CLOCK: node.create_publisher(Clock, graph.TOPIC_CLOCK, qos),
        graph.TOPIC_HEALTH: node.create_publisher(HealthStatus, graph.TOPIC_HEALTH, qos),
    }
    deadline = time.monotonic() + wait_s
    while any(p.get_subscription_count() == 0 for p in pubs.values()):
        if time.monotonic() > deadline:
            raise SystemExit('bench publisher: the recorder did not match')
        time.sleep(0.02)

    state = ActuatorState(model='hf')
    state.header.frame_id = 'jack'
    cmd, sv, clock = ActuatorCommand(), ServovalveCommand(), Clock()
    cmd.header.frame_id = 'jack'
    diag = DiagnosticArray()
    status = DiagnosticStatus(level=DiagnosticStatus.OK, name='eha/plant', message='ok',
                              hardware_id='eha-sim')
    status.values = [KeyValue(key='real_time_factor', value='1.0'),
                     KeyValue(key='tick', value='0')]
    diag.status = [status]
    health = HealthStatus(method='bench', message='ok', samples_used=1000)
    health_every = max(1, int(round(rate_hz / 10.0)))
    every_tick = ((graph.TOPIC_CLOCK, clock), (graph.TOPIC_COMMAND, cmd),
                  (graph.TOPIC_SERVOVALVE, sv), (graph.TOPIC_STATE, state),
                  (graph.TOPIC_DIAGNOSTICS, diag))

    n_ticks = int(round(duration_s * rate_hz))
    counts = {t: 0 for t in pubs}
    lateness = np.zeros(n_ticks)
    period = 1.0 / rate_hz
    start = time.monotonic()
    for k in range(n_ticks):
        target = start + k * period
        now = time.monotonic()
        if target > now:
            time.sleep(target - now)
        lateness[k] = time.monotonic() - target
        t_ns = int(round(k * period * 1e9))
        sec, nsec = divmod(t_ns, 1_000_000_000)
        x = 0.05 * math.sin(2 * math.pi * 0.5 * k * period)
        for msg in (state, cmd, sv, diag):
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
        clock.clock.sec, clock.clock.nanosec = sec, nsec
        state.jack_position_m = x
        state.jack_position_measured_m = round(x / 1e-6) * 1e-6
        state.jack_velocity_m_s = 0.05 * math.pi * math.cos(math.pi * k * period)
        state.spool_position_m = 1e-4 * math.sin(2 * math.pi * 3 * k * period)
        state.flapper_position_m = 1e-5 * math.sin(2 * math.pi * 3 * k * period)
        state.p1_pa, state.p2_pa = 1.0e7 + 2e6 * x, 1.0e7 - 2e6 * x
        state.p12_pa = 4e6 * x
        state.load_flow_m3_s = 1e-4 * x
        state.coil_current_a = 0.01 * math.sin(k * period)
        state.torque_motor_force_n = 2.0 * state.coil_current_a
        state.sim_time_s = k * period
        state.tick = k
        cmd.position_setpoint_m = x
        sv.current_command_a = state.coil_current_a
        status.values[1].value = str(k)
        for topic, msg in every_tick:
            pubs[topic].publish(msg)
            counts[topic] += 1
        if k % health_every == 0:
            health.header.stamp.sec, health.header.stamp.nanosec = sec, nsec
            pubs[graph.TOPIC_HEALTH].publish(health)
            counts[graph.TOPIC_HEALTH] += 1
    wall = time.monotonic() - start
    for pub in pubs.values():
        pub.wait_for_all_acked(Duration(seconds=5.0))
    rclpy.try_shutdown()
    return {'published': counts, 'simulated_s': n_ticks * period, 'wall_s': wall,
            'lateness_p50_us': float(np.percentile(lateness, 50) * 1e6),
            'lateness_p99_us': float(np.percentile(lateness, 99) * 1e6)}


# --- replay timing (in-process subscriber) ----------------------------------------------------

def _replay_timing(path: Path, seconds: float, env: dict, cwd: Path) -> dict:
    """Replay the first ``seconds`` of /eha/state and compare inter-arrival with spacing."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from eha_ros.msg import ActuatorState
    from eha_ros import graph
    from eha_ros.recording.reader import McapReader
    from eha_ros.recording.writer import McapWriter

    # A file holding the first `seconds` of /eha/state, as recorded.
    clip = cwd / 'replay_clip.mcap'
    recorded = []
    with McapWriter(clip) as writer:
        reader = McapReader(path, topics=[graph.TOPIC_STATE], decode=False, strict=True)
        for msg in reader:
            if recorded and msg.log_time_ns - recorded[0] > seconds * 1e9:
                break
            if not writer.topics:
                writer.add_topic(msg.topic, msg.type_name,
                                 offered_qos_profiles=reader.channels[msg.topic].metadata.get(
                                     'offered_qos_profiles'))
            writer.write(msg.topic, msg.data, msg.log_time_ns, msg.publish_time_ns,
                         msg.sequence)
            recorded.append(msg.log_time_ns)
    spacing = np.diff(np.asarray(recorded, dtype=np.int64))

    received = []   # (sequence in the clip, reception time ns)
    context = Context()
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_LOG_DIR',
                                           'RMW_IMPLEMENTATION',
                                           'ROS_AUTOMATIC_DISCOVERY_RANGE')})
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node('bench_replay_sink', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        node.create_subscription(
            ActuatorState, graph.TOPIC_STATE,
            lambda data, info: received.append(info['received_timestamp']),
            graph.graph_qos(depth=1000), raw=True)
        replay = subprocess.Popen([str(BIN / 'eha-replay'), str(clip), '--no-clock',
                                   '--wait-for-subscribers', '10'], env=env, cwd=cwd,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + seconds + 60
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if replay.poll() is not None and len(received) >= len(recorded):
                break
            if replay.poll() is not None:
                deadline = min(deadline, time.monotonic() + 2.0)
        if replay.poll() is None:
            replay.kill()
        replay.communicate()
    finally:
        rclpy.try_shutdown(context=context)
    arrivals = np.diff(np.asarray(received, dtype=np.int64))
    n = min(arrivals.size, spacing.size)
    err_us = np.abs(arrivals[:n] - spacing[:n]) / 1e3
    return {'replayed_s': seconds, 'messages': len(recorded), 'received': len(received),
            'recorded_spacing_mean_us': float(spacing.mean() / 1e3) if spacing.size else None,
            'error_p50_us': float(np.percentile(err_us, 50)) if n else None,
            'error_p99_us': float(np.percentile(err_us, 99)) if n else None,
            'error_max_us': float(err_us.max()) if n else None}


# --- the benchmark ----------------------------------------------------------------------------

def _cpu_s(pid: int) -> float:
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK   # utime + stime


def run_real_graph(env: dict, duration_s: float, rate_hz: float) -> dict:
    """Run the actuator graph in realtime for ``duration_s`` (``--graph``); returns what the
    synthetic publisher reports, from the harness's view of the run."""
    from eha_ros.harness import GraphConfig, run_graph
    r = run_graph(GraphConfig(scenario='sine_0p1_5pi', mode='realtime', duration_s=duration_s,
                              rate_hz=rate_hz, health=True), processes=True, env=env,
                  timeout_s=60)
    arrival = r.state['arrival_s']
    late = np.abs(np.diff(arrival) - 1.0 / rate_hz) * 1e6 if arrival.size > 1 else np.zeros(1)
    timing = {name: {k: float(v) for k, v in d['values'].items()}
              for name, d in r.diagnostics.items() if name.endswith(': timing')}
    return {'simulated_s': r.sim_s, 'wall_s': r.wall_s, 'published': None,
            'lateness_p50_us': float(np.percentile(late, 50)),
            'lateness_p99_us': float(np.percentile(late, 99)),
            'node_timing': {n: {k: t.get(k) for k in (
                'Events since startup', 'On time since startup (%)', 'Late ticks since startup',
                'Slipped ticks since startup', 'Overruns since startup')}
                for n, t in timing.items()},
            'health_estimates': len(r.health)}


def run(duration_s: float = 60.0, rate_hz: float = 1000.0, replay_s: float = 10.0,
        graph: bool = False) -> dict:
    """Record ``duration_s`` of 1 kHz traffic and replay part of it; returns the figures."""
    from eha_ros.recording.reader import scan
    from eha_ros.isolation import ros_environment

    load_before = os.getloadavg()
    with ros_environment() as env, tempfile.TemporaryDirectory(prefix='eha_bench_rec_') as tmp:
        env.pop('ROS_PYTHON_CHECK_FIELDS', None)   # field checks are a test aid, not a cost
        cwd = Path(tmp)
        output = cwd / 'bench.mcap'
        recorder = subprocess.Popen([str(BIN / 'recorder'), '-o', str(output)], env=env,
                                    cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                    text=True)
        try:
            if graph:
                cpu0, wall0 = _cpu_s(recorder.pid), time.monotonic()
                pub = run_real_graph(env, duration_s, rate_hz)
                cpu1, wall1 = _cpu_s(recorder.pid), time.monotonic()
                time.sleep(1.0)  # the last messages reach the recorder
            else:
                source = subprocess.Popen(
                    [sys.executable, str(HERE), '--role', 'publisher', '--duration',
                     str(duration_s), '--rate', str(rate_hz)], env=env, cwd=cwd,
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                # CPU of the recorder while traffic flows (discovery excluded as far as
                # possible).
                time.sleep(min(2.0, duration_s / 10))
                cpu0, wall0 = _cpu_s(recorder.pid), time.monotonic()
                out, err = source.communicate(timeout=duration_s + 120)
                cpu1, wall1 = _cpu_s(recorder.pid), time.monotonic()
        finally:
            if recorder.poll() is None:
                recorder.send_signal(signal.SIGINT)
            _, rec_err = recorder.communicate(timeout=60)
        if recorder.returncode != 0:
            raise RuntimeError(f'recorder failed: {rec_err.strip()}')
        if not graph:
            if source.returncode != 0:
                raise RuntimeError(f'publisher failed: {err.strip()}')
            pub = json.loads(out.strip().splitlines()[-1])

        info = scan(output, strict=True)
        lost = info.lost_messages()
        missed = info.run_info().get('missed_at_start', {})
        if pub['published'] is None:  # the graph: as far as the sequence numbers tell
            pub['published'] = {t: n + lost.get(t, 0) + missed.get(t, 0)
                                for t, n in info.message_counts.items()}
        per_topic = {}
        for topic, published in pub['published'].items():
            recorded = info.message_counts.get(topic, 0)
            per_topic[topic] = {
                'published': published, 'recorded': recorded, 'lost': lost.get(topic, 0),
                'missed_at_start': missed.get(topic, 0),
                'unaccounted': published - recorded - lost.get(topic, 0) - missed.get(topic, 0)}
        size = output.stat().st_size
        result = {
            'benchmark': 'recording',
            'source': 'graph' if graph else 'synthetic_publisher',
            'rate_hz': rate_hz,
            'simulated_s': pub['simulated_s'],
            'publisher_wall_s': round(pub['wall_s'], 3),
            'publisher_lateness_p50_us': round(pub['lateness_p50_us'], 1),
            'publisher_lateness_p99_us': round(pub['lateness_p99_us'], 1),
            'topics': per_topic,
            'messages_recorded': sum(v['recorded'] for v in per_topic.values()),
            'messages_lost': sum(v['lost'] for v in per_topic.values()),
            'recorder_cpu_fraction': round((cpu1 - cpu0) / (wall1 - wall0), 3),
            'file_bytes': size,
            'file_bytes_per_simulated_s': round(size / pub['simulated_s']),
            'chunks': info.chunks,
            'replay': _replay_timing(output, min(replay_s, duration_s), env, cwd),
            'cpu': platform.processor() or platform.machine(),
            'cores': os.cpu_count(),
            # what the recorder itself stored in the file's eha_ros metadata record
            'counts_stored_in_file': {
                'recorded_messages': json.loads(
                    info.metadata['eha_ros']['recorded_messages']),
                'lost_messages': lost},
            'load_average_1_5_15_before': [round(x, 2) for x in load_before],
            'load_average_1_5_15_after': [round(x, 2) for x in os.getloadavg()],
        }
        if graph:
            result['node_timing'] = pub['node_timing']
            result['health_estimates'] = pub['health_estimates']
        return result


def kill_trials(trials: int, rate_hz: float = 1000.0, seed: int = 0) -> dict:
    """SIGKILL the recorder at random moments while the synthetic publisher runs; recover
    each file with ``eha-recover`` and read it with rosbags (an independent reader).

    A trial passes when rosbags decodes every message of the recovered file, their count
    equals what the killed file holds up to its last complete chunk (every message received
    before the last flushed chunk is there), no ``/eha/state`` tick is there twice, and the
    ticks missing between the first and the last recovered are exactly the losses the
    recovered file reports for it (messages the recorder never received, counted from the
    sequence numbers)."""
    from rosbags.highlevel import AnyReader

    from eha_ros.graph import TOPIC_STATE
    from eha_ros.isolation import ros_environment
    from eha_ros.recording.reader import scan

    rng = np.random.default_rng(seed)
    results = []
    for trial in range(trials):
        kill_after_s = float(rng.uniform(0.5, 4.0))
        with ros_environment() as env, tempfile.TemporaryDirectory(prefix='eha_kill_') as tmp:
            env.pop('ROS_PYTHON_CHECK_FIELDS', None)
            cwd = Path(tmp)
            output, fixed = cwd / 'killed.mcap', cwd / 'recovered.mcap'
            recorder = subprocess.Popen([str(BIN / 'recorder'), '-o', str(output)], env=env,
                                        cwd=cwd, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE, text=True)
            source = subprocess.Popen(
                [sys.executable, str(HERE), '--role', 'publisher', '--duration', '6',
                 '--rate', str(rate_hz)], env=env, cwd=cwd, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE, text=True)
            # the moment counts from the first recorded chunk (the recorder is then running)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    if scan(output).chunks:
                        break
                except Exception:
                    pass
                time.sleep(0.05)
            time.sleep(kill_after_s)
            recorder.send_signal(signal.SIGKILL)
            recorder.communicate()
            source.communicate(timeout=120)
            killed = scan(output)
            done = subprocess.run([str(BIN / 'eha-recover'), str(output), '-o', str(fixed)],
                                  env=env, cwd=cwd, capture_output=True, text=True)
            decoded, ticks, error = 0, [], None
            try:
                with AnyReader([fixed]) as reader:
                    for conn, _, raw in reader.messages():
                        msg = reader.deserialize(raw, conn.msgtype)
                        decoded += 1
                        if conn.topic == TOPIC_STATE:
                            ticks.append(int(msg.tick))
            except Exception as exc:  # reported, and the trial fails
                error = f'{type(exc).__name__}: {exc}'
            held = sum(killed.message_counts.values())
            # rosbags yields messages by log time, which need not follow tick order exactly:
            # compare the set of ticks
            unique = np.unique(ticks)
            missing = int(unique[-1] - unique[0] + 1 - unique.size) if unique.size else 0
            recovered = scan(fixed) if done.returncode == 0 else None
            lost = recovered.lost_messages() if recovered else {}
            publishers = (recovered.run_info().get('publishers', {}).get(TOPIC_STATE)
                          if recovered else None)
            results.append({
                'kill_after_first_chunk_s': round(kill_after_s, 3),
                'killed_file_complete': killed.complete, 'killed_file_messages': held,
                'recover_exit': done.returncode, 'rosbags_decoded': decoded,
                'rosbags_error': error, 'state_ticks': len(ticks),
                'state_ticks_missing': missing, 'lost_reported': lost,
                'state_ticks_repeated': len(ticks) - len(set(ticks)),
                'state_publishers': publishers,
                'passed': (done.returncode == 0 and error is None and decoded == held
                           and held > 0 and not killed.complete
                           and missing == lost.get(TOPIC_STATE, -1)
                           and len(ticks) == len(set(ticks)))})
    return {'benchmark': 'recording_kill_trials', 'trials': trials,
            'passed': sum(r['passed'] for r in results), 'results': results}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--duration', type=float, default=60.0, help='seconds recorded (60)')
    ap.add_argument('--rate', type=float, default=1000.0, help='publication rate, Hz (1000)')
    ap.add_argument('--replay-seconds', type=float, default=10.0,
                    help='seconds of /eha/state replayed for the timing figures (10)')
    ap.add_argument('--graph', action='store_true',
                    help='record the real actuator graph instead of the synthetic publisher')
    ap.add_argument('--kill-trials', type=int, default=0, metavar='N',
                    help='instead: SIGKILL the recorder at N random moments, recover, check')
    ap.add_argument('--role', choices=('bench', 'publisher'), default='bench',
                    help=argparse.SUPPRESS)
    ap.add_argument('--smoke', action='store_true',
                    help='1 s recorded, 0.5 s replayed (with --kill-trials: one trial): a check')
    args = ap.parse_args()
    if args.smoke and args.role == 'bench':
        args.duration, args.replay_seconds = 1.0, 0.5
        args.kill_trials = min(args.kill_trials, 1)
    if args.kill_trials:
        print(json.dumps(kill_trials(args.kill_trials, args.rate)))
        return 0
    if args.role == 'publisher':
        print(json.dumps(_publish(args.duration, args.rate, wait_s=15.0)))
        return 0
    print(json.dumps({**run(args.duration, args.rate, args.replay_seconds, args.graph),
                      'smoke': args.smoke}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
