"""``foxglove_bridge``: the graph live in Foxglove (desktop or web, "Open connection",
``ws://localhost:8765``) over the Foxglove WebSocket protocol.

Examples::

    eha-graph --mode realtime --duration 60 --foxglove            # the graph and the bridge
    ros2 run eha_ros foxglove_bridge                              # beside a running graph
    foxglove_bridge --ros-args -p port:=9000 -p host:=0.0.0.0

Every graph topic is one channel, with its ROS type and the ``ros2msg`` schema the MCAP
writer uses (:func:`eha_ros.recording.definitions.message_definition`); messages travel as
the CDR bytes rclpy received (``raw=True``), never decoded.  Latched topics (``/eha/events``,
``/eha/handshake``) reach a client that connects late: the bridge keeps their history.  Each
1 kHz topic also has a decimated channel per rate of ``decimated_rates_hz``
(``/eha/state/decimated_50hz``: the first message of each 20 ms of its stamps; the
channel's metadata says so).  In lockstep the bridge broadcasts the simulation time (the
protocol's time capability) from ``/clock``, so Foxglove's plots run on simulated time; in
realtime the messages' stamps are their log times.

A slow client never slows the graph: the subscriptions only append to each client's bounded
queue (:class:`eha_ros.foxglove.core.ClientQueue`); when one is full its oldest message is
dropped, counted per channel and client, reported on ``/diagnostics`` (``foxglove_bridge:
clients``, WARN once anything was dropped) and told to the client as a warning status.

Parameters (the protocol's parameters capability): a client lists every node's parameters,
``node.parameter`` (``servovalve_plant.radial_clearance_m``), and sets them.  A set goes
through the checks of ``--set``: an unknown node or parameter is refused with the nearest
declared names, and the node's own checks refuse a value out of range with the reason; the
client gets each refusal as an error status.  Every accepted change is on ``/eha/events`` as
``live``: the plant (wear) and the controller (gains) publish it themselves, at the tick it
took effect; for the other nodes' parameters the bridge publishes it, stamped with the last
state's time.  Setting a wear parameter from Foxglove's parameter panel is live fault
injection.

Parameters (``--ros-args -p name:=value``):

======================  ===================================================  =============
``host``                address to serve on                                  ``127.0.0.1``
``port``                TCP port (0: any free one, see ``port_file``)        8765
``port_file``           write the bound port to this file ('' : none)        ``''``
``mode``                the graph's timing mode (lockstep: time capability)   ``realtime``
``topics``              graph topics to serve                                 all
``decimated_rates_hz``  rates of the decimated channels of 1 kHz topics       ``[50.0]``
``client_queue_depth``  data messages a client's queue holds                  4096
``send_buffer_b``       a client socket's send buffer (0: the system's)       0
``wait_for_clients``    report to the start-up handshake only once this many  0
                        clients subscribed to every full-rate channel
``parameter_nodes``     nodes whose parameters clients list and set           the graph's
``diagnostics_period_s`` period of the bridge's own ``/diagnostics`` status   1.0
======================  ===================================================  =============
"""

from __future__ import annotations

from contextlib import suppress
import itertools
import math
from pathlib import Path
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from eha_ros import graph
from eha_ros.foxglove.core import (ChannelTable, header_stamp_ns, LiveServer, QUEUE_DEPTH,
                                   resolve_parameter)
from eha_ros.nodes.common import (advertise, check_choice, declare, EventChannel, publish_status,
                                  run_node, take_waiting)
from eha_ros.nodes.handshake import Handshake
from eha_ros.physics import ParameterError
from eha_ros.physics.events import CONTROLLER_RUNTIME, PLANT_RUNTIME

__all__ = ['FoxgloveBridge', 'main', 'SELF_ANNOUNCED']

#: Parameters whose live changes the node itself publishes on ``/eha/events`` (at its tick).
SELF_ANNOUNCED = {'servovalve_plant': frozenset(PLANT_RUNTIME),
                  'controller': frozenset(CONTROLLER_RUNTIME)}
#: Topics at 1 kHz that get decimated channels.
FAST_TOPICS = tuple(t for t, hz in graph.RATES_HZ.items() if hz >= 500.0)
#: rclpy's own parameters, left out of the lists.
_OWN = frozenset({'use_sim_time', 'start_type_description_service'})


class _Parameters:
    """The parameters capability over the graph nodes' parameter services: names, types and
    values read once each node's services are up, sets sent to the node (whose own checks
    decide), the results handed back to the server."""

    def __init__(self, bridge: 'FoxgloveBridge', nodes):
        self.bridge = bridge
        self.clients = {n: AsyncParameterClient(bridge, n) for n in nodes}
        self.values: dict = {}                    # node -> {name: value}
        self._lock = threading.Lock()
        self._listing = set()

    def poll(self) -> None:
        """List the parameters of the nodes whose services came up (a timer)."""
        for node, client in self.clients.items():
            if node in self.values or node in self._listing or not client.services_are_ready():
                continue
            self._listing.add(node)
            client.list_parameters(callback=lambda f, n=node: self._on_list(n, f))

    def _on_list(self, node, future):
        names = [n for n in future.result().result.names if n not in _OWN]
        self.clients[node].get_parameters(
            names, callback=lambda f: self._on_values(node, names, f))

    def _on_values(self, node, names, future):
        values = {n: _native(v) for n, v in zip(names, future.result().values)}
        with self._lock:
            self.values[node] = values

    def unlisted(self) -> list:
        """The nodes whose parameters are not listed yet."""
        with self._lock:
            return [n for n in self.clients if n not in self.values]

    def get(self, names):
        with self._lock:
            everything = [{'name': f'{n}.{k}', 'value': v} for n, vals in self.values.items()
                          for k, v in sorted(vals.items())]
        if not names:
            return everything
        wanted = {str(n).lstrip('/') for n in names}
        return [p for p in everything if p['name'] in wanted]

    def set(self, params, done) -> None:
        refusals, by_node = [], {}
        with self._lock:
            declared = {n: set(v) for n, v in self.values.items()}
        for p in params:
            try:
                node, name = resolve_parameter(p['name'], declared)
                value = _typed(p.get('value'), self.values[node][name], p['name'])
            except (ValueError, KeyError) as exc:
                refusals.append(str(exc).strip('"\''))
                continue
            by_node.setdefault(node, []).append((name, value))
        if not by_node:
            done([], refusals)
            return
        pending = {'n': len(by_node), 'values': []}
        lock = threading.Lock()

        def answered(node, items, future):
            try:
                results = future.result().results
            except Exception as exc:  # the node is gone
                results = [type('R', (), {'successful': False, 'reason': str(exc)})] * len(items)
            accepted = {}
            with lock:
                for (name, value), r in zip(items, results):
                    if r.successful:
                        accepted[name] = value
                    else:
                        refusals.append(f'{node}.{name} = {value!r} refused: {r.reason}')
                if accepted:
                    with self._lock:
                        self.values[node].update(accepted)
                    pending['values'] += [{'name': f'{node}.{k}', 'value': v}
                                          for k, v in accepted.items()]
                    self.bridge.announce(node, accepted)
                pending['n'] -= 1
                last = pending['n'] == 0
            if last:
                done(pending['values'], refusals)
        for node, items in by_node.items():
            self.clients[node].set_parameters(
                [Parameter(n, value=v) for n, v in items],
                callback=lambda f, n=node, i=items: answered(n, i, f))


def _native(value):
    """A ROS ``ParameterValue`` as a JSON value."""
    from rclpy.parameter import parameter_value_to_python
    v = parameter_value_to_python(value)
    return list(v) if isinstance(v, (list, tuple)) or hasattr(v, 'tolist') else v


def _typed(value, current, name):
    """``value`` as the type of the parameter's ``current`` value (a JSON integer for a
    double parameter is a double, a boolean is no number); raises ValueError for another
    type."""
    if isinstance(current, float) and type(value) in (int, float):
        return float(value)
    if type(current) in (bool, int, str, list) and type(value) is type(current):
        return value
    raise ValueError(f'{name} = {value!r} refused: the parameter is of type '
                     f'{type(current).__name__}')


class FoxgloveBridge(Node):
    """The bridge node (see the module docstring)."""

    node_name = 'foxglove_bridge'

    def __init__(self, **kwargs):
        super().__init__(self.node_name, **kwargs)
        host = declare(self, 'host', '127.0.0.1', 'address to serve the WebSocket on')
        port = declare(self, 'port', 8765, 'TCP port to serve on (0: any free port, written '
                       'to port_file)', 0, 65535)
        port_file = declare(self, 'port_file', '', 'file to write the bound port to ("": '
                            'none), for a caller that asked for port 0')
        mode = declare(self, 'mode', 'realtime', 'the graph timing mode: lockstep adds the '
                       'time capability (simulation time from /clock)', choices=graph.MODES)
        check_choice('mode', mode, graph.MODES)
        topics = declare(self, 'topics', list(graph.TOPICS) + [graph.TOPIC_HANDSHAKE],
                         'graph topics to serve, one channel each')
        rates = declare(self, 'decimated_rates_hz', [50.0], 'rates of the decimated channel '
                        'of each 1 kHz topic [Hz] (first message of each period of its stamps)')
        depth = declare(self, 'client_queue_depth', QUEUE_DEPTH, 'data messages one client\'s '
                        'queue holds before its oldest is dropped (counted)', 1, 10 ** 7)
        send_buffer = declare(self, 'send_buffer_b', 0, 'send buffer of a client socket [B] '
                              '(0: the system default)', 0, 1 << 30)
        self.wait_for_clients = declare(
            self, 'wait_for_clients', 0, 'report to the start-up handshake only once this '
            'many clients subscribed to every full-rate channel (a run seen from its first '
            'message)', 0, 1000)
        nodes = declare(self, 'parameter_nodes', list(graph.NODES), 'nodes whose parameters '
                        'clients list and set')
        period = declare(self, 'diagnostics_period_s', 1.0, 'period of the bridge\'s own '
                         '/diagnostics status [s]', 0.01, 3600.0)
        known = {**graph.TOPICS, graph.TOPIC_HANDSHAKE: 'diagnostic_msgs/msg/DiagnosticStatus'}
        unknown = [t for t in topics if t not in known]
        if unknown:
            raise ParameterError(f'topics: {unknown[0]!r} is not a graph topic (topics: '
                                 f'{", ".join(known)})')
        from eha_ros.recording.definitions import message_definition
        served = {t: known[t] for t in topics}
        self.table = ChannelTable(served, message_definition, latched=graph.LATCHED_TOPICS,
                                  decimate={t: rates for t in FAST_TOPICS if t in served})
        self.mode = mode
        self.parameters = _Parameters(self, [n for n in nodes if n])
        self.events = EventChannel(self, 1_000_000)
        self._last_state_ns = 0
        self.server = LiveServer(self.table, host, port, depth, self.parameters,
                                 time=mode == 'lockstep', send_buffer_b=send_buffer,
                                 metadata={'mode': mode})
        self._entries = []  # (message class, {'forward': callback, 'sub': subscription, 'topic'})
        for topic, type_name in served.items():
            cls = graph.message_class(type_name)
            entry: dict = {'topic': topic}
            entry['forward'] = self._forward(topic, cls, entry)
            entry['sub'] = self.create_subscription(cls, topic, entry['forward'],
                                                    graph.topic_qos(topic), raw=True)
            self._entries.append((cls, entry))
        self.handshake = None
        self.diagnostics = advertise(self, DiagnosticArray, graph.TOPIC_DIAGNOSTICS)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.05, self._poll, clock=steady)
        self.create_timer(period, self._report, clock=steady)
        self.port_file = port_file

    def serve(self) -> 'FoxgloveBridge':
        """Bind and serve (raises OSError, e.g. for a port in use); the port to
        ``port_file``."""
        self.server.start()
        if self.port_file:
            tmp = Path(self.port_file).with_suffix('.tmp')
            tmp.write_text(f'{self.server.port}\n')
            tmp.replace(self.port_file)
        self.get_logger().info(f'serving ws://{self.server.host}:{self.server.port} '
                               f'({len(self.table.channels)} channels, {self.mode})')
        return self

    # messages --------------------------------------------------------------------------------
    def _forward(self, topic: str, cls, entry: dict):
        """The raw callback of ``topic``: forward the bytes, and what else is waiting
        (``entry['sub']``: the subscription, set once created)."""
        server, state = self.server, topic == graph.TOPIC_STATE
        clock = topic == graph.TOPIC_CLOCK and self.mode == 'lockstep'

        def on_message(data: bytes) -> None:
            # then what else is waiting: far cheaper than a pass each
            waiting = (taken for taken, _ in take_waiting(entry['sub'], cls, raw=True))
            for data in itertools.chain([data], waiting):
                data = bytes(data)
                server.publish(topic, data)
                if state or clock:
                    t = header_stamp_ns(data)
                    if t is not None and state:
                        self._last_state_ns = t
                    elif t is not None:
                        server.broadcast_time(t)
        return on_message

    def _poll(self) -> None:
        self.parameters.poll()
        if self.handshake is None:
            full = [c.id for c in self.table.channels if c.rate_hz is None]
            if self.server.subscribed_clients(full) >= self.wait_for_clients:
                self.handshake = Handshake(self)
                for _, entry in self._entries:
                    self.handshake.watch(entry['sub'], entry['topic'])
                self.handshake.watch(self.diagnostics, graph.TOPIC_DIAGNOSTICS)
                self.handshake.watch(self.events.pub, graph.TOPIC_EVENTS)

    def announce(self, node: str, changes: dict) -> None:
        """A live change the node does not publish itself, on ``/eha/events``."""
        own = SELF_ANNOUNCED.get(node, frozenset())
        numeric = {k: float(v) for k, v in changes.items() if k not in own
                   and isinstance(v, (int, float)) and not isinstance(v, bool)}
        if numeric:
            self.events.publish(self._last_state_ns, 'live', math.nan, numeric, node=node)

    def _report(self) -> None:
        """The bridge's own status on ``/diagnostics``, from the graph's start on (before it,
        a listener not yet matched would see a gap)."""
        if self.handshake is None or not self.handshake.started:
            return
        stats = self.server.client_stats()
        dropped = sum(sum(s['dropped'].values()) for s in stats)
        live = [s for s in stats if s['connected']]
        values = {'Clients connected': len(live), 'Clients since start': len(stats),
                  'Dropped (all clients)': dropped}
        for s in stats:
            values[f'client {s["client"]} remote'] = s['remote']
            values[f'client {s["client"]} sent'] = sum(s['sent'].values())
            values[f'client {s["client"]} queued'] = s['queued']
            for topic, n in sorted(s['dropped'].items()):
                values[f'client {s["client"]} dropped {topic}'] = n
        lost = f'{dropped} message(s) dropped for slow clients' if dropped else 'nothing dropped'
        publish_status(self, self.diagnostics, f'{self.get_name()}: clients',
                       DiagnosticStatus.WARN if dropped else DiagnosticStatus.OK,
                       f'{len(live)} client(s); {lost}', values,
                       hardware_id=f'ws://{self.server.host}:{self.server.port}')

    def close(self) -> None:
        """Forward what the subscriptions still hold, let each client's queue drain (at most
        5 s), then close the connections; a message left unsent is logged, never silent."""
        for cls, entry in self._entries:
            try:
                with entry['sub'].handle:
                    taken = entry['sub'].handle.take_message(cls, True)
            except Exception:  # the subscription is gone (the context shut down)
                continue
            if taken is not None:
                entry['forward'](taken[0])
        with suppress(Exception):  # the context may be shut down (SIGINT): nothing to publish on
            self._report()
        for cid, n in sorted(self.server.stop().items()):
            self.get_logger().warning(f'client {cid}: {n} message(s) still queued when the '
                                      f'bridge stopped were not sent (it read too slowly)')


def _serving(**kwargs) -> FoxgloveBridge:
    return FoxgloveBridge(**kwargs).serve()


_serving.node_name = FoxgloveBridge.node_name


def main(args=None) -> int:
    return run_node(_serving, args)
