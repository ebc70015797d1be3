"""The live view's ROS-free core: the Foxglove WebSocket protocol (``foxglove.websocket.v1``)
as far as the bridge speaks it, the channel table, a bounded queue per client that counts
every message it drops, channel decimation, and the parameter names' refusals.

The bridge node (:mod:`eha_ros.nodes.foxglove_bridge`) feeds :class:`LiveServer` the serialized
bytes of every graph topic; the server sends each client what it subscribed to, from that
client's own queue, on an asyncio loop in a thread of its own.  A client that reads slowly
fills its queue; the oldest data message is then dropped *there* - never in the graph, whose
callbacks only append - counted per channel, reported on the bridge's ``/diagnostics`` and
told to the client as a warning status (control messages are never dropped, so the client
sees it once it reads again).

Why not foxglove-sdk's server: its per-client outbox (``message_backlog_size``, 1024 messages)
drops the oldest message with a log line throttled to one per 30 s and exposes no count
(``send_lossy`` in foxglove-sdk 0.30.3), so a drop could not be counted or reported per
channel.  The wire format is the same protocol, checked against Foxglove's own client
library (``test/foxglove_client``).
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import difflib
import itertools
import json
import math
import struct
import threading
import time
from typing import Callable, Dict, Iterable, List, Mapping, Optional, Sequence

__all__ = ['SUBPROTOCOL', 'ChannelSpec', 'ChannelTable', 'ClientQueue', 'LiveServer',
           'ProtocolError', 'message_data', 'parse_client_message',
           'resolve_parameter', 'parse_endpoint', 'header_stamp_ns', 'decimated_topic']

SUBPROTOCOL = 'foxglove.websocket.v1'
#: Server binary opcodes.
OP_MESSAGE_DATA = 1
OP_TIME = 2
#: Status levels.
INFO, WARNING, ERROR = 0, 1, 2
#: Default data messages a client's queue holds before the oldest is dropped: 1 s of the
#: graph's 1 kHz topics (states, commands, current commands) with room for the rest.
QUEUE_DEPTH = 4096
#: At most one drop status per client this often (s): a slow client is told, not flooded.
DROP_STATUS_PERIOD_S = 1.0

_CLIENT_OPS = {
    'subscribe': ('subscriptions',), 'unsubscribe': ('subscriptionIds',),
    'getParameters': ('parameterNames',), 'setParameters': ('parameters',),
    'subscribeParameterUpdates': ('parameterNames',),
    'unsubscribeParameterUpdates': ('parameterNames',),
    'subscribeConnectionGraph': (), 'unsubscribeConnectionGraph': (),
}


#: How long a parameter request waits for the nodes' parameter lists (s): a client that
#: connects as the graph starts asks before every node's services are up.
PARAMETER_WAIT_S = 5.0


class ProtocolError(ValueError):
    """A client message the protocol does not allow (one line, sent back as an error
    status)."""


def message_data(subscription_id: int, log_time_ns: int, payload: bytes) -> bytes:
    """A ``MESSAGE_DATA`` frame: opcode, subscription id (u32), log time (u64, ns), payload."""
    return struct.pack('<BIQ', OP_MESSAGE_DATA, subscription_id, log_time_ns) + payload


def header_stamp_ns(cdr: bytes) -> Optional[int]:
    """The stamp of a CDR message whose first field is a ``builtin_interfaces/Time`` (a
    ``std_msgs/Header`` or ``rosgraph_msgs/Clock``), read from its first 12 bytes (the
    encapsulation header, then ``int32 sec``, ``uint32 nanosec`` in the message's byte order);
    None when the bytes are too short or the encapsulation is unknown."""
    if len(cdr) < 12 or cdr[0] != 0 or cdr[1] not in (0, 1):
        return None
    sec, nsec = struct.unpack('<iI' if cdr[1] == 1 else '>iI', cdr[4:12])
    return sec * 1_000_000_000 + nsec


def decimated_topic(topic: str, rate_hz: float) -> str:
    """The channel of ``topic`` at ``rate_hz``: ``/eha/state/decimated_50hz``."""
    return f'{topic}/decimated_{rate_hz:g}hz'


def parse_endpoint(text: str, default_host: str = '127.0.0.1') -> tuple:
    """``[HOST:]PORT`` -> ``(host, port)``; raises ValueError naming what is wrong."""
    host, sep, port = str(text).rpartition(':')
    host = host if sep else default_host
    try:
        value = int(port)
    except ValueError:
        raise ValueError(f'{text!r}: expected [HOST:]PORT with PORT an integer') from None
    if not 0 <= value <= 65535 or not host:
        raise ValueError(f'{text!r}: expected [HOST:]PORT with PORT in 0..65535')
    return host, value


@dataclasses.dataclass(frozen=True)
class ChannelSpec:
    """One advertised channel: ``topic`` carries ``type_name`` (``pkg/msg/Type``) in CDR with
    its ``ros2msg`` ``schema``; ``source`` is the graph topic it comes from (itself, or for a
    decimated channel the full-rate one), ``rate_hz`` its forwarding rate (None: every
    message), ``latched``: a client that subscribes late gets its history."""

    id: int
    topic: str
    type_name: str
    schema: str
    source: str
    rate_hz: Optional[float] = None
    latched: bool = False

    def advertisement(self) -> dict:
        meta = {'ros_type': self.type_name, 'source_topic': self.source,
                'latched': str(self.latched).lower()}
        if self.rate_hz is not None:
            meta['decimated_to_hz'] = f'{self.rate_hz:g}'
        return {'id': self.id, 'topic': self.topic, 'encoding': 'cdr',
                'schemaName': self.type_name, 'schema': self.schema,
                'schemaEncoding': 'ros2msg', 'metadata': meta}


class ChannelTable:
    """The channels of ``topics`` (``{topic: type}``), schemas from ``definition(type)`` (the
    MCAP writer's :func:`eha_ros.recording.definitions.message_definition`), plus a decimated
    channel per rate in ``decimate`` (``{topic: [Hz, ...]}``) of each topic named there."""

    def __init__(self, topics: Mapping[str, str], definition: Callable[[str], str],
                 latched: Iterable[str] = (), decimate: Optional[Mapping] = None):
        self.channels: List[ChannelSpec] = []
        latched = set(latched)
        schemas = {}
        for topic, type_name in topics.items():
            schema = schemas.setdefault(type_name, definition(type_name))
            self.channels.append(ChannelSpec(len(self.channels) + 1, topic, type_name, schema,
                                             topic, None, topic in latched))
        for topic, rates in (decimate or {}).items():
            if topic not in topics:
                raise ValueError(f'decimate: {topic!r} is not a bridged topic (topics: '
                                 f'{", ".join(topics)})')
            for rate in rates:
                rate = float(rate)
                if not (math.isfinite(rate) and rate > 0):
                    raise ValueError(f'decimate: {topic} at {rate!r} Hz: the rate must be a '
                                     'positive number')
                self.channels.append(ChannelSpec(
                    len(self.channels) + 1, decimated_topic(topic, rate), topics[topic],
                    schemas[topics[topic]], topic, rate, topic in latched))
        self.by_id = {c.id: c for c in self.channels}
        self.by_source: Dict[str, List[ChannelSpec]] = {}
        for c in self.channels:
            self.by_source.setdefault(c.source, []).append(c)


class Decimator:
    """Forwards the first message of each period of ``rate_hz`` on the stamp clock: one per
    bin ``stamp // period``, so the choice depends on the stamps alone (a lockstep run gives
    the same messages every time)."""

    def __init__(self, rate_hz: float):
        self.period_ns = max(1, round(1e9 / rate_hz))
        self._last_bin: Optional[int] = None

    def keep(self, stamp_ns: int) -> bool:
        b = stamp_ns // self.period_ns
        if self._last_bin is not None and b <= self._last_bin:
            return False
        self._last_bin = b
        return True


class ClientQueue:
    """A client's outbox: control messages (JSON text, never dropped) and data frames (at
    most ``depth``; when full the oldest is dropped and counted per channel topic).  Producers
    may be any thread; :meth:`take` is the sender's."""

    def __init__(self, depth: int = QUEUE_DEPTH):
        if depth < 1:
            raise ValueError(f'client queue depth {depth!r} must be at least 1')
        self.depth = int(depth)
        self._data: collections.deque = collections.deque()
        self._control: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self.dropped: Dict[str, int] = {}
        self.sent: Dict[str, int] = {}
        self.wake: Callable[[], None] = lambda: None

    def put_data(self, topic: str, frame: bytes) -> None:
        with self._lock:
            was_empty = not self._data and not self._control
            if len(self._data) >= self.depth:
                old, _ = self._data.popleft()
                self.dropped[old] = self.dropped.get(old, 0) + 1
            self._data.append((topic, frame))
        if was_empty:
            self.wake()

    def put_control(self, message) -> None:
        with self._lock:
            was_empty = not self._data and not self._control
            self._control.append(message)
        if was_empty:
            self.wake()

    def take(self, limit: int = 256) -> list:
        """Up to ``limit`` messages, control first: ``[(topic or None, bytes or str)]``."""
        out = []
        with self._lock:
            while self._control and len(out) < limit:
                out.append((None, self._control.popleft()))
            while self._data and len(out) < limit:
                topic, frame = self._data.popleft()
                self.sent[topic] = self.sent.get(topic, 0) + 1
                out.append((topic, frame))
        return out

    def __len__(self) -> int:
        with self._lock:
            return len(self._data) + len(self._control)

    @property
    def total_dropped(self) -> int:
        with self._lock:
            return sum(self.dropped.values())


def parse_client_message(text) -> dict:
    """A client's JSON message, checked: a known ``op`` with its required fields.

    Raises
    ------
    ProtocolError
        Naming the op or field that is wrong.
    """
    if isinstance(text, (bytes, bytearray)):
        raise ProtocolError('binary client messages (client publish, service calls) are not '
                            'supported by this server')
    try:
        msg = json.loads(text)
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f'client message is not JSON: {exc}') from None
    if not isinstance(msg, dict) or not isinstance(msg.get('op'), str):
        raise ProtocolError('client message has no "op"')
    op = msg['op']
    if op not in _CLIENT_OPS:
        near = difflib.get_close_matches(op, list(_CLIENT_OPS), n=1)
        hint = f' (did you mean {near[0]}?)' if near else ''
        raise ProtocolError(f'unsupported op {op!r}{hint}')
    for field in _CLIENT_OPS[op]:
        if not isinstance(msg.get(field), list):
            raise ProtocolError(f'{op}: "{field}" must be a list')
    if op == 'subscribe':
        if not all(isinstance(s, dict) and _is_uint(s.get('id')) and _is_uint(s.get('channelId'))
                   for s in msg['subscriptions']):
            raise ProtocolError('subscribe: each subscription needs integer "id" and '
                                '"channelId"')
    elif op == 'unsubscribe':
        if not all(_is_uint(i) for i in msg['subscriptionIds']):
            raise ProtocolError('unsubscribe: "subscriptionIds" must be integers')
    elif op == 'setParameters':
        if not all(isinstance(p, dict) and isinstance(p.get('name'), str)
                   for p in msg['parameters']):
            raise ProtocolError('setParameters: each parameter needs a "name"')
    elif op in ('getParameters', 'subscribeParameterUpdates', 'unsubscribeParameterUpdates'):
        if not all(isinstance(n, str) for n in msg['parameterNames']):
            raise ProtocolError(f'{op}: "parameterNames" must be strings')
    return msg


def _is_uint(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 2 ** 32


def resolve_parameter(name: str, declared: Mapping[str, Iterable[str]]) -> tuple:
    """``[/]node.parameter`` -> ``(node, parameter)`` among ``declared`` (``{node: names}``).

    Raises
    ------
    ValueError
        One line: the name has no node part, the node is unknown (with the graph's nodes), or
        the node has no such parameter (with the nearest declared names, as ``--set``).
    """
    from eha_ros.graph import undeclared_message
    node, dot, param = str(name).lstrip('/').partition('.')
    if not dot or not node or not param:
        raise ValueError(f'parameter {name!r}: expected node.parameter')
    if node not in declared:
        near = difflib.get_close_matches(node, list(declared), n=1)
        raise ValueError(f'parameter {name!r}: unknown node {node!r}'
                         + (f' (did you mean {near[0]}?)' if near else '')
                         + f' (nodes: {", ".join(declared)})')
    if param not in declared[node]:
        raise ValueError(undeclared_message(node, param, declared[node]))
    return node, param


class _Client:
    def __init__(self, cid: int, ws, depth: int):
        self.id = cid
        self.ws = ws
        self.remote = '%s:%s' % tuple(ws.remote_address[:2])
        self.queue = ClientQueue(depth)
        self.subs: Dict[int, int] = {}        # channel id -> subscription id
        self.params: set = set()              # parameter update subscriptions
        self.event = asyncio.Event()
        self.sending = 0                      # messages taken from the queue, not yet sent
        self.reported_drops = 0
        self.last_drop_status = 0.0


class LiveServer:
    """A Foxglove WebSocket server on ``host:port`` (port 0: any free one, see :attr:`port`)
    for the channels of ``table``, each client with its own :class:`ClientQueue` of
    ``queue_depth`` data messages.

    ``parameters`` (optional) serves the parameters capability: an object with
    ``get(names) -> [{'name', 'value'[, 'type']}]`` and ``set(params, done)``, where ``done``
    (callable from any thread) takes ``(values, refusals)``: the parameters' values after the
    set and one line per refused parameter.  ``time``: advertise the time capability
    (:meth:`broadcast_time`).  :meth:`publish` may be called from any thread and never
    blocks on a client."""

    def __init__(self, table: ChannelTable, host: str = '127.0.0.1', port: int = 8765,
                 queue_depth: int = QUEUE_DEPTH, parameters=None, time: bool = False,
                 name: str = 'eha_ros foxglove_bridge', send_buffer_b: int = 0,
                 metadata: Optional[Mapping[str, str]] = None):
        self.table = table
        self.host, self.requested_port = host, int(port)
        self.queue_depth = int(queue_depth)
        self.parameters = parameters
        self.time = bool(time)
        self.name = name
        self.send_buffer_b = int(send_buffer_b)
        self.metadata = dict(metadata or {})
        self.clients: Dict[int, _Client] = {}
        self.closed_clients: List[dict] = []
        self._lock = threading.Lock()
        self._client_ids = itertools.count(1)
        self._latched: Dict[int, collections.deque] = {
            c.id: collections.deque(maxlen=1000) for c in table.channels if c.latched}
        self._decimators = {c.id: Decimator(c.rate_hz) for c in table.channels if c.rate_hz}
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._thread: Optional[threading.Thread] = None
        self._server = None
        self.port: Optional[int] = None

    # lifecycle ---------------------------------------------------------------------------
    def start(self, timeout_s: float = 10.0) -> 'LiveServer':
        """Bind and serve in a thread of its own; raises OSError (e.g. the port is taken)."""
        ready = threading.Event()
        failure: list = []

        def run():
            self._loop = loop = asyncio.new_event_loop()
            try:
                loop.run_until_complete(self._open())
            except Exception as exc:  # reported to start()'s caller
                failure.append(exc)
                loop.close()
                return
            finally:
                ready.set()
            try:
                loop.run_forever()
            finally:
                loop.run_until_complete(loop.shutdown_asyncgens())
                loop.close()

        self._thread = threading.Thread(target=run, name='foxglove_server', daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s):
            raise OSError(f'foxglove server did not start within {timeout_s:g} s')
        if failure:
            raise failure[0]
        return self

    async def _open(self):
        from websockets.asyncio.server import serve
        self._server = await serve(self._handle, self.host, self.requested_port,
                                   subprotocols=[SUBPROTOCOL], compression=None,
                                   max_size=1 << 20, ping_interval=None)
        self.port = self._server.sockets[0].getsockname()[1]

    def stop(self, flush_s: float = 5.0) -> Dict[int, int]:
        """Stop serving: first let every connected client's queue drain (at most ``flush_s``),
        so that a client sees the run to its last message, then close each connection (code
        1001, going away).  Returns ``{client id: messages left unsent}`` for the clients
        whose queue did not drain in time (empty when every message was sent)."""
        if self._loop is None or self._thread is None:
            return {}
        left: Dict[int, int] = {}

        async def close():
            self._server.close(close_connections=False)   # no new clients
            for c in self._clients():   # the final drop count, however recent the last one was
                self._tell_drops(c, force=True)
            deadline = time.monotonic() + flush_s
            while time.monotonic() < deadline and any(
                    len(c.queue) or c.sending for c in self._clients()):
                await asyncio.sleep(0.01)
            left.update({c.id: len(c.queue) + c.sending for c in self._clients()
                         if len(c.queue) or c.sending})
            for c in self._clients():
                await c.ws.close(1001, 'server stopping')
            await self._server.wait_closed()
        try:
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(flush_s + 5.0)
        except Exception:
            pass
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5.0)
        self._thread = None
        return left

    def _clients(self) -> List[_Client]:
        """The clients connected now (a copy, to go through without the lock)."""
        with self._lock:
            return list(self.clients.values())

    # producers (any thread) ------------------------------------------------------------------
    def publish(self, source: str, payload: bytes, log_time_ns: Optional[int] = None) -> None:
        """Forward one message of graph topic ``source`` to every client subscribed to one
        of its channels (log time: its header stamp, else ``log_time_ns``, else now)."""
        stamp = header_stamp_ns(payload)
        t = stamp if stamp is not None else (log_time_ns if log_time_ns is not None
                                             else time.time_ns())
        for ch in self.table.by_source.get(source, ()):
            if ch.rate_hz is not None and not self._decimators[ch.id].keep(t):
                continue
            if ch.latched:
                with self._lock:
                    self._latched[ch.id].append((t, payload))
            with self._lock:
                targets = [(c, c.subs[ch.id]) for c in self.clients.values() if ch.id in c.subs]
            for client, sid in targets:
                client.queue.put_data(ch.topic, message_data(sid, t, payload))

    def broadcast_time(self, t_ns: int) -> None:
        frame = struct.pack('<BQ', OP_TIME, int(t_ns))  # TIME: opcode, server time (u64, ns)
        for c in self._clients():
            c.queue.put_data('time', frame)

    def publish_parameter_values(self, values: Sequence[dict]) -> None:
        """Parameter updates to the clients subscribed to them."""
        for c in self._clients():
            mine = [v for v in values if v['name'] in c.params]
            if mine:
                c.queue.put_control(json.dumps({'op': 'parameterValues', 'parameters': mine}))

    # accounting ------------------------------------------------------------------------------
    def client_stats(self) -> List[dict]:
        """Every client, connected or gone: ``{'client', 'remote', 'connected', 'dropped':
        {topic: n}, 'sent': {topic: n}, 'queued'}``."""
        with self._lock:
            live = list(self.clients.values())
            gone = list(self.closed_clients)
        return sorted(gone + [_stats(c, True) for c in live], key=lambda s: s['client'])

    def subscribed_clients(self, channel_ids: Iterable[int]) -> int:
        """How many clients are subscribed to every one of ``channel_ids``."""
        ids = set(channel_ids)
        with self._lock:
            return sum(ids <= set(c.subs) for c in self.clients.values())

    # the loop --------------------------------------------------------------------------------
    async def _handle(self, ws):
        if self.send_buffer_b:
            import socket
            sock = ws.transport.get_extra_info('socket')
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer_b)
        with self._lock:
            client = _Client(next(self._client_ids), ws, self.queue_depth)
            self.clients[client.id] = client
        loop = asyncio.get_running_loop()
        client.queue.wake = lambda: loop.call_soon_threadsafe(client.event.set)
        caps = (['parameters', 'parametersSubscribe'] if self.parameters is not None else [])
        caps += ['time'] if self.time else []
        client.queue.put_control(json.dumps({
            'op': 'serverInfo', 'name': self.name, 'capabilities': caps,
            'supportedEncodings': ['cdr'], 'metadata': self.metadata}))
        client.queue.put_control(json.dumps({
            'op': 'advertise', 'channels': [c.advertisement() for c in self.table.channels]}))
        sender = asyncio.ensure_future(self._send_loop(client))
        try:
            async for raw in ws:
                try:
                    self._on_message(client, parse_client_message(raw))
                except (ProtocolError, ValueError) as exc:
                    client.queue.put_control(json.dumps(
                        {'op': 'status', 'level': ERROR, 'message': str(exc)}))
        except Exception:
            pass
        finally:
            sender.cancel()
            with self._lock:
                self.clients.pop(client.id, None)
                self.closed_clients.append(_stats(client, False))

    async def _send_loop(self, client: _Client):
        while True:
            await client.event.wait()
            client.event.clear()
            while batch := client.queue.take():
                client.sending = len(batch)
                for _, item in batch:
                    await client.ws.send(item)
                    client.sending -= 1
                self._tell_drops(client)

    def _tell_drops(self, client: _Client, force: bool = False) -> None:
        """A warning status with the client's drops per topic, when it has new ones: at most
        one per :data:`DROP_STATUS_PERIOD_S`, unless ``force`` (the last one, at stop)."""
        total = client.queue.total_dropped
        now = time.monotonic()
        if total == client.reported_drops or (
                not force and now - client.last_drop_status < DROP_STATUS_PERIOD_S):
            return
        client.reported_drops, client.last_drop_status = total, now
        per = ', '.join(f'{t}: {n}' for t, n in sorted(client.queue.dropped.items()))
        client.queue.put_control(json.dumps({
            'op': 'status', 'level': WARNING, 'id': 'dropped',
            'message': f'the bridge dropped {total} messages for this client, which reads '
                       f'slower than the graph publishes (queue of {client.queue.depth}; '
                       f'{per}); the graph itself lost nothing'}))

    def _on_message(self, client: _Client, msg: dict) -> None:
        op = msg['op']
        if op == 'subscribe':
            latched = []
            for s in msg['subscriptions']:
                ch = self.table.by_id.get(s['channelId'])
                if ch is None:
                    raise ProtocolError(f'subscribe: no channel {s["channelId"]}')
                if s['id'] in client.subs.values():
                    raise ProtocolError(f'subscribe: subscription id {s["id"]} is in use')
                with self._lock:
                    client.subs[ch.id] = s['id']
                    if ch.latched:
                        latched += [(ch, s['id'], t, p) for t, p in self._latched[ch.id]]
            for ch, sid, t, payload in latched:   # the history first, then live messages
                client.queue.put_data(ch.topic, message_data(sid, t, payload))
        elif op == 'unsubscribe':
            gone = set(msg['subscriptionIds'])
            with self._lock:
                client.subs = {c: s for c, s in client.subs.items() if s not in gone}
        elif op in ('getParameters', 'setParameters', 'subscribeParameterUpdates',
                    'unsubscribeParameterUpdates'):
            self._on_parameters(client, msg)

    def _on_parameters(self, client: _Client, msg: dict) -> None:
        if self.parameters is None:
            raise ProtocolError(f'{msg["op"]}: this server has no parameters capability')
        op = msg['op']
        if op == 'subscribeParameterUpdates':
            client.params.update(msg['parameterNames'])
            return
        if op == 'unsubscribeParameterUpdates':
            client.params.difference_update(msg['parameterNames'])
            return
        reply = {'op': 'parameterValues'}
        if 'id' in msg:
            reply['id'] = msg['id']
        if op == 'getParameters':
            async def answer():
                await self._parameters_listed(client)
                reply['parameters'] = self.parameters.get(msg['parameterNames'])
                client.queue.put_control(json.dumps(reply))
            asyncio.ensure_future(answer())
            return

        def done(values, refusals):
            for line in refusals:
                client.queue.put_control(json.dumps(
                    {'op': 'status', 'level': ERROR, 'message': line}))
            client.queue.put_control(json.dumps(dict(reply, parameters=list(values))))
            self.publish_parameter_values(values)

        async def apply():
            await self._parameters_listed(client)
            self.parameters.set(msg['parameters'], done)
        asyncio.ensure_future(apply())

    async def _parameters_listed(self, client: _Client) -> None:
        """Wait (at most :data:`PARAMETER_WAIT_S`) until the provider has listed every
        node's parameters (its optional ``unlisted() -> [node]``); a node still unlisted then
        is told to the client as a warning, never left out quietly."""
        unlisted = getattr(self.parameters, 'unlisted', lambda: [])
        deadline = time.monotonic() + PARAMETER_WAIT_S
        while unlisted() and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        missing = unlisted()
        if missing:
            client.queue.put_control(json.dumps({
                'op': 'status', 'level': WARNING, 'id': 'parameters-unlisted',
                'message': f'parameters of {", ".join(missing)} are not listed: their '
                           f'parameter services did not answer within {PARAMETER_WAIT_S:g} s '
                           f'(not running?)'}))


def _stats(client: _Client, connected: bool) -> dict:
    q = client.queue
    with q._lock:
        return {'client': client.id, 'remote': client.remote, 'connected': connected,
                'dropped': dict(q.dropped), 'sent': dict(q.sent),
                'queued': len(q._data) + len(q._control)}
