"""What a run returned: :class:`GraphResult` (the arrays the collector received and an
account of what arrived and what did not), the ticks missing from it (:func:`missing_ticks`),
the errors that carry a partial result and the one line that describes a fault.  Free of
ROS."""

from __future__ import annotations

import dataclasses

import numpy as np

from eha_ros.graph import STATUS_STOPPED

from .config import GraphConfig, GraphError


class GraphDataLoss(GraphError):
    """A lockstep run ended with messages missing; ``result`` holds what arrived."""

    def __init__(self, message: str, result: 'GraphResult'):
        super().__init__(message)
        self.result = result


class GraphFault(GraphDataLoss):
    """A node died or hung mid-run: the rest were stopped cleanly (the recording closed
    with everything up to the fault); ``result`` holds what arrived, its ``fault`` says which
    node, when and how, and it is not :attr:`~GraphResult.complete`."""


@dataclasses.dataclass
class GraphResult:
    """Arrays of what the collector received, in arrival order (``arrival_s``: the
    middleware's receipt time of states and current commands, on the monotonic clock);
    ``health`` is a list of HealthStatus
    messages; ``events``: every parameter change that took effect (``/eha/events``, as
    dicts).  ``wall_s`` runs from the graph's synchronised start to the last state;
    ``discovery_s`` from the nodes' launch to that start.  In lockstep, ticks the plant
    re-sent (``resent_ticks`` of them) appear once.  ``interrupted``: the run was stopped
    (``stop``) before the plant reached its duration; ``diagnostics``: the last
    ``DiagnosticStatus`` of each name seen on ``/diagnostics`` (``name -> {'level', 'message',
    'values'}``), e.g. each node's timing.

    What arrived and what did not: ``messages`` (per topic, re-sent ticks included), ``lost``
    (per topic, gaps in the publishers' sequence numbers), ``missed_at_start`` (per topic,
    published before the collector's subscription matched: the handshake makes these 0), and
    ``missing`` (lockstep: the ticks, from 0 to the last state, without a state, a position
    command or a current command; realtime: the ticks between the first and the last state
    without a state). ``fault``: a node that died or hung mid-run (``{'node', 'how',
    'wall_s', 'sim_s'}``: how - its exit status, the signal that ended it, or how long it was
    silent; when - wall seconds since the start and the last state's simulated time), else
    None. :attr:`complete` is true when there is no fault and all of these are empty or zero.
    The plant's command watchdog is in the states: ``command_age_ticks`` (a tick that ran on
    a stale command) and ``safe_action`` (``ActuatorState.SAFE_*``)."""

    state: dict
    command: dict
    servovalve: dict
    health: list
    wall_s: float
    config: GraphConfig
    resent_ticks: int = 0
    interrupted: bool = False
    diagnostics: dict = dataclasses.field(default_factory=dict)
    events: list = dataclasses.field(default_factory=list)
    discovery_s: float = 0.0
    messages: dict = dataclasses.field(default_factory=dict)
    lost: dict = dataclasses.field(default_factory=dict)
    missed_at_start: dict = dataclasses.field(default_factory=dict)
    missing: dict = dataclasses.field(default_factory=dict)
    fault: dict | None = None
    trace: dict | None = None

    @property
    def sim_s(self) -> float:
        t = self.state['sim_time_s']
        return float(t[-1]) if t.size else 0.0

    @property
    def complete(self) -> bool:
        """No fault, and nothing lost, missed at the start or missing."""
        return not (self.fault or self.stopped or any(self.lost.values())
                    or any(self.missed_at_start.values())
                    or any(len(v) for v in self.missing.values()))

    @property
    def stopped(self) -> bool:
        """The plant's command watchdog stopped it (its last state: ``STATUS_STOPPED``)."""
        status = self.state.get('status')
        return bool(status is not None and status.size and status[-1] == STATUS_STOPPED)

    @property
    def stale_ticks(self) -> int:
        """States whose tick ran on a stale current command (``command_age_ticks`` > 0)."""
        age = self.state.get('command_age_ticks')
        return int(np.count_nonzero(age)) if age is not None else 0

    def loss_report(self) -> str:
        """One line: the fault and what did not arrive (empty when :attr:`complete`)."""
        parts = [describe_fault(self.fault)] if self.fault else []
        if self.stopped:
            parts.append(f'the plant was stopped by its command watchdog at t = '
                         f'{self.sim_s:.6g} s')
        for what, ticks in self.missing.items():
            if len(ticks):
                parts.append(f'{len(ticks)} ticks without {what} (first: tick {ticks[0]})')
        for name, counts in (('lost', self.lost), ('missed at the start', self.missed_at_start)):
            for topic, n in counts.items():
                if n:
                    parts.append(f'{topic}: {n} {name}')
        return '; '.join(parts)


def missing_ticks(config, state_ns, command_ns, servo_ns) -> dict:
    """Ticks without a state (both modes: between the first and the last state; lockstep:
    from tick 0) and, in lockstep, without a position or a current command."""
    period = round(1e9 / config.rate_hz)
    if not state_ns.size:
        return {}
    have = np.unique(state_ns // period)
    first = 0 if config.mode == 'lockstep' else int(have[0])
    expected = np.arange(first, int(have[-1]) + 1)
    out = {'state': np.setdiff1d(expected, have).tolist()}
    if config.mode == 'lockstep':
        out['command'] = np.setdiff1d(expected, np.unique(command_ns // period)).tolist()
        out['current command'] = np.setdiff1d(expected, np.unique(servo_ns // period)).tolist()
    return out


def describe_fault(fault: dict) -> str:
    """One line: which node failed mid-run, how and when (:attr:`GraphResult.fault`)."""
    return (f"node {fault['node']} failed mid-run: {fault['how']}, {fault['wall_s']:.3f} s "
            f"after the start (last state at t = {fault['sim_s']:.6g} s)")
