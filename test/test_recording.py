"""Recording tools: MCAP layout and round trips, truncated files, the recorder node, lost
message counting, ``eha-echo``, ``eha-replay`` and ``eha-compare``.

File-format tests run in memory (``io.BytesIO``); tests that start nodes use the ``ros_env``
fixture (own ROS domain, temporary log folder) for the test process and every subprocess.
Waits are for events with generous timeouts; no assertion depends on how fast anything runs.
"""

from contextlib import contextmanager
import csv
import io
import json
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

import numpy as np
from numpy.testing import assert_allclose
import pytest
import yaml

from eha_ros import graph
from eha_ros.recording.arrays import load_topic_arrays, message_to_plain_data
from eha_ros.recording.definitions import (CorruptError, count_sequence_gaps,
                                           message_definition, NotMcapError, RecordingError,
                                           SequenceGapCounter, TruncatedError, type_hash)
from eha_ros.recording.reader import McapReader, scan
from eha_ros.recording.writer import McapWriter
from eha_ros.testing import sample_message

DISCOVERY_TIMEOUT_S = 10.0
PROCESS_TIMEOUT_S = 60.0
BIN = Path(sys.executable).parent


# --- helpers ----------------------------------------------------------------------------------

def _bitwise(value):
    """Plain data with floats as hex strings, so comparisons are bit for bit."""
    if isinstance(value, dict):
        return {k: _bitwise(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_bitwise(v) for v in value]
    if isinstance(value, float):
        return value.hex()
    return value


def _fields(msg):
    return _bitwise(message_to_plain_data(msg))


def _diagnostics(seed: int = 0):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    msg = DiagnosticArray()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000 + seed, 123_456_789
    msg.header.frame_id = 'eha ✓'
    for i in range(2):
        status = DiagnosticStatus(level=DiagnosticStatus.WARN, name=f'eha/valve{i}',
                                  message=f'drift {seed}', hardware_id='sv-1')
        status.values = [KeyValue(key='radial_clearance_m', value=f'{2.5e-6 + i:.9g}'),
                         KeyValue(key='overlap_m', value='-1e-6')]
        msg.status.append(status)
    return msg


def _clock(t_ns: int):
    from rosgraph_msgs.msg import Clock

    msg = Clock()
    msg.clock.sec, msg.clock.nanosec = divmod(t_ns, 1_000_000_000)
    return msg


def graph_sample(topic: str, seed: int = 0):
    """A distinctive message of the topic's type (every field non-default)."""
    type_name = graph.TOPICS[topic]
    if type_name.startswith('diagnostic_msgs/'):
        return _diagnostics(seed)
    if type_name.startswith('rosgraph_msgs/'):
        return _clock(1_700_000_000_000_000_000 + seed * 1_000_000)
    msg = sample_message(graph.message_class(type_name), seed=seed)
    if hasattr(msg, 'tick'):
        msg.tick = seed
    return msg


def _state(t_ns: int, tick: int, model: str = 'hf', jack=0.0, p12=0.0, spool=0.0):
    from eha_ros.msg import ActuatorState

    msg = ActuatorState(jack_position_m=float(jack), p12_pa=float(p12),
                        spool_position_m=float(spool), tick=tick, model=model)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
    return msg


def _write_states(path, times_ns, jack, p12, spool, model):
    with McapWriter(path) as writer:
        for i, t in enumerate(times_ns):
            writer.write_message(graph.TOPIC_STATE,
                                 _state(t, i, model, jack[i], p12[i], spool[i]),
                                 log_time_ns=int(t))


def _one_line_error(stderr: str, prog: str):
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith(f'{prog}: error:'), stderr


@contextmanager
def ros_node(name: str):
    """A node in the test process on its own context (uses the ``ros_env`` environment)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = executor = None
    try:
        node = rclpy.create_node(name, context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        yield node, executor
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def _wait_matched(publishers, timeout=DISCOVERY_TIMEOUT_S):
    deadline = time.monotonic() + timeout
    while any(p.get_subscription_count() == 0 for p in publishers):
        assert time.monotonic() < deadline, 'no subscriber matched'
        time.sleep(0.02)


def _start_recorder(output, env, cwd, *extra):
    return subprocess.Popen([str(BIN / 'recorder'), '-o', str(output), *extra], env=env,
                            cwd=cwd, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _stop(process, sig=signal.SIGINT):
    """Signal a process and collect its output; kill it if it hangs."""
    if process.poll() is None:
        process.send_signal(sig)
    try:
        out, err = process.communicate(timeout=PROCESS_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    return out, err


# --- schema text ------------------------------------------------------------------------------

def test_schema_text_has_every_dependency_once():
    text = message_definition('eha_ros/msg/ActuatorState')
    share = Path(sys.prefix) / 'share'
    assert text.startswith((share / 'eha_ros/msg/ActuatorState.msg').read_text())
    assert text.count('MSG: std_msgs/Header\n') == 1
    assert text.count('MSG: builtin_interfaces/Time\n') == 1
    assert text.count('MSG: ') == 2
    assert '\n' + '=' * 80 + '\nMSG: std_msgs/Header\n' + (
        share / 'std_msgs/msg/Header.msg').read_text() in text
    for line in text.splitlines():
        assert set(line) != {'='} or len(line) == 80

    diag = message_definition('diagnostic_msgs/DiagnosticArray')
    for dep in ('diagnostic_msgs/DiagnosticStatus', 'diagnostic_msgs/KeyValue',
                'std_msgs/Header', 'builtin_interfaces/Time'):
        assert diag.count(f'MSG: {dep}\n') == 1, dep
    assert diag.count('MSG: ') == 4
    # Time is needed by Header and by Clock: nested dependencies resolve recursively.
    assert message_definition('rosgraph_msgs/msg/Clock').count('MSG: ') == 1


def test_type_hash_from_installed_description():
    assert type_hash('eha_ros/msg/ActuatorState').startswith('RIHS01_')
    assert len(type_hash('std_msgs/msg/Header')) == len('RIHS01_') + 64


# --- round trips ------------------------------------------------------------------------------

def test_round_trip_every_message_type_in_memory():
    buf = io.BytesIO()
    sent = []
    with McapWriter(buf, chunk_size=2048, run_info={'case': 'round trip'}) as writer:
        for i in range(20):
            for topic in graph.TOPICS:
                msg = graph_sample(topic, seed=i)
                t = 1_000_000_000 + i * 1_000_000 + len(sent)
                writer.write_message(topic, msg, log_time_ns=t, publish_time_ns=t - 7,
                                     sequence=i + 1)
                sent.append((topic, t, msg))
        writer.lost_counts[graph.TOPIC_STATE] = 3
    data = buf.getvalue()

    reader = McapReader(io.BytesIO(data), strict=True)
    received = list(reader)
    assert reader.complete and reader.problem is None
    assert len(received) == len(sent)
    for (topic, t, msg), rec in zip(sent, received):
        assert rec.topic == topic
        assert rec.type_name == graph.TOPICS[topic]
        assert (rec.log_time_ns, rec.publish_time_ns) == (t, t - 7)
        assert _fields(rec.message) == _fields(msg), topic

    info = scan(data, strict=True)
    assert info.complete and info.chunks > 1
    assert info.topics == graph.TOPICS
    assert all(n == 20 for n in info.message_counts.values())
    for topic, channel in info.channels.items():
        assert channel.message_encoding == 'cdr' and channel.schema_encoding == 'ros2msg'
        profiles = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert profiles[0]['reliability'] == 'reliable'
        assert profiles[0]['history'] == 'keep_last' and profiles[0]['depth'] == 1000
        assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
    bag = info.rosbag2_metadata()
    assert bag['version'] == 9 and bag['storage_identifier'] == 'mcap'
    assert bag['message_count'] == len(sent)
    assert {t['topic_metadata']['name']: t['message_count']
            for t in bag['topics_with_message_count']} == {t: 20 for t in graph.TOPICS}
    assert info.lost_messages()[graph.TOPIC_STATE] == 3
    assert info.lost_messages()[graph.TOPIC_CLOCK] == 0
    assert info.run_info() == {'case': 'round trip'}

    # The file is standard MCAP: the reference reader decodes it through its summary.
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    ref = make_reader(io.BytesIO(data), decoder_factories=[DecoderFactory()])
    assert ref.get_header().profile == 'ros2'
    assert ref.get_summary().statistics.message_count == len(sent)
    decoded = [m for _, _, _, m in ref.iter_decoded_messages()]
    assert [_fields(m) for m in decoded] == [_fields(m) for _, _, m in sent]
    assert {m.name for m in ref.iter_metadata()} == {'rosbag2', 'eha_ros'}


def test_topic_arrays_for_analysis(tmp_path):
    buf = io.BytesIO()
    t = 5_000_000_000 + np.arange(50) * 1_000_000
    x = np.sin(np.arange(50) / 7.0)
    _write_states(buf, t, x, 1e5 * x, 1e-4 * x, 'lut')
    arrays = load_topic_arrays(buf.getvalue(), graph.TOPIC_STATE)
    np.testing.assert_array_equal(arrays['stamp_ns'], t)
    np.testing.assert_array_equal(arrays['jack_position_m'], x)
    np.testing.assert_array_equal(arrays['p12_pa'], 1e5 * x)
    np.testing.assert_array_equal(arrays['tick'], np.arange(50))
    assert arrays['jack_position_m'].dtype == np.float64
    assert set(arrays['model']) == {'lut'}
    with pytest.raises(KeyError, match='/eha/command'):
        load_topic_arrays(buf.getvalue(), graph.TOPIC_COMMAND)
    with pytest.raises(RecordingError) as err:  # one error type for every caller
        load_topic_arrays(buf.getvalue(), graph.TOPIC_COMMAND)
    assert str(err.value).startswith('input has no topic /eha/command (topics: /eha/state')
    with pytest.raises(RecordingError, match='cannot read .*missing.mcap'):
        load_topic_arrays(tmp_path / 'missing.mcap', graph.TOPIC_STATE)


def test_writer_refuses_to_overwrite(tmp_path):
    path = tmp_path / 'a.mcap'
    path.write_bytes(b'keep me')
    with pytest.raises(FileExistsError):
        McapWriter(path)
    assert path.read_bytes() == b'keep me'


# --- truncated and damaged files --------------------------------------------------------------

def _chunked_file(n_messages=1000, per_chunk=50):
    """An in-memory recording with a chunk closed every ``per_chunk`` messages; returns the
    bytes and the chunk indexes of its summary (sorted by offset)."""
    buf = io.BytesIO()
    with McapWriter(buf, chunk_size=1 << 30) as writer:
        for i in range(n_messages):
            writer.write_message(graph.TOPIC_STATE, _state(i * 1_000_000, i, jack=i * 1e-3),
                                 log_time_ns=i * 1_000_000)
            if (i + 1) % per_chunk == 0:
                writer.flush()
    data = buf.getvalue()
    from mcap.reader import make_reader
    chunks = sorted(make_reader(io.BytesIO(data)).get_summary().chunk_indexes,
                    key=lambda c: c.chunk_start_offset)
    assert len(chunks) == n_messages // per_chunk
    return data, chunks


def _chunk_end(chunk):
    return chunk.chunk_start_offset + chunk.chunk_length


def _inside_payload(chunk):
    """A byte offset in the middle of a chunk's compressed data (the record's last field)."""
    return _chunk_end(chunk) - chunk.compressed_size // 2


@pytest.mark.parametrize('fraction', [0.13, 0.5, 0.77, 0.999])
def test_truncated_file_reads_up_to_last_complete_chunk(fraction):
    data, chunks = _chunked_file()
    cut = int(len(data) * fraction)
    complete_chunks = sum(1 for c in chunks if _chunk_end(c) <= cut)
    reader = McapReader(data[:cut])
    ticks = [m.message.tick for m in reader]
    assert ticks == list(range(50 * complete_chunks))
    assert not reader.complete and 'truncated' in reader.problem
    with pytest.raises(TruncatedError):
        list(McapReader(data[:cut], strict=True))
    info = scan(data[:cut])
    assert not info.complete and info.message_counts[graph.TOPIC_STATE] == len(ticks)


def test_unclosed_writer_leaves_readable_file(tmp_path):
    """What a killed writer leaves: the chunks it flushed, without summary or footer."""
    path = tmp_path / 'killed.mcap'
    writer = McapWriter(path, chunk_size=4096)
    n = 0
    while writer.chunks_written < 4:  # until a fourth chunk is flushed, then one more message:
        writer.write_message(graph.TOPIC_STATE, _state(n, n), log_time_ns=n)
        n += 1
    writer.write_message(graph.TOPIC_STATE, _state(n, n), log_time_ns=n)  # ... left open
    n += 1
    ticks = [m.message.tick for m in McapReader(path)]
    assert 0 < len(ticks) < n and ticks == list(range(len(ticks)))
    writer.close()
    assert [m.message.tick for m in McapReader(path, strict=True)] == list(range(n))


def test_damaged_chunk_is_reported():
    data, chunks = _chunked_file()
    bad = bytearray(data)
    bad[_inside_payload(chunks[4])] ^= 0xFF
    reader = McapReader(bytes(bad))
    assert len(list(reader)) == 4 * 50
    assert 'damaged chunk' in reader.problem
    with pytest.raises(CorruptError):
        scan(bytes(bad), strict=True)


def test_not_mcap_input_raises():
    for data in (b'', b'hello, not a recording\n' * 10, b'\x89PNG\r\n\x1a\n' + bytes(100)):
        with pytest.raises(NotMcapError):
            scan(data)


# --- lost message counting --------------------------------------------------------------------

@pytest.mark.parametrize('sequences, publishers, lost, missed', [
    ([1, 2, 3, 4], None, 0, 0),
    ([1, 2, 5, 6, 10], None, 2 + 3, 0),
    ([7, 8, 9], None, 0, 6),                            # joined late: not lost
    ([1, 1, 2, 3, 5], [b'a', b'b', b'a', b'a', b'a'], 1, 0),   # two publishers
    ([1, 2, 3, 1, 2, 4], None, 1, 0),                   # publisher restarted (same id)
    ([None, None], None, 0, 0),                         # no sequence numbers: nothing known
])
def test_sequence_gap_counter(sequences, publishers, lost, missed):
    counter = SequenceGapCounter()
    for seq, pub in zip(sequences, publishers or [None] * len(sequences)):
        counter.add(seq, pub)
    assert (counter.lost, counter.missed_at_start, counter.received) == (
        lost, missed, len(sequences))
    assert count_sequence_gaps(sequences, publishers) == lost


# --- CLI tools on bad input -------------------------------------------------------------------

@pytest.fixture
def bad_inputs(tmp_path):
    data, chunks = _chunked_file(n_messages=200)
    corrupt = bytearray(data)
    for i in range(_inside_payload(chunks[1]), _inside_payload(chunks[1]) + 8):
        corrupt[i] ^= 0xFF
    files = {
        'truncated': data[:_inside_payload(chunks[2])],
        'corrupt': bytes(corrupt),
        'not_mcap': b'time,position\n0,0\n' * 20,
        'empty': b'',
    }
    paths = {}
    for name, content in files.items():
        paths[name] = tmp_path / f'{name}.mcap'
        paths[name].write_bytes(content)
    paths['missing'] = tmp_path / 'missing.mcap'
    good = tmp_path / 'good.mcap'
    good.write_bytes(data)
    return paths, good


@pytest.mark.parametrize('case', ['corrupt', 'not_mcap', 'empty', 'missing'])
def test_replay_and_compare_reject_bad_input(case, bad_inputs, tmp_path, capsys):
    from eha_ros.recording import compare, replay

    paths, good = bad_inputs
    assert replay.main([str(paths[case])]) == 2
    _one_line_error(capsys.readouterr().err, 'eha-replay')
    assert compare.main([str(good), str(paths[case]), '--out', str(tmp_path / 'plots')]) == 2
    _one_line_error(capsys.readouterr().err, 'eha-compare')
    assert not (tmp_path / 'plots').exists()


def test_offline_tools_read_a_truncated_file_with_one_warning(bad_inputs, ros_env, tmp_path,
                                                              capsys):
    """A killed recorder's file (cut inside its third chunk): compare, diagnose and replay read
    the 100 messages of its two complete chunks, and say so in one line naming eha-recover."""
    from eha_ros.recording import compare
    from eha_ros.tools.diagnose import diagnose

    paths, good = bad_inputs
    cut = paths['truncated']
    assert compare.main([str(good), str(cut), '--out', str(tmp_path / 'plots')]) == 0
    warning = [line for line in capsys.readouterr().err.splitlines() if 'warning' in line]
    assert len(warning) == 1 and warning[0].startswith('eha-compare: warning:')
    assert 'using the 100 /eha/state messages' in warning[0]
    assert f'eha-recover {cut} -o' in warning[0]
    from eha_ros.physics import ParameterError
    try:
        diagnose(cut)
    except ParameterError:
        pass  # 100 synthetic states need not make an estimate; the warning is what counts
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith('eha-diagnose: warning:') and 'using the 100' in err[0]
    result = subprocess.run([str(BIN / 'eha-replay'), str(cut), '--rate', '10'], env=ros_env,
                            cwd=tmp_path, text=True, capture_output=True,
                            timeout=PROCESS_TIMEOUT_S)
    assert result.returncode == 0, result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines[0].startswith('eha-replay: warning:') and 'using the 100 messages' in lines[0]
    assert 'replayed 100 messages' in lines[-1]


def test_replay_rejects_missing_topics(bad_inputs, tmp_path, capsys):
    from eha_ros.recording import replay

    _, good = bad_inputs                      # holds /eha/state only
    other = tmp_path / 'other.mcap'
    with McapWriter(other) as writer:
        writer.write_message('/chatter', _clock(5), log_time_ns=5)
    for args in ([str(other)],                                   # none of the graph topics
                 [str(good), '--topics', '/eha/no_such_topic'],  # unknown topic
                 [str(good), '--topics', graph.TOPIC_COMMAND],  # graph topic not in file
                 [str(good), '--rate', '0']):
        assert replay.main(args) == 2, args
        _one_line_error(capsys.readouterr().err, 'eha-replay')


def test_console_scripts_reject_bad_input(bad_inputs, ros_env, tmp_path):
    paths, good = bad_inputs
    for command, prog in (([str(BIN / 'eha-replay'), str(paths['corrupt'])], 'eha-replay'),
                          ([str(BIN / 'eha-compare'), str(good), str(paths['not_mcap'])],
                           'eha-compare')):
        result = subprocess.run(command, env=ros_env, cwd=tmp_path, text=True,
                                capture_output=True, timeout=PROCESS_TIMEOUT_S)
        assert result.returncode == 2
        _one_line_error(result.stderr, prog)
    assert (BIN.parent / 'lib' / 'eha_ros' / 'recorder').is_file()


# --- recorder ---------------------------------------------------------------------------------

def test_recorder_records_every_graph_topic(ros_env, tmp_path):
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    n = 300
    output = tmp_path / 'run.mcap'
    recorder = _start_recorder(output, ros_env, tmp_path)
    sent = {t: [] for t in graph.TOPICS}
    try:
        with ros_node('recording_test_publisher') as (node, _):
            # Keep every sample until acknowledged: the test is about the recorder.
            qos = QoSProfile(depth=n, reliability=ReliabilityPolicy.RELIABLE)
            pubs = {t: node.create_publisher(graph.message_class(ty), t,
                                             graph.topic_qos(t, depth=n)
                                             if t in graph.LATCHED_TOPICS else qos)
                    for t, ty in graph.TOPICS.items()}
            _wait_matched(pubs.values())
            for i in range(n):
                for topic, pub in pubs.items():
                    msg = graph_sample(topic, seed=i)
                    pub.publish(msg)
                    sent[topic].append(msg)
                time.sleep(0.001)
            for pub in pubs.values():
                assert pub.wait_for_all_acked(Duration(seconds=DISCOVERY_TIMEOUT_S))
    finally:
        _, err = _stop(recorder)
    assert recorder.returncode == 0, err
    assert 'recorder' in err and '0 lost' in err

    info = scan(output, strict=True)
    assert info.message_counts == {t: n for t in graph.TOPICS}
    assert info.lost_messages() == {t: 0 for t in graph.TOPICS}
    run = info.run_info()
    assert run['missed_at_start'] == {t: 0 for t in graph.TOPICS}
    assert set(run['loss_detection'].values()) == {'publication_sequence_number'}
    assert info.rosbag2_metadata()['message_count'] == n * len(graph.TOPICS)
    for topic, channel in info.channels.items():
        profiles = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert profiles and all(p['reliability'] == 'reliable' for p in profiles)
        assert channel.metadata['topic_type_hash'] == type_hash(graph.TOPICS[topic])
    received = {t: [] for t in graph.TOPICS}
    for rec in McapReader(output, strict=True):
        received[rec.topic].append(_fields(rec.message))
        assert rec.sequence == len(received[rec.topic])
    for topic in graph.TOPICS:
        assert received[topic] == [_fields(m) for m in sent[topic]], topic


def test_recorder_refuses_existing_output_and_unknown_topic(ros_env, tmp_path):
    existing = tmp_path / 'exists.mcap'
    existing.write_bytes(b'precious')
    for extra, what in (([], 'exists'), (['--topics', '/eha/nope'], "unknown topic '/eha/nope'")):
        output = existing if not extra else tmp_path / 'new.mcap'
        result = subprocess.run([str(BIN / 'recorder'), '-o', str(output), *extra],
                                env=ros_env, cwd=tmp_path, text=True, capture_output=True,
                                timeout=PROCESS_TIMEOUT_S)
        assert result.returncode == 2
        _one_line_error(result.stderr, 'recorder')
        assert what in result.stderr
    assert existing.read_bytes() == b'precious'
    assert not (tmp_path / 'new.mcap').exists()


@pytest.mark.parametrize('name, value, words', [
    ('queue_depth', 0, 'queue_depth must be >= 1, got 0'),
    ('chunk_size', 0, 'chunk_size must be >= 1, got 0'),
    ('flush_interval_s', 0.0, 'flush_interval_s must be > 0, got 0.0'),
    ('compression', 'gzip', "compression must be one of auto, zstd, lz4, none, got 'gzip'"),
    ('max_bag_size_b', -1, 'max_bag_size_b must be >= 0, got -1'),
    ('snapshot_s', -1.0, 'snapshot_s must be >= 0, got -1.0'),
    ('batch_period_s', 0.5, 'Parameter batch_period_s out of range'),
    ('thread_priority', 100, 'Parameter thread_priority out of range'),
    ('queue_depth', 'ten', 'queue_depth'),
])
def test_recorder_refuses_a_bad_parameter_before_creating_its_file(ros_env, tmp_path, name,
                                                                   value, words):
    """Every bad value is refused at construction (as the other nodes refuse theirs), with the
    parameter named, and no file is created."""
    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.parameter import Parameter

    from eha_ros.nodes.recorder import Recorder

    output = tmp_path / 'run.mcap'
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        with pytest.raises((ValueError, ParameterException)) as err:
            Recorder(context=context, parameter_overrides=[
                Parameter('output', value=str(output)), Parameter(name, value=value)])
    finally:
        rclpy.try_shutdown(context=context)
    assert words in str(err.value)
    assert '\n' not in str(err.value)
    assert not output.exists()


def test_recorder_refuses_snapshot_with_split_and_changes_while_running(ros_env, tmp_path):
    """Snapshot mode with a split is refused; a recorder's parameters cannot change while it
    records (set_parameters is refused, the value kept); the command line says which."""
    import rclpy
    from rclpy.parameter import Parameter

    from eha_ros.nodes.recorder import Recorder

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        with pytest.raises(ValueError, match='no split with it'):
            Recorder(context=context, parameter_overrides=[
                Parameter('snapshot_s', value=1.0), Parameter('max_bag_size_b', value=100)])
        node = Recorder(context=context, parameter_overrides=[
            Parameter('snapshot_s', value=1.0), Parameter('output', value=str(tmp_path / 'a'))])
        try:
            result, = node.set_parameters([Parameter('queue_depth', value=5)])
            assert not result.successful
            assert result.reason == 'queue_depth cannot change while running'
            assert node.get_parameter('queue_depth').value == 1000
        finally:
            node.close()
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    bad = subprocess.run([str(BIN / 'recorder'), '-o', str(tmp_path / 'x.mcap'), '--ros-args',
                          '-p', 'compression:=gzip'], env=ros_env, cwd=tmp_path, text=True,
                         capture_output=True, timeout=PROCESS_TIMEOUT_S)
    assert bad.returncode == 2 and 'compression must be one of' in bad.stderr
    _one_line_error(bad.stderr, 'recorder')
    assert not list(tmp_path.iterdir())


def test_recorder_counts_messages_lost_while_stalled(ros_env, tmp_path):
    """A real gap: the recorder is frozen (SIGSTOP) while a publisher that keeps only its last
    sample (reliable, depth 1) sends a burst; the samples it overwrote never arrive."""
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from eha_ros.msg import ActuatorState

    output = tmp_path / 'stalled.mcap'
    recorder = _start_recorder(output, ros_env, tmp_path, '--topics', graph.TOPIC_STATE)
    published = 0
    try:
        with ros_node('recording_test_burst') as (node, _):
            pub = node.create_publisher(ActuatorState, graph.TOPIC_STATE,
                                        QoSProfile(depth=1,
                                                   reliability=ReliabilityPolicy.RELIABLE))
            _wait_matched([pub])

            def send(count, pause_s):
                nonlocal published
                for _ in range(count):
                    published += 1
                    pub.publish(ActuatorState(tick=published))
                    if pause_s:
                        time.sleep(pause_s)

            send(50, 0.002)
            assert pub.wait_for_all_acked(Duration(seconds=DISCOVERY_TIMEOUT_S))
            os.kill(recorder.pid, signal.SIGSTOP)
            try:
                send(3000, 0.0)
            finally:
                os.kill(recorder.pid, signal.SIGCONT)
            send(50, 0.002)
            assert pub.wait_for_all_acked(Duration(seconds=DISCOVERY_TIMEOUT_S))
    finally:
        _, err = _stop(recorder, signal.SIGTERM)    # SIGTERM closes the file as SIGINT does
    assert recorder.returncode == 0, err

    info = scan(output, strict=True)
    lost = info.lost_messages()[graph.TOPIC_STATE]
    recorded = info.message_counts[graph.TOPIC_STATE]
    missed = info.run_info()['missed_at_start'][graph.TOPIC_STATE]
    ticks = load_topic_arrays(output, graph.TOPIC_STATE)['tick']
    assert lost > 0
    assert recorded + lost + missed == published
    assert np.all(np.diff(ticks) >= 1)
    # The sequence-number count agrees with the gaps in the payload's own counter.
    assert lost == int(np.sum(np.diff(ticks) - 1))
    assert ticks[-1] == published


# --- eha-echo ---------------------------------------------------------------------------------

def test_echo_prints_live_messages(ros_env, tmp_path):
    from eha_ros.msg import ActuatorState

    expected = graph_sample(graph.TOPIC_STATE, seed=4)
    with ros_node('recording_test_echo_source') as (node, _):
        pub = node.create_publisher(ActuatorState, graph.TOPIC_STATE, graph.graph_qos())
        stop = threading.Event()

        def publish():
            while not stop.is_set():
                pub.publish(expected)
                stop.wait(0.02)

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        try:
            common = dict(env=ros_env, cwd=tmp_path, text=True, capture_output=True,
                          timeout=PROCESS_TIMEOUT_S)
            yaml_run = subprocess.run([str(BIN / 'eha-echo'), graph.TOPIC_STATE, '--count', '3',
                                       '--timeout', str(DISCOVERY_TIMEOUT_S)], **common)
            csv_run = subprocess.run([str(BIN / 'eha-echo'), 'eha/state', '--csv', '--count',
                                      '2', '--timeout', str(DISCOVERY_TIMEOUT_S)], **common)
            missing = subprocess.run([str(BIN / 'eha-echo'), '/eha/no_such_topic',
                                      '--timeout', '1'], **common)
        finally:
            stop.set()
            thread.join()

    assert yaml_run.returncode == 0, yaml_run.stderr
    docs = [d for d in yaml.safe_load_all(yaml_run.stdout) if d is not None]
    assert len(docs) == 3
    want = message_to_plain_data(expected)
    for doc in docs:
        assert doc == want

    assert csv_run.returncode == 0, csv_run.stderr
    rows = list(csv.DictReader(io.StringIO(csv_run.stdout)))
    assert len(rows) == 2
    assert list(rows[0])[:3] == ['header.stamp.sec', 'header.stamp.nanosec', 'header.frame_id']
    for row in rows:
        assert float(row['jack_position_m']) == expected.jack_position_m
        assert int(row['tick']) == expected.tick
        assert row['model'] == expected.model

    assert missing.returncode == 2
    _one_line_error(missing.stderr, 'eha-echo')


# --- eha-replay -------------------------------------------------------------------------------

def test_replay_republishes_in_order_with_clock(ros_env, tmp_path):
    from rclpy.qos import QoSProfile
    from rosgraph_msgs.msg import Clock

    from eha_ros.msg import ActuatorCommand, ActuatorState

    n, spacing_ns, t0 = 40, 10_000_000, 1_800_000_000_000_000_000
    path = tmp_path / 'recorded.mcap'
    with McapWriter(path) as writer:
        for i in range(n):
            t = t0 + i * spacing_ns
            writer.write_message(graph.TOPIC_STATE, _state(t, i, jack=i * 1e-3),
                                 log_time_ns=t)
            cmd = ActuatorCommand(position_setpoint_m=i * 1e-3)
            writer.write_message(graph.TOPIC_COMMAND, cmd, log_time_ns=t + 1000)

    got = {'state': [], 'command': [], 'clock': []}
    with ros_node('recording_test_replay_sink') as (node, executor):
        qos = QoSProfile(depth=1000)
        node.create_subscription(ActuatorState, graph.TOPIC_STATE,
                                 lambda m: got['state'].append(m.tick), qos)
        node.create_subscription(ActuatorCommand, graph.TOPIC_COMMAND,
                                 lambda m: got['command'].append(m.position_setpoint_m), qos)
        node.create_subscription(
            Clock, graph.TOPIC_CLOCK,
            lambda m: got['clock'].append(m.clock.sec * 1_000_000_000 + m.clock.nanosec), qos)
        replay = subprocess.Popen(
            [str(BIN / 'eha-replay'), str(path), '--wait-for-subscribers',
             str(DISCOVERY_TIMEOUT_S)], env=ros_env, cwd=tmp_path, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + PROCESS_TIMEOUT_S
            while time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
                if replay.poll() is not None:
                    if len(got['state']) >= n and len(got['command']) >= n:
                        break
                    deadline = min(deadline, time.monotonic() + 5.0)  # what is in flight
        finally:
            _, err = _stop(replay)

    assert replay.returncode == 0, err
    assert got['state'] == list(range(n))
    assert got['command'] == [i * 1e-3 for i in range(n)]
    assert got['clock'], '/clock not published'
    assert got['clock'] == sorted(got['clock'])
    assert t0 <= got['clock'][0] and got['clock'][-1] <= t0 + n * spacing_ns
    # The replay paces itself by the recorded log times (sleeps never end early).
    summary = [line for line in err.splitlines() if line.startswith('eha-replay: replayed')]
    elapsed = float(summary[-1].rsplit(' in ', 1)[1].split()[0])
    assert elapsed >= (n - 1) * spacing_ns / 1e9


# --- eha-compare ------------------------------------------------------------------------------

def test_compare_reports_closed_form_errors_and_plots(tmp_path, capsys):
    from eha_ros.recording import compare

    eps, offset_pa = 0.02, 3e4
    t = 2_000_000_000 + np.arange(1000) * 1_000_000          # 1 s at 1 kHz
    w = 2 * np.pi * 2.0 * (t - t[0]) * 1e-9
    jack, p12, spool = 0.05 * np.sin(w), 8e6 * np.sin(w + 0.3), 2e-4 * np.cos(w)
    a, b, c = tmp_path / 'a.mcap', tmp_path / 'b.mcap', tmp_path / 'c.mcap'
    _write_states(a, t, jack, p12, spool, 'hf')
    _write_states(b, t, (1 + eps) * jack, p12 + offset_pa, (1 + eps) * spool, 'lut')
    # Run c at twice the rate: its samples at a's stamps are a's, shifted by eps as b.
    t2 = 2_000_000_000 + np.arange(2000) * 500_000
    w2 = 2 * np.pi * 2.0 * (t2 - t2[0]) * 1e-9
    _write_states(c, t2, (1 - eps) * 0.05 * np.sin(w2), 8e6 * np.sin(w2 + 0.3),
                  2e-4 * np.cos(w2), 'nn')

    out = tmp_path / 'plots'
    args = [str(a), str(b), str(c), '--out', str(out)]
    assert compare.main(args + ['--json']) == 0
    result = json.loads(capsys.readouterr().out)
    assert result['reference']['label'] == 'hf'
    runs = {r['label']: r for r in result['runs']}
    assert set(runs) == {'lut', 'nn'}
    p12_expected = offset_pa * math.sqrt(t.size) / np.linalg.norm(p12)
    assert_allclose(runs['lut']['relative_error']['jack_position_m'], eps, rtol=1e-9)
    assert_allclose(runs['lut']['relative_error']['spool_position_m'], eps, rtol=1e-9)
    assert_allclose(runs['lut']['relative_error']['p12_pa'], p12_expected, rtol=1e-9)
    # c's last stamp is half a sample past a's: every reference sample is inside its span.
    assert runs['nn']['samples'] == t.size
    assert_allclose(runs['nn']['relative_error']['jack_position_m'], eps, rtol=1e-6)
    assert_allclose(runs['nn']['relative_error']['p12_pa'], 0.0, atol=1e-12)

    pngs = sorted(p.name for p in out.iterdir())
    assert pngs == ['jack_position.png', 'p12.png', 'spool_position.png']
    for name in pngs:
        assert (out / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    before = {name: (out / name).read_bytes() for name in pngs}

    # Existing plots are kept unless --force; the table names the runs.
    assert compare.main(args) == 2
    _one_line_error(capsys.readouterr().err, 'eha-compare')
    assert {name: (out / name).read_bytes() for name in pngs} == before
    assert compare.main(args + ['--force', '--reference', 'lut']) == 0
    table = capsys.readouterr().out
    assert table.startswith('reference: lut') and 'hf' in table and 'nn' in table


# --- eha-recover ------------------------------------------------------------------------------

def _rosbags_messages(path):
    """Every message of a file through rosbags (an independent reader), decoded."""
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(path)]) as reader:
        return [(conn.topic, reader.deserialize(raw, conn.msgtype))
                for conn, _, raw in reader.messages()]


def test_recover_rewrites_a_truncated_file_complete(bad_inputs, tmp_path):
    from mcap.reader import make_reader

    from eha_ros.recording.recover import recover

    paths, _ = bad_inputs
    with pytest.raises(Exception, match='File end magic'):  # what rosbags says of a cut file
        _rosbags_messages(paths['truncated'])
    out = tmp_path / 'fixed.mcap'
    result = recover(paths['truncated'], out)
    assert result['messages'] == {graph.TOPIC_STATE: 100} and not result['source_complete']
    summary = make_reader(open(out, 'rb')).get_summary()
    assert summary.statistics.message_count == 100 and summary.chunk_indexes
    decoded = _rosbags_messages(out)
    assert [m.tick for _, m in decoded] == list(range(100))
    info = scan(out, strict=True)
    assert info.complete and info.lost_messages() == {graph.TOPIC_STATE: 0}
    assert info.rosbag2_metadata()['message_count'] == 100
    assert info.run_info()['recovered']['source'] == str(paths['truncated'])
    assert 'truncated' in info.run_info()['recovered']['problem']


def test_recover_cli_bad_input(bad_inputs, tmp_path, capsys):
    from eha_ros.recording import recover

    paths, good = bad_inputs
    out = tmp_path / 'out.mcap'
    for source in ('not_mcap', 'empty', 'missing', 'corrupt'):
        code = recover.main([str(paths[source]), '-o', str(out)])
        err = capsys.readouterr().err
        if source == 'corrupt':  # damaged inside: the messages before the damage are kept
            assert code == 0 and out.is_file(), err
            assert 0 < scan(out, strict=True).message_counts[graph.TOPIC_STATE] < 200
            out.unlink()
            continue
        assert code == 2 and not out.exists(), source
        _one_line_error(err, 'eha-recover')
    out.write_bytes(b'keep')
    assert recover.main([str(good), '-o', str(out)]) == 2 and out.read_bytes() == b'keep'
    _one_line_error(capsys.readouterr().err, 'eha-recover')
    assert recover.main([str(good), '-o', str(good)]) == 2
    _one_line_error(capsys.readouterr().err, 'eha-recover')


def test_sigkilled_recorder_is_recovered_with_its_losses(ros_env, tmp_path):
    """SIGKILL a recorder that has lost messages (frozen during a burst to a depth-1 reader):
    after eha-recover, rosbags decodes every message the killed file held, the ticks before
    its last flushed chunk are all there but the lost ones, and the loss count is stored."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from eha_ros.msg import ActuatorState

    output = tmp_path / 'killed.mcap'
    recorder = _start_recorder(output, ros_env, tmp_path, '--topics', graph.TOPIC_STATE,
                               '--ros-args', '-p', 'flush_interval_s:=0.02')
    published = 0

    def recorded():
        try:
            return scan(output).message_counts.get(graph.TOPIC_STATE, 0)
        except (OSError, RecordingError):  # not created, or not even its header yet
            return 0

    try:
        with ros_node('recording_test_kill') as (node, _):
            pub = node.create_publisher(ActuatorState, graph.TOPIC_STATE,
                                        QoSProfile(depth=1,
                                                   reliability=ReliabilityPolicy.RELIABLE))
            _wait_matched([pub])

            def send_until(condition, pause_s=0.002):
                nonlocal published
                deadline = time.monotonic() + PROCESS_TIMEOUT_S
                while not condition():
                    assert time.monotonic() < deadline, 'the recorder wrote no chunk'
                    published += 1
                    pub.publish(ActuatorState(tick=published))
                    time.sleep(pause_s)

            send_until(lambda: recorded() > 0)
            os.kill(recorder.pid, signal.SIGSTOP)
            try:
                for _ in range(3000):
                    published += 1
                    pub.publish(ActuatorState(tick=published))
            finally:
                os.kill(recorder.pid, signal.SIGCONT)
            burst_end = published
            send_until(lambda: load_topic_arrays(
                output, graph.TOPIC_STATE)['tick'][-1] > burst_end)
            os.kill(recorder.pid, signal.SIGKILL)
    finally:
        _stop(recorder, signal.SIGKILL)
    assert recorder.returncode == -signal.SIGKILL
    killed = scan(output)
    assert not killed.complete
    fixed = tmp_path / 'fixed.mcap'
    result = subprocess.run([str(BIN / 'eha-recover'), str(output), '-o', str(fixed)],
                            env=ros_env, cwd=tmp_path, text=True, capture_output=True,
                            timeout=PROCESS_TIMEOUT_S)
    assert result.returncode == 0, result.stderr
    decoded = _rosbags_messages(fixed)
    ticks = np.array([m.tick for _, m in decoded])
    assert ticks.size == killed.message_counts[graph.TOPIC_STATE]
    assert np.all(np.diff(ticks) >= 1) and ticks[-1] > burst_end
    info = scan(fixed, strict=True)
    lost = info.lost_messages()[graph.TOPIC_STATE]
    assert lost > 0 and lost == int(np.sum(np.diff(ticks) - 1))
    assert info.run_info()['recovered']['loss_counted_from'][graph.TOPIC_STATE].startswith(
        'sequence numbers')


# --- recorder controls: topic patterns, split, snapshot -----------------------------------------

def _wait_for_line(process, words, timeout=PROCESS_TIMEOUT_S):
    """Read the process's stderr until a line holds ``words``; returns that line."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stderr.readline()
        if not line and process.poll() is not None:
            break
        if words in line:
            return line
    raise AssertionError(f'no line with {words!r}: ' + process.stderr.read())


def test_recorder_topic_patterns(ros_env, tmp_path):
    output = tmp_path / 'some.mcap'
    recorder = _start_recorder(output, ros_env, tmp_path, '--regex', '^/eha/',
                               '--exclude-regex', 'command')
    _wait_for_line(recorder, 'topics to')
    _, err = _stop(recorder)
    assert recorder.returncode == 0, err
    assert set(scan(output, strict=True).channels) == {graph.TOPIC_STATE, graph.TOPIC_HEALTH,
                                                       graph.TOPIC_EVENTS}
    bad = subprocess.run([str(BIN / 'recorder'), '-o', str(tmp_path / 'x.mcap'),
                          '--regex', '^/nothing'], env=ros_env, cwd=tmp_path, text=True,
                         capture_output=True, timeout=PROCESS_TIMEOUT_S)
    assert bad.returncode == 2 and 'no topic left' in bad.stderr
    _one_line_error(bad.stderr, 'recorder')


@pytest.mark.parametrize('split', [('--max-bag-size', '6000'), ('--max-bag-duration', '0.25')])
def test_recorder_splits_into_numbered_complete_files(ros_env, tmp_path, split):
    """Split by size or duration: files run_0.mcap, run_1.mcap, ... each complete, together
    every published message once, in order."""
    from rclpy.duration import Duration

    from eha_ros.msg import ActuatorState

    output = tmp_path / 'run.mcap'
    recorder = _start_recorder(output, ros_env, tmp_path, '--topics', graph.TOPIC_STATE,
                               *split, '--ros-args', '-p', 'chunk_size:=2000')
    n = 1200
    try:
        with ros_node('recording_test_split') as (node, _):
            pub = node.create_publisher(ActuatorState, graph.TOPIC_STATE, graph.graph_qos())
            _wait_matched([pub])
            for k in range(n):  # at least 1.2 s: the duration split makes >= 4 files
                pub.publish(ActuatorState(tick=k))
                time.sleep(0.001)
            assert pub.wait_for_all_acked(Duration(seconds=DISCOVERY_TIMEOUT_S))
    finally:
        _, err = _stop(recorder)
    assert recorder.returncode == 0, err
    assert not output.exists()
    files = sorted(tmp_path.glob('run_*.mcap'), key=lambda p: int(p.stem.split('_')[1]))
    assert [p.name for p in files] == [f'run_{i}.mcap' for i in range(len(files))]
    assert len(files) >= 3
    ticks = []
    for path in files:
        info = scan(path, strict=True)
        assert info.complete and info.lost_messages() == {graph.TOPIC_STATE: 0}
        ticks += list(load_topic_arrays(path, graph.TOPIC_STATE)['tick'])
    assert ticks == list(range(n))


def test_snapshot_mode_writes_the_last_seconds_on_request_and_on_health_error(ros_env,
                                                                              tmp_path):
    """Snapshot mode, states flowing at 1 kHz: the ~/snapshot service and then a health ERROR
    each write the last 0.5 s (contiguous ticks, no more than 0.5 s) to box_0 and box_1."""
    from rclpy.duration import Duration
    from std_srvs.srv import Trigger

    from eha_ros.msg import ActuatorState, HealthStatus

    output = tmp_path / 'box.mcap'
    recorder = _start_recorder(output, ros_env, tmp_path, '--snapshot', '0.5')
    stop = threading.Event()
    try:
        with ros_node('recording_test_snapshot') as (node, executor):
            pub = node.create_publisher(ActuatorState, graph.TOPIC_STATE, graph.graph_qos())
            health = node.create_publisher(HealthStatus, graph.TOPIC_HEALTH, graph.graph_qos())
            client = node.create_client(Trigger, '/recorder/snapshot')
            _wait_matched([pub, health])
            assert client.wait_for_service(timeout_sec=DISCOVERY_TIMEOUT_S)

            def stream():
                tick = 0
                while not stop.is_set():
                    tick += 1
                    pub.publish(ActuatorState(tick=tick))
                    time.sleep(0.001)
            thread = threading.Thread(target=stream)
            thread.start()
            time.sleep(1.0)  # more than the 0.5 s kept (what is kept is checked below)
            future = client.call_async(Trigger.Request())
            executor.spin_until_future_complete(future, timeout_sec=PROCESS_TIMEOUT_S)
            answer = future.result()
            assert answer.success and answer.message.endswith('box_0.mcap')
            time.sleep(0.2)
            health.publish(HealthStatus(level=HealthStatus.LEVEL_WARN))
            health.publish(HealthStatus(level=HealthStatus.LEVEL_ERROR, message='worn'))
            assert health.wait_for_all_acked(Duration(seconds=DISCOVERY_TIMEOUT_S))
            deadline = time.monotonic() + PROCESS_TIMEOUT_S
            while not (tmp_path / 'box_1.mcap').exists():
                assert time.monotonic() < deadline
                time.sleep(0.05)
            stop.set()
            thread.join()
    finally:
        stop.set()
        _, err = _stop(recorder)
    assert recorder.returncode == 0, err
    assert sorted(p.name for p in tmp_path.glob('box*.mcap')) == ['box_0.mcap', 'box_1.mcap']
    last = []
    for path in (tmp_path / 'box_0.mcap', tmp_path / 'box_1.mcap'):
        info = scan(path, strict=True)
        assert info.complete and set(info.channels) == set(graph.TOPICS)
        state = load_topic_arrays(path, graph.TOPIC_STATE)
        assert state['tick'].size > 0
        span_ns = int(state['log_time_ns'][-1] - state['log_time_ns'][0])
        assert span_ns <= 0.5e9                               # only the last 0.5 s
        assert np.all(np.diff(state['tick']) == 1)
        assert info.lost_messages()[graph.TOPIC_STATE] == 0
        last.append(int(state['tick'][-1]))
    assert last[0] < last[1]
    assert scan(tmp_path / 'box_0.mcap').run_info()['snapshot_reason'] == \
        'requested on ~/snapshot'
    assert scan(tmp_path / 'box_1.mcap').run_info()['snapshot_reason'] == 'health ERROR: worn'
