"""What the nodes share: topic names, QoS, timing modes, parameter declaration, the tick
loop (:class:`NodeLoop`) and the ``main()`` boilerplate; each node's timing report is
:mod:`.timing`'s."""

from __future__ import annotations

import functools
import math
import sys
import threading
from contextlib import nullcontext, suppress
from typing import Callable, Iterable

import rclpy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from eha_ros.physics import ParameterError
from eha_ros.physics.params import SPEC_BY_NAME

from eha_ros.graph import undeclared_message  # noqa: F401 (re-exported)
from eha_ros.graph import (MODES, TIMING_SUFFIX, TOPIC_CLOCK, TOPIC_COMMAND,
                           TOPIC_DIAGNOSTICS, TOPIC_HEALTH, TOPIC_SERVOVALVE, TOPIC_STATE,
                           graph_qos)

__all__ = ['TOPIC_COMMAND', 'TOPIC_SERVOVALVE', 'TOPIC_STATE', 'TOPIC_HEALTH',
           'TOPIC_DIAGNOSTICS', 'TOPIC_CLOCK', 'QOS', 'MODES', 'declare', 'declare_physics',
           'run_node', 'stamp_to_ns', 'ns_to_stamp', 'TIMING_SUFFIX',
           'refuse_undeclared', 'undeclared_message', 'declare_realtime', 'declare_loop',
           'NodeLoop', 'refuse_loop_options', 'take_waiting',
           'apply_realtime_settings', 'EventChannel']

#: Every graph topic (names and QoS from :mod:`eha_ros.graph`): reliable, last 1000
#: kept, volatile: a reader outside the loop (recorder, health monitor) may lag 1 s at 1 kHz.
QOS = graph_qos()


def subscribe(node: Node, msg_type, topic: str, callback):
    """A subscription on the graph QoS without rclpy's default QoS-event handlers (each is one
    more entity in every wait of the executor, at 1 kHz that is most of its cost)."""
    from rclpy.event_handler import SubscriptionEventCallbacks
    return node.create_subscription(
        msg_type, topic, callback, QOS,
        event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))


def advertise(node: Node, msg_type, topic: str):
    """A publisher on the graph QoS without default QoS-event handlers (see subscribe)."""
    from rclpy.event_handler import PublisherEventCallbacks
    return node.create_publisher(
        msg_type, topic, QOS, event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))


def take_waiting(subscription, msg_type, raw: bool = False):
    """Every message waiting on ``subscription`` (one no executor spins), oldest first, as
    ``(message, info)``: rclpy's ``take`` with the message info (sequence number, receipt
    time), without an executor pass or a callback per message; ``raw``: the message as its
    serialized bytes."""
    handle = subscription.handle
    while True:
        with handle:
            taken = handle.take_message(msg_type, raw)
        if taken is None:
            return
        yield taken


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(stamp, t_ns: int):
    stamp.sec, stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
    return stamp


def declare(node: Node, name: str, default, description: str, lo=None, hi=None,
            choices: Iterable[str] = (), read_only: bool = False, ints: bool = False):
    """Declare a parameter with its description and range (shown by parameter tools)."""
    desc = ParameterDescriptor(description=description, read_only=read_only)
    if choices:
        desc.additional_constraints = 'one of: ' + ', '.join(choices)
    if isinstance(default, bool):
        desc.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        desc.type = ParameterType.PARAMETER_INTEGER
        if lo is not None:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
    elif isinstance(default, float):
        desc.type = ParameterType.PARAMETER_DOUBLE
        if lo is not None and math.isfinite(lo) and math.isfinite(hi):
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
    elif isinstance(default, str):
        desc.type = ParameterType.PARAMETER_STRING
    elif isinstance(default, (list, tuple)) and ints:
        desc.type = ParameterType.PARAMETER_INTEGER_ARRAY
        default = [int(v) for v in default]
    elif isinstance(default, (list, tuple)) and default and all(
            isinstance(v, str) for v in default):
        desc.type = ParameterType.PARAMETER_STRING_ARRAY
    elif isinstance(default, (list, tuple)) and default and all(
            isinstance(v, float) for v in default):
        desc.type = ParameterType.PARAMETER_DOUBLE_ARRAY
        default = [float(v) for v in default]
    return node.declare_parameter(name, default, desc).value


def declare_physics(node: Node, params, names: Iterable[str]) -> dict:
    """Declare physical parameters ``names`` with the schema's unit, range and meaning and the
    values of ``params`` as defaults; returns ``name -> value``."""
    out = {}
    for name in names:
        spec = SPEC_BY_NAME[name]
        value = getattr(params, name)
        text = f'{spec.meaning} [{spec.unit}]'
        if spec.choices:
            out[name] = declare(node, name, spec.choices[int(value)], text, choices=spec.choices)
        else:  # a range only where both bounds are finite (declare)
            out[name] = declare(node, name, float(value), text, spec.lo, spec.hi)
    return out


def validator(check: Callable[[dict], None]):
    """An ``on_set_parameters`` callback: ``check({name: value})`` raises ParameterError to
    refuse the change with its message."""
    def callback(parameters):
        try:
            check({p.name: p.value for p in parameters})
        except (ParameterError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)
    return callback


def publish_status(node: Node, pub, name: str, level, message: str, values: dict,
                   hardware_id: str | None = None) -> None:
    """Publish one ``DiagnosticStatus`` ``name`` on ``/diagnostics`` through ``pub``, stamped
    now: ``level``, ``message``, ``values`` as key-values (``str`` of each) and ``hardware_id``
    (default: the node's full name)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    st = DiagnosticStatus(name=name, message=message,
                          hardware_id=hardware_id or node.get_fully_qualified_name())
    st.level = level
    st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    msg = DiagnosticArray()
    msg.header.stamp = node.get_clock().now().to_msg()
    msg.status = [st]
    pub.publish(msg)


class EventChannel:
    """A node's parameter changes on the latched ``/eha/events`` (``GraphEvent``): each one
    that takes effect, scheduled or live, with the tick it took effect at; :meth:`mirror`
    writes a scheduled change into the node's own parameters (``applying`` is true meanwhile,
    so the node's set-parameters callback can tell it from a live set)."""

    def __init__(self, node: Node, period_ns: int):
        from eha_ros.graph import TOPIC_EVENTS, topic_qos
        from eha_ros.msg import GraphEvent
        self.node = node
        self.period_ns = int(period_ns)
        self.applying = False
        self._cls = GraphEvent
        self.pub = node.create_publisher(GraphEvent, TOPIC_EVENTS, topic_qos(TOPIC_EVENTS))

    def publish(self, stamp_ns: int, source: str, scheduled_s: float, changes: dict,
                node: str | None = None) -> None:
        """Publish that ``changes`` took effect at the tick stamped ``stamp_ns`` (in ``node``:
        default this channel's node)."""
        msg = self._cls()
        ns_to_stamp(msg.header.stamp, stamp_ns)
        msg.header.frame_id = 'jack'
        msg.tick_index = stamp_ns // self.period_ns
        msg.node = node or self.node.get_name()
        msg.source = source
        msg.scheduled_time_s = float(scheduled_s)
        msg.parameter_names = list(changes)
        msg.parameter_values = [float(v) for v in changes.values()]
        self.pub.publish(msg)
        self.node.get_logger().info(
            f'{source} change at t = {stamp_ns * 1e-9:.6g} s (tick {msg.tick_index}): '
            + ', '.join(f'{k}={float(v):g}' for k, v in changes.items()))

    def mirror(self, changes: dict) -> None:
        """Set the node's parameters to a scheduled change it has applied."""
        from rclpy.parameter import Parameter
        self.applying = True
        try:
            self.node.set_parameters([Parameter(k, value=float(v)) for k, v in changes.items()])
        finally:
            self.applying = False


#: Executors a node can spin in (environment variable ``EHA_ROS_EXECUTOR``).
EXECUTORS = ('single', 'events')


def make_executor(context=None):
    """The executor every node spins in: rclpy's C++ ``EventsExecutor`` (experimental in rclpy;
    in one process it runs the lockstep graph about twice as fast as the Python executor,
    ``python bench/graph.py``), or with ``EHA_ROS_EXECUTOR=single`` the
    ``SingleThreadedExecutor``.  Nodes spin it with ``spin_once`` in a loop: its ``spin()``
    does not return on shutdown."""
    import os
    kind = os.environ.get('EHA_ROS_EXECUTOR', 'events') or 'events'
    if kind not in EXECUTORS:
        raise ParameterError(f'EHA_ROS_EXECUTOR={kind!r} must be one of {", ".join(EXECUTORS)}')
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor(context=context)


#: Parameters rclpy itself reads from overrides without a declaration (QoS overrides).
_RCLPY_PREFIXES = ('qos_overrides.',)


def refuse_undeclared(node: Node) -> None:
    """Refuse overrides (``-p``, ``--params-file``, ``parameter_overrides``) of parameters
    ``node`` does not declare: ROS would ignore them, so a misspelt fault would run the
    nominal valve. Call it after every declaration.

    Raises
    ------
    ParameterError
        Naming the first such parameter and the nearest declared names.
    """
    declared = set(node._parameters)
    unknown = sorted(n for n in node._parameter_overrides
                     if n not in declared and not n.startswith(_RCLPY_PREFIXES))
    if unknown:
        raise ParameterError(undeclared_message(node.get_name(), unknown[0], declared))


def declare_realtime(node: Node):
    """Declare the real-time settings of a ticking node (``ros2_control_node``'s names) and
    return them as :class:`eha_ros.realtime.RealtimeSettings`."""
    from eha_ros.realtime import RealtimeSettings
    priority = declare(node, 'thread_priority', 0, 'SCHED_FIFO priority (1-99; 0: normal '
                       'scheduling) of the tick loop thread where the node has one (realtime), '
                       'else of every thread of the process', 0, 99)
    cpus = declare(node, 'cpu_affinity', [-1], 'CPUs to pin the tick loop thread to where the '
                   'node has one (realtime), else every thread of the process ([-1]: no '
                   'pinning)', ints=True)
    lock = declare(node, 'lock_memory', False, 'lock the process memory in RAM (mlockall), '
                   'so no page fault stalls a tick')
    cpus = tuple(int(c) for c in cpus if int(c) >= 0)
    try:
        return RealtimeSettings(thread_priority=int(priority), cpu_affinity=cpus,
                                lock_memory=bool(lock))
    except ValueError as exc:
        raise ParameterError(str(exc)) from None


def declare_loop(node: Node) -> dict:
    """Declare the parameters of a ticking node's realtime loop (:class:`NodeLoop`)."""
    return {
        'executor_priority': declare(
            node, 'executor_priority', 0, 'realtime: SCHED_FIFO priority of the process\'s '
            'threads other than the tick loop (the executor, the middleware; 0: normal '
            'scheduling); thread_priority is the tick loop thread\'s', 0, 99),
        'switch_interval_s': declare(
            node, 'switch_interval_s', 0.0, 'the interpreter\'s GIL switch interval '
            '(sys.setswitchinterval) [s]: how long a thread that wants the GIL waits before '
            'asking its holder for it (0: Python\'s default, 5 ms)', 0.0, 0.1),
        'trace_file': declare(
            node, 'trace_file', '', 'realtime: write a timing trace of every tick here '
            '(.npz, at shutdown; empty: no trace)'),
        'trace_ticks': declare(
            node, 'trace_ticks', 120000, 'realtime: ticks the trace has room for (ticks '
            'beyond are counted as dropped and the trace flagged incomplete)', 1, 10 ** 8),
    }


def refuse_loop_options(options: dict, why: str) -> None:
    """A node without a tick loop (``why``: e.g. 'a lockstep run') refuses the loop's
    parameters that would otherwise be ignored."""
    if options.get('trace_file'):
        raise ParameterError(f'trace_file needs a tick loop, and {why} has none (its ticks have '
                             'no wall-clock schedule to be late on)')
    if options.get('executor_priority'):
        raise ParameterError(f'executor_priority needs a tick loop, and {why} has none: '
                             'thread_priority sets every thread')


#: The tick loop thread's name (``/proc/<pid>/task/<tid>/comm``, ``top -H``, ``ps -L``).
LOOP_THREAD_NAME = 'eha_tick'


class NodeLoop:
    """A ticking node's realtime loop: :class:`eha_ros.tickloop.TickLoop` calling
    ``on_wake(now_ns)`` at the node's period from the graph's start, in a thread of its own.

    The loop thread alone gets ``settings.thread_priority`` (``SCHED_FIFO``) and
    ``settings.cpu_affinity``, and a timer slack of 1 ns (``PR_SET_TIMERSLACK``: a normal thread's
    sleeps end up to 50 us late by default); the other threads of the process get
    ``executor_priority``.  Every wake holds :attr:`lock` (reentrant), which the node's
    executor callbacks that touch the tick's state take too.  With ``trace_file``, a
    :class:`eha_ros.tickloop.TickTrace` records every tick (the node calls :meth:`record`)
    and is written at :meth:`close`.  An exception in a tick sets ``node.fatal`` (the node
    exits 1 naming it)."""

    def __init__(self, node: Node, period_ns: int, on_wake: Callable[[int], None], settings,
                 options: dict):
        from eha_ros.tickloop import TickLoop, TickTrace
        self.node = node
        self.on_wake = on_wake
        self.settings = settings
        self.options = dict(options)
        self.lock = threading.RLock()
        self.trace = (TickTrace(int(options['trace_ticks']), period_ns)
                      if options.get('trace_file') else None)
        self.loop = TickLoop(f'{node.get_name()} tick', period_ns, self._wake,
                             priority=settings.thread_priority, lock=self.lock)
        self.loop.on_thread_start = self._on_thread_start
        self.deadline_ns = None  # the deadline of the current wake
        self._closed = False

    def apply_process_settings(self) -> None:
        """Memory lock for the process, ``executor_priority`` for its threads, the switch
        interval; each refusal is one warning.  Then the first full garbage collection, now
        (:func:`eha_ros.realtime.settle_gc`): at the start it would hold the GIL for over
        100 ms of CPU (a quarter of a second beside two CPU hogs) while the loop's first
        ticks fall due; the start's own collection then only has what start-up added."""
        from eha_ros.realtime import RealtimeSettings, apply_realtime, settle_gc
        settle_gc()
        if self.options.get('switch_interval_s'):
            sys.setswitchinterval(float(self.options['switch_interval_s']))
        rest = RealtimeSettings(thread_priority=int(self.options.get('executor_priority', 0)),
                                lock_memory=self.settings.lock_memory)
        for line in apply_realtime(rest):  # nothing where both are off
            self.node.get_logger().warning(line)

    def _on_thread_start(self) -> None:
        from eha_ros.realtime import apply_realtime, RealtimeSettings
        with suppress(AttributeError, OSError):
            import ctypes
            libc = ctypes.CDLL(None)
            libc.prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK: 1 ns
            libc.prctl(15, ctypes.c_char_p(LOOP_THREAD_NAME.encode()), 0, 0, 0)  # PR_SET_NAME
        pinned = RealtimeSettings(cpu_affinity=self.settings.cpu_affinity)
        for line in apply_realtime(pinned, threads='current') + self.loop.warnings:
            self.node.get_logger().warning(line)
        if self.trace is not None:
            self.trace.bind_thread()

    def start(self, anchor_ns: int, gc=None) -> None:
        """Start the loop: wake k at ``anchor_ns`` + k periods (``time.monotonic_ns``)."""
        if self.trace is not None:
            self.trace.gc = gc
        self.loop.start(anchor_ns)

    def _wake(self, due_ns: int, woke_ns: int, ran_ns: int) -> None:
        self.deadline_ns = due_ns
        tr = self.trace
        if tr is not None:
            tr.begin_wake(woke_ns, ran_ns, self.loop.slept_ns)
        try:
            self.on_wake(ran_ns)
        except Exception as exc:
            self.node.fatal = f'tick loop stopped: {type(exc).__name__}: {exc}'
            raise
        if tr is not None:
            tr.end_wake()

    def record(self, k: int, due_ns: int, work_end_ns: int, published_ns: int) -> None:
        """Tick ``k`` of the current wake, for the trace (nothing without one)."""
        if self.trace is not None:
            self.trace.tick(k, due_ns, work_end_ns, published_ns)

    def close(self) -> None:
        """Stop the loop and write the trace (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.loop.stop()
        if self.trace is not None:
            path = self.options['trace_file']
            self.trace.save(path, self.node.get_name())
            self.trace.close()
            if self.trace.dropped:
                self.node.get_logger().warning(
                    f'timing trace {path}: {self.trace.dropped} ticks beyond its '
                    f'{self.trace.capacity} (trace_ticks) were not recorded')


def node_loop(node: Node, wanted: bool, on_wake: Callable[[int], None], settings,
              options: dict, why: str) -> NodeLoop | None:
    """Where ``wanted``, the node's :class:`NodeLoop` at ``node.period_ns``, ``node.timing``
    counting under its lock; else None, the loop's parameters refused (``why``:
    :func:`refuse_loop_options`)."""
    if not wanted:
        refuse_loop_options(options, why)
        return None
    loop = NodeLoop(node, node.period_ns, on_wake, settings, options)
    node.timing.lock = loop.lock
    return loop


#: What :func:`locked` holds in a node without a tick loop.
_NO_LOOP = nullcontext()


def locked(method):
    """``method`` run holding the lock of the node's tick loop ``rt_loop`` (none without)."""
    @functools.wraps(method)
    def run(self, *args):
        with _NO_LOOP if self.rt_loop is None else self.rt_loop.lock:
            return method(self, *args)
    return run


def take_changes(target, changes: dict, **kinds) -> None:
    """Set each attribute of ``target`` that ``kinds`` names (``name=type``) and ``changes``
    (a set of parameters) holds to its new value, as that type."""
    for name, kind in kinds.items():
        if name in changes:
            setattr(target, name, kind(changes[name]))


def check_choice(name: str, value, choices) -> None:
    """Refuse ``value`` of parameter ``name`` unless it is one of ``choices``."""
    if value not in choices:
        raise ParameterError(f'{name} {value!r} must be one of {", ".join(choices)}')


def apply_realtime_settings(node: Node, settings, loop: NodeLoop | None = None) -> None:
    """Apply ``settings`` to the process (with a tick loop ``loop``, its
    :meth:`NodeLoop.apply_process_settings` instead); each refusal by the OS is one warning
    saying what to change (the node runs on without it)."""
    from eha_ros.realtime import apply_realtime
    if loop is not None:
        loop.apply_process_settings()
        return
    for line in apply_realtime(settings):  # nothing where every setting is off
        node.get_logger().warning(line)


def run_node(factory: Callable[[], Node], args=None) -> int:
    """Init, build the node, spin, shut down cleanly; a bad parameter exits with status 2 and
    one line on stderr."""
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        refuse_undeclared(node)
        executor = make_executor()
        executor.add_node(node)
        while rclpy.ok():  # spin_once: EventsExecutor.spin() ignores shutdown
            executor.spin_once(timeout_sec=0.1)
            fatal = getattr(node, 'fatal', None)
            if fatal:
                print(f'{getattr(factory, "node_name", "eha_ros")}: error: {fatal}',
                      file=sys.stderr)
                return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParameterError, ValueError, ParameterException, OSError) as exc:
        text = ' '.join(str(exc).split())
        print(f'{getattr(factory, "node_name", "eha_ros")}: error: {text}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            getattr(node, 'close', lambda: None)()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0
