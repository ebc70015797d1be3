"""The node graph's vocabulary, defined once: topic names, types, rates and QoS, the plant's
fluid-block models, the plant status and health level codes, and the reference's scenario list.

Nodes, recording, tools and bench scripts import these names from here. Importing this module
needs neither ``rclpy`` nor the generated messages; :func:`graph_qos` and
:func:`message_class` import them when called. The status and level codes equal the constants
of the generated messages (``ActuatorState.STATUS_*``, ``HealthStatus.LEVEL_*``; a test checks
it), so code that has no message classes (offline tools, bench) can use them.

=============================  =====================================  ==========
Topic                          Type                                   Rate
=============================  =====================================  ==========
``/eha/command``               ``eha_ros/msg/ActuatorCommand``        1 kHz
``/eha/servovalve_command``    ``eha_ros/msg/ServovalveCommand``      1 kHz
``/eha/state``                 ``eha_ros/msg/ActuatorState``          1 kHz
``/eha/health``                ``eha_ros/msg/HealthStatus``           1-10 Hz
``/diagnostics``               ``diagnostic_msgs/msg/DiagnosticArray`` 1 kHz
``/clock``                     ``rosgraph_msgs/msg/Clock``            1 kHz
``/eha/events``                ``eha_ros/msg/GraphEvent``             per event
=============================  =====================================  ==========

Every topic but ``/eha/events`` is reliable, keeps the last 1000 samples and is volatile.
``/eha/events`` (each parameter change that took effect, with its tick) is latched
(transient local): a reader that joins late still receives every event.

Besides these, ``/eha/handshake`` (``diagnostic_msgs/msg/DiagnosticStatus``, latched) carries
the start-up handshake (:mod:`eha_ros.nodes.handshake`); it is the graph's control channel,
not recorded.  The depth is what a
subscriber outside the loop (the recorder, the health monitor, a test's collector) may fall
behind without losing a sample: 1 s at 1 kHz.  In lockstep the loop runs as fast as the
controller answers, so a slower reader falls behind by however long it is slower.
"""

from __future__ import annotations

import importlib
from typing import Dict, Iterable, Optional

__all__ = ['undeclared_message',
           'NAMESPACE', 'TOPIC_COMMAND', 'TOPIC_SERVOVALVE', 'TOPIC_STATE', 'TOPIC_HEALTH',
           'TOPIC_DIAGNOSTICS', 'TOPIC_CLOCK', 'TOPIC_EVENTS', 'TOPIC_HANDSHAKE', 'TOPICS',
           'LATCHED_TOPICS', 'LATCHED_DEPTH', 'is_latched', 'topic_qos', 'RATES_HZ', 'QOS_DEPTH',
           'QOS_RELIABILITY', 'QOS_DURABILITY', 'QOS_HISTORY', 'graph_qos', 'topics_in',
           'normalize_type', 'message_class', 'MODES', 'MODELS', 'REFERENCE_MODELS',
           'DYNAMIC_MODELS', 'ALGEBRAIC_MODELS',
           'STATUS_OK', 'STATUS_END_STOP', 'STATUS_CAVITATION', 'STATUS_DIVERGED',
           'STATUS_VALVE_TEST', 'STATUS_PREFLIGHT', 'STATUS_STOPPED', 'STATUS_NAMES', 'LEVEL_OK',
           'LEVEL_WARN', 'LEVEL_ERROR', 'LEVEL_CANNOT_ASSESS', 'LEVEL_NAMES',
           'REFERENCE_SCENARIOS', 'NODES', 'TIMING_SUFFIX', 'RUN_ENDED']

#: Default namespace of the actuator's own topics (``/diagnostics`` and ``/clock`` are global).
NAMESPACE = '/eha'

TOPIC_COMMAND = '/eha/command'
TOPIC_SERVOVALVE = '/eha/servovalve_command'
TOPIC_STATE = '/eha/state'
TOPIC_HEALTH = '/eha/health'
TOPIC_DIAGNOSTICS = '/diagnostics'
TOPIC_CLOCK = '/clock'
TOPIC_EVENTS = '/eha/events'
TOPIC_HANDSHAKE = '/eha/handshake'

#: Every graph topic and its type, ``pkg/msg/Type``.
TOPICS: Dict[str, str] = {
    TOPIC_COMMAND: 'eha_ros/msg/ActuatorCommand',
    TOPIC_SERVOVALVE: 'eha_ros/msg/ServovalveCommand',
    TOPIC_STATE: 'eha_ros/msg/ActuatorState',
    TOPIC_HEALTH: 'eha_ros/msg/HealthStatus',
    TOPIC_DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    TOPIC_CLOCK: 'rosgraph_msgs/msg/Clock',
    TOPIC_EVENTS: 'eha_ros/msg/GraphEvent',
}

#: Latched topics (transient local): a late reader receives what was published before it.
LATCHED_TOPICS = frozenset((TOPIC_EVENTS, TOPIC_HANDSHAKE))

#: Samples a latched topic keeps for late readers (per publisher).
LATCHED_DEPTH = 1000

#: Nominal publication rate of every topic, Hz (health: the fastest it is published).
RATES_HZ: Dict[str, float] = {
    TOPIC_COMMAND: 1000.0,
    TOPIC_SERVOVALVE: 1000.0,
    TOPIC_STATE: 1000.0,
    TOPIC_HEALTH: 10.0,
    TOPIC_DIAGNOSTICS: 1000.0,
    TOPIC_CLOCK: 1000.0,
    TOPIC_EVENTS: 0.0,
}

#: The graph's nodes, by their ROS names (and console scripts).
NODES = ('command_generator', 'controller', 'servovalve_plant', 'health_monitor')

#: Timing modes: wall-clock timers (a rig), or the plant paces everything through /clock.
MODES = ('realtime', 'lockstep')

#: Fluid-dynamic blocks the plant can run: the high-fidelity model and the shipped surrogates.
MODELS = ('hf', 'lut', 'ga', 'nn', 'nn2', 'dlut', 'dnn', 'dga')

#: The dynamic surrogates (metering-edge flows learned, chambers and jack physical): the
#: recommended in-loop surrogates.
DYNAMIC_MODELS = ('dlut', 'dnn', 'dga')

#: The reference's algebraic surrogates P12(XS, Q[, wear]), kept as its reproduction.
ALGEBRAIC_MODELS = ('lut', 'ga', 'nn', 'nn2')

#: The reference's four models of its comparison (section 6.3), in its order.
REFERENCE_MODELS = ('hf', 'ga', 'nn', 'lut')

#: The reference's test campaign (section 6.3): named scenarios of ``config/scenarios.yaml``.
REFERENCE_SCENARIOS = ('step_0p1', 'step_0p01', 'ramp_0p1', 'ramp_0p01', 'sine_0p1_5pi',
                       'sine_0p1_10pi', 'sine_0p01_5pi', 'sine_0p01_10pi', 'sine_0p01_2pi')

#: Plant status codes (``ActuatorState.status``, the message's ``STATUS_*`` constants).
STATUS_OK = 0
STATUS_END_STOP = 1
STATUS_CAVITATION = 2
STATUS_DIVERGED = 3
STATUS_VALVE_TEST = 4
STATUS_PREFLIGHT = 5
STATUS_STOPPED = 6
STATUS_NAMES = ('OK', 'END_STOP', 'CAVITATION', 'DIVERGED', 'VALVE_TEST', 'PREFLIGHT',
                'STOPPED')

#: The ``ActuatorState`` fields that carry the plant's state (its ``snapshot()``'s names).
SNAPSHOT_FIELDS = ('jack_position_m', 'jack_position_measured_m', 'jack_velocity_m_s',
                   'spool_position_m', 'flapper_position_m', 'p1_pa', 'p2_pa', 'p12_pa',
                   'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n')

#: Name of a node's timing status on ``/diagnostics``: ``'<node>: timing'`` (the health
#: monitor's statuses have other names).
TIMING_SUFFIX = ': timing'
#: The same for the plant's command watchdog (``'<node>: command watchdog'``).
WATCHDOG_SUFFIX = ': command watchdog'
#: The key of a node's last timing report, sent when its run ends (value 1: every timing
#: value is a number).
RUN_ENDED = 'Run ended'

#: Health levels (``HealthStatus.level``, the message's ``LEVEL_*`` constants).
LEVEL_OK = 0
LEVEL_WARN = 1
LEVEL_ERROR = 2
LEVEL_CANNOT_ASSESS = 3
LEVEL_NAMES = ('OK', 'WARN', 'ERROR', 'CANNOT_ASSESS')

#: QoS of every graph topic (names as ``rmw_qos_*_policy_to_str`` spells them).
QOS_HISTORY = 'keep_last'
QOS_DEPTH = 1000
QOS_RELIABILITY = 'reliable'
QOS_DURABILITY = 'volatile'


def graph_qos(depth: Optional[int] = None):
    """The graph's QoS as an ``rclpy.qos.QoSProfile`` (``depth`` overrides the history depth)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST,
                      depth=QOS_DEPTH if depth is None else int(depth),
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def is_latched(topic: str) -> bool:
    """Whether graph topic ``topic`` (any namespace) is one of :data:`LATCHED_TOPICS`."""
    return topic.rsplit('/', 1)[-1] in {t.rsplit('/', 1)[-1] for t in LATCHED_TOPICS}


def topic_qos(topic: str, depth: Optional[int] = None):
    """The QoS of graph topic ``topic`` (any namespace): latched for :data:`LATCHED_TOPICS`,
    else :func:`graph_qos`."""
    from rclpy.qos import DurabilityPolicy

    qos = graph_qos(depth)
    if is_latched(topic):
        qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        if depth is None:
            qos.depth = LATCHED_DEPTH
    return qos


def topics_in(namespace: str = NAMESPACE) -> Dict[str, str]:
    """:data:`TOPICS` with the actuator's topics moved from ``/eha`` to ``namespace``.

    ``/diagnostics`` and ``/clock`` are global and keep their names.
    """
    namespace = '/' + namespace.strip('/') if namespace.strip('/') else ''
    return {(namespace + name[len(NAMESPACE):] if name.startswith(NAMESPACE + '/') else name):
            type_name for name, type_name in TOPICS.items()}


def normalize_type(type_name: str) -> str:
    """``pkg/Type`` or ``pkg/msg/Type`` -> ``pkg/msg/Type``.

    Raises
    ------
    ValueError
        If ``type_name`` is not of either form.
    """
    parts = type_name.strip().split('/')
    if len(parts) == 2 and all(parts):
        return f'{parts[0]}/msg/{parts[1]}'
    if len(parts) == 3 and all(parts) and parts[1] == 'msg':
        return '/'.join(parts)
    raise ValueError(f'not a message type name: {type_name!r} (expected pkg/msg/Type)')


def message_class(type_name: str) -> type:
    """Import the message class of ``pkg/msg/Type`` (or ``pkg/Type``).

    Raises
    ------
    ValueError
        If the type is not installed.
    """
    pkg, _, name = normalize_type(type_name).split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f'message type {type_name} is not installed ({exc})') from None


def undeclared_message(node_name: str, name: str, declared: Iterable[str]) -> str:
    """One line refusing parameter ``name`` of ``node_name``: the nearest declared names, or
    for a physical parameter that is not a node parameter, where it is set instead."""
    import difflib

    from eha_ros.physics.params import SPEC_BY_NAME
    declared = sorted(declared)
    text = f'{node_name} has no parameter {name!r}'
    if name in SPEC_BY_NAME:
        return (f'{text}: {name} is a physical parameter fixed for a run; set it in the '
                f'physical parameter file (config/eha_params.yaml form) given as '
                f'{node_name}.params_file')
    near = difflib.get_close_matches(name, declared, n=3, cutoff=0.6)
    return text + (f' (did you mean {", ".join(near)}?)' if near else
                   f' (it declares {", ".join(declared)})')
