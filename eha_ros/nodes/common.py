"""What the nodes share: topic names, QoS, timing modes, parameter declaration and the
``main()`` boilerplate."""

from __future__ import annotations

import math
import sys
from typing import Callable, Iterable

import rclpy
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from eha_ros.physics import ParameterError
from eha_ros.physics.params import SPEC_BY_NAME

from eha_ros.graph import (MODES, TOPIC_CLOCK, TOPIC_COMMAND, TOPIC_DIAGNOSTICS, TOPIC_HEALTH,
                           TOPIC_SERVOVALVE, TOPIC_STATE, graph_qos)

__all__ = ['TOPIC_COMMAND', 'TOPIC_SERVOVALVE', 'TOPIC_STATE', 'TOPIC_HEALTH',
           'TOPIC_DIAGNOSTICS', 'TOPIC_CLOCK', 'QOS', 'MODES', 'declare', 'declare_physics',
           'run_node', 'stamp_to_ns', 'ns_to_stamp']

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


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(stamp, t_ns: int):
    stamp.sec, stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
    return stamp


def declare(node: Node, name: str, default, description: str, lo=None, hi=None,
            choices: Iterable[str] = (), read_only: bool = False):
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
        if spec.choices:
            out[name] = declare(node, name, spec.choices[int(value)],
                                f'{spec.meaning} [{spec.unit}]', choices=spec.choices)
        else:
            lo = spec.lo if math.isfinite(spec.lo) else None
            hi = spec.hi if math.isfinite(spec.hi) else None
            out[name] = declare(node, name, float(value), f'{spec.meaning} [{spec.unit}]',
                                lo if hi is not None else None, hi)
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


def run_node(factory: Callable[[], Node], args=None) -> int:
    """Init, build the node, spin, shut down cleanly; a bad parameter exits with status 2 and
    one line on stderr."""
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        executor = make_executor()
        executor.add_node(node)
        while rclpy.ok():  # spin_once: EventsExecutor.spin() ignores shutdown
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParameterError, ValueError, ParameterException) as exc:
        text = ' '.join(str(exc).split())
        print(f'{getattr(factory, "node_name", "eha_ros")}: error: {text}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0
