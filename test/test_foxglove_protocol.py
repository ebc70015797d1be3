"""The live view's ROS-free core (``eha_ros.foxglove.core``) without Node and without nodes:
the channel table against the MCAP writer's schemas, and property tests (hypothesis, draws no
other test uses) of what a client can send, the endpoint and parameter-name parsers, the
decimation, the per-client queue's accounting (every data message sent, dropped and counted,
or still queued; control never dropped), the CDR stamp reader on real serialized messages;
then the server end to end over a real socket with a ``websockets`` client.
"""

import asyncio
import json
import struct
import threading
import time

from hypothesis import given, settings, strategies as st
import pytest

from eha_ros import graph
from eha_ros.foxglove.core import (ChannelTable, ClientQueue, Decimator, decimated_topic,
                                   header_stamp_ns, LiveServer, parse_client_message,
                                   parse_endpoint, ProtocolError, resolve_parameter)
from eha_ros.recording.definitions import message_definition

SUBPROTOCOL = 'foxglove.websocket.v1'
FAST = [t for t, hz in graph.RATES_HZ.items() if hz >= 500.0]


def table():
    topics = dict(graph.TOPICS)
    topics[graph.TOPIC_HANDSHAKE] = 'diagnostic_msgs/msg/DiagnosticStatus'
    return ChannelTable(topics, message_definition, latched=graph.LATCHED_TOPICS,
                        decimate={t: [50.0] for t in FAST})


def test_one_channel_per_topic_with_the_mcap_writers_schema_and_decimated_ones():
    t = table()
    full = [c for c in t.channels if c.rate_hz is None]
    assert [c.topic for c in full] == list(graph.TOPICS) + [graph.TOPIC_HANDSHAKE]
    assert len({c.id for c in t.channels}) == len(t.channels)
    for c in t.channels:
        ad = c.advertisement()
        assert ad['encoding'] == 'cdr' and ad['schemaEncoding'] == 'ros2msg'
        assert ad['schema'] == message_definition(c.type_name)
        assert ad['metadata']['latched'] == str(c.source in graph.LATCHED_TOPICS).lower()
    dec = {c.topic: c for c in t.channels if c.rate_hz is not None}
    assert set(dec) == {decimated_topic(s, 50.0) for s in FAST}
    assert dec['/eha/state/decimated_50hz'].advertisement()['metadata']['decimated_to_hz'] == '50'
    with pytest.raises(ValueError, match='not a bridged topic'):
        ChannelTable({'/a': 'std_msgs/msg/Empty'}, lambda n: '', decimate={'/b': [1.0]})
    with pytest.raises(ValueError, match='positive'):
        ChannelTable({'/a': 'std_msgs/msg/Empty'}, lambda n: '', decimate={'/a': [0.0]})


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
    max_leaves=12)
ops = st.sampled_from(['subscribe', 'unsubscribe', 'getParameters', 'setParameters',
                       'subscribeParameterUpdates', 'unsubscribeParameterUpdates', 'advertise',
                       'subscribe ', 'Subscribe', ''])


@settings(max_examples=400, deadline=None)
@given(st.one_of(st.text(), st.builds(lambda op, body: json.dumps(dict(body, op=op)), ops,
                                      st.dictionaries(st.sampled_from(
                                          ['subscriptions', 'subscriptionIds', 'parameterNames',
                                           'parameters', 'id']), json_values, max_size=3))))
def test_any_client_text_parses_or_is_refused_in_one_line(text):
    try:
        msg = parse_client_message(text)
    except ProtocolError as exc:
        assert str(exc) and '\n' not in str(exc)
        return
    assert msg['op'] in ('subscribe', 'unsubscribe', 'getParameters', 'setParameters',
                         'subscribeParameterUpdates', 'unsubscribeParameterUpdates')


@given(st.lists(st.tuples(st.integers(0, 2 ** 32 - 1), st.integers(0, 2 ** 32 - 1)),
                max_size=5))
def test_a_valid_subscribe_parses(pairs):
    text = json.dumps({'op': 'subscribe', 'subscriptions': [{'id': i, 'channelId': c}
                                                            for i, c in pairs]})
    assert len(parse_client_message(text)['subscriptions']) == len(pairs)


@pytest.mark.parametrize('text, words', [
    (b'\x01', 'binary'), ('{', 'not JSON'), ('[]', 'no "op"'),
    ('{"op": "subscrbe", "subscriptions": []}', 'did you mean subscribe'),
    ('{"op": "subscribe", "subscriptions": [{"id": -1, "channelId": 1}]}', 'integer'),
    ('{"op": "subscribe", "subscriptions": [{"id": true, "channelId": 1}]}', 'integer'),
    ('{"op": "setParameters", "parameters": [{"value": 1}]}', '"name"'),
    ('{"op": "getParameters", "parameterNames": "a"}', 'must be a list')])
def test_bad_client_messages_are_named(text, words):
    with pytest.raises(ProtocolError, match=words):
        parse_client_message(text)


@given(st.from_regex(r'[a-z][a-z0-9.\-]{0,20}', fullmatch=True), st.integers(0, 65535))
def test_endpoints_round_trip(host, port):
    assert parse_endpoint(f'{host}:{port}') == (host, port)
    assert parse_endpoint(str(port)) == ('127.0.0.1', port)


@given(st.one_of(st.integers(65536, 10 ** 9).map(str), st.integers(-10 ** 9, -1).map(str),
                 st.text().filter(lambda s: not s.strip().lstrip('+-').isdigit())))
def test_bad_endpoints_are_refused_naming_the_input(text):
    try:
        host, port = parse_endpoint(text)
    except ValueError as exc:
        assert repr(text) in str(exc)
    else:  # only HOST:PORT forms with a valid port may pass
        assert 0 <= port <= 65535 and host


DECLARED = {'servovalve_plant': ['radial_clearance_m', 'overlap_supply_m', 'dt_s'],
            'controller': ['kp', 'current_limit_a']}


@given(st.sampled_from(sorted(DECLARED)), st.data())
def test_declared_parameters_resolve_and_misspellings_name_the_nearest(node, data):
    name = data.draw(st.sampled_from(DECLARED[node]))
    assert resolve_parameter(f'{node}.{name}', DECLARED) == (node, name)
    assert resolve_parameter(f'/{node}.{name}', DECLARED) == (node, name)
    k = data.draw(st.integers(0, len(name) - 1))
    wrong = name[:k] + name[k + 1:]       # one letter dropped
    if wrong not in DECLARED[node]:
        with pytest.raises(ValueError, match=f'has no parameter {wrong!r}') as info:
            resolve_parameter(f'{node}.{wrong}', DECLARED)
        assert '\n' not in str(info.value)
    with pytest.raises(ValueError, match='unknown node'):
        resolve_parameter(f'{node}x.{name}', DECLARED)
    with pytest.raises(ValueError, match='expected node.parameter'):
        resolve_parameter(name.replace('.', ''), DECLARED)


@given(st.floats(1.0, 2000.0), st.lists(st.integers(0, 10 ** 7), min_size=1, max_size=300))
def test_decimation_keeps_exactly_the_first_message_of_each_period(rate_hz, steps):
    stamps, t = [], 0
    for s in steps:
        t += s
        stamps.append(t)
    d = Decimator(rate_hz)
    kept = [s for s in stamps if d.keep(s)]
    period = d.period_ns
    first_of_bin = {}
    for s in stamps:
        first_of_bin.setdefault(s // period, s)
    assert kept == sorted(first_of_bin.values())


queue_ops = st.lists(st.one_of(
    st.tuples(st.just('data'), st.sampled_from(['/a', '/b', '/c'])),
    st.tuples(st.just('control'), st.none()),
    st.tuples(st.just('take'), st.integers(1, 20))), max_size=200)


@settings(max_examples=300, deadline=None)
@given(st.integers(1, 12), queue_ops)
def test_the_client_queue_accounts_for_every_message(depth, program):
    q = ClientQueue(depth)
    put, got, controls_put, controls_got = {}, {}, 0, 0
    seq = 0
    for op, arg in program:
        if op == 'data':
            seq += 1
            put.setdefault(arg, []).append(seq)
            q.put_data(arg, struct.pack('<I', seq))
        elif op == 'control':
            controls_put += 1
            q.put_control(f'c{controls_put}')
        else:
            for topic, item in q.take(arg):
                if topic is None:
                    controls_got += 1
                    assert item == f'c{controls_got}'     # control in order, none lost
                else:
                    got.setdefault(topic, []).append(struct.unpack('<I', item)[0])
        assert len(q._data) <= depth
    remaining = {}
    for topic, frame in list(q._data):
        remaining.setdefault(topic, []).append(struct.unpack('<I', frame)[0])
    assert controls_put == controls_got + len(q._control)
    for topic, seqs in put.items():
        sent = got.get(topic, [])
        assert sent == sorted(sent)                        # order kept per topic
        assert q.sent.get(topic, 0) == len(sent)
        # sent + dropped + still queued = put: nothing vanishes uncounted
        assert len(sent) + q.dropped.get(topic, 0) + len(remaining.get(topic, [])) == len(seqs)
        assert set(sent) | set(remaining.get(topic, [])) <= set(seqs)


@given(st.integers(-2 ** 31, 2 ** 31 - 1), st.integers(0, 999_999_999), st.floats(-1e3, 1e3))
def test_the_stamp_is_read_from_real_cdr_bytes(sec, nanosec, value):
    from rclpy.serialization import serialize_message
    from rosgraph_msgs.msg import Clock
    from eha_ros.msg import ActuatorState
    msg = ActuatorState(p12_pa=value)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    assert header_stamp_ns(serialize_message(msg)) == sec * 10 ** 9 + nanosec
    clock = Clock()
    clock.clock.sec, clock.clock.nanosec = sec, nanosec
    assert header_stamp_ns(serialize_message(clock)) == sec * 10 ** 9 + nanosec
    assert header_stamp_ns(b'\x00\x01\x00') is None
    assert header_stamp_ns(b'\x07' * 16) is None


# the server over a real socket -------------------------------------------------------------

class Params:
    """A parameters provider: one node, one parameter, sets above 1.0 refused."""

    def __init__(self):
        self.value = 0.5

    def get(self, names):
        return [{'name': 'plant.x', 'value': self.value}]

    def set(self, params, done):
        ok, bad = [], []
        for p in params:
            if p['value'] > 1.0:
                bad.append(f'{p["name"]} = {p["value"]} refused: above 1.0')
            else:
                self.value = p['value']
                ok.append({'name': p['name'], 'value': p['value']})
        threading.Thread(target=done, args=(ok, bad)).start()


def run_client(port, script):
    """``script(ws)`` (async) against the server; returns its result."""
    from websockets.asyncio.client import connect

    async def main():
        async with connect(f'ws://127.0.0.1:{port}', subprotocols=[SUBPROTOCOL]) as ws:
            return await script(ws)
    return asyncio.run(main())


async def until(ws, pred, timeout_s=10.0):
    """Frames until ``pred(frame)``: returns them all (text decoded as JSON)."""
    out = []
    while True:
        raw = await asyncio.wait_for(ws.recv(), timeout_s)
        frame = json.loads(raw) if isinstance(raw, str) else raw
        out.append(frame)
        if pred(frame):
            return out


def test_the_server_end_to_end():
    t = ChannelTable({'/eha/state': 'eha_ros/msg/ActuatorState',
                      '/eha/events': 'eha_ros/msg/GraphEvent'}, message_definition,
                     latched=['/eha/events'])
    server = LiveServer(t, port=0, queue_depth=8, parameters=Params(), time=True).start()
    try:
        stamp = struct.pack('<BBHiI', 0, 1, 0, 3, 7)   # CDR LE header, sec 3, nanosec 7
        server.publish('/eha/events', stamp + b'event')  # before any client: latched

        async def script(ws):
            first = await until(ws, lambda f: isinstance(f, dict) and f['op'] == 'advertise')
            info = first[0]
            channels = {c['topic']: c['id'] for c in first[-1]['channels']}
            await ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
                {'id': 10, 'channelId': channels['/eha/state']},
                {'id': 11, 'channelId': channels['/eha/events']}]}))
            latched = await until(ws, lambda f: isinstance(f, bytes))
            end = time.monotonic() + 10
            while server.subscribed_clients([channels['/eha/state']]) < 1:
                assert time.monotonic() < end
                await asyncio.sleep(0.01)
            server.publish('/eha/state', stamp + b'state')
            live = await until(ws, lambda f: isinstance(f, bytes))
            server.broadcast_time(42)
            tick = await until(ws, lambda f: isinstance(f, bytes) and f[0] == 2)
            await ws.send(json.dumps({'op': 'setParameters', 'id': 's',
                                      'parameters': [{'name': 'plant.x', 'value': 2.0},
                                                     {'name': 'plant.x', 'value': 0.7}]}))
            replies = await until(ws, lambda f: isinstance(f, dict)
                                  and f['op'] == 'parameterValues')

            # a burst beyond the queue: the data frames are dropped, counted and told
            async def burst():   # on the server's loop: its sender cannot run meanwhile
                for k in range(200):
                    server.publish('/eha/state', stamp + b'%d' % k)
            asyncio.run_coroutine_threadsafe(burst(), server._loop).result(10)
            dropped = server.client_stats()[0]['dropped']['/eha/state']   # final: publish
            seen = {'data': 0, 'told': None}                               # is synchronous

            def done(f):
                if isinstance(f, bytes) and f[0] == 1:
                    seen['data'] += 1
                elif isinstance(f, dict) and f.get('id') == 'dropped':
                    seen['told'] = f['message']
                return seen['told'] is not None and seen['data'] + dropped == 200
            await until(ws, done)
            return info, latched[-1], live[-1], tick[-1], replies, (dropped, seen['told'])
        info, latched, live, tick, replies, frames = run_client(server.port, script)
        assert info['op'] == 'serverInfo'
        assert {'parameters', 'time'} <= set(info['capabilities'])
        assert latched[0] == 1 and struct.unpack('<IQ', latched[1:13]) == (11, 3 * 10 ** 9 + 7)
        assert latched[13:] == stamp + b'event'
        assert struct.unpack('<IQ', live[1:13]) == (10, 3 * 10 ** 9 + 7)
        assert live[13:] == stamp + b'state'            # the bytes forwarded unchanged
        assert struct.unpack('<Q', tick[1:9]) == (42,)
        errors = [f['message'] for f in replies if isinstance(f, dict) and f['op'] == 'status']
        assert errors == ['plant.x = 2.0 refused: above 1.0']
        assert replies[-1]['parameters'] == [{'name': 'plant.x', 'value': 0.7}]
        # every one of the burst was delivered or dropped (the until above), the drops
        # counted per topic, and the client told with that count
        dropped, told = frames
        assert dropped == 200 - 8             # a queue of 8 kept the last 8
        assert f'/eha/state: {dropped}' in told
    finally:
        assert server.stop() == {}
