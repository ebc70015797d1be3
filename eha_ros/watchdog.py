"""Watchdogs of the loop, free of ROS: the plant's on its current commands and the
controller's on the plant's states.

A servo amplifier that loses its command goes to a defined state and says so; a HIL rig does
the same, because the unit under test must not be driven by a dead controller.  The
:class:`TickWatchdog` counts, tick by tick, how long a node has run on its last input:

* every tick is stepped once, ``fresh`` when an input arrived for it (realtime: since the
  previous tick; lockstep: the answer stamped with that tick);
* ``age`` is the number of ticks since the last fresh one (0: this tick's input is fresh; 1 or
  more: the tick ran on a stale input, which the node flags);
* when ``age`` reaches ``timeout_ticks`` (``ceil(timeout_s / period)``) the watchdog trips and
  its action is in force until a fresh input returns, when it resumes;
* it arms at the first fresh input: before it, the ticks count (the node has no input yet)
  but do not trip.  In realtime the plant's first ticks come in catch-up bursts of tens of
  ticks, run in one callback with no command between them; a controller that never commands
  at all is a start-up failure, which the handshake and the harness report.

In lockstep the timeout counts ticks, which keeps the run deterministic: its ticks are the
simulation clock.  In realtime the node passes ``overdue_s``, the wall time its oldest
unanswered output has waited for an input (the plant: since the first state it published
after the last command arrived), and the timeout counts that: the ticks a late plant catches up
at once, in one callback with no command between them, run on a stale command (their age says
so) but do not make a live controller look dead, and a plant stall does not either.

The plant's actions (:data:`SAFE_ACTIONS`): ``hold`` (the last command stays, flagged),
``null_current`` (the coil current goes to zero, as an amplifier does: the default) and
``stop`` (the plant stops advancing and ends the run).  Codes: :data:`SAFE_CODES`, equal to
``ActuatorState.SAFE_*`` (a test checks it).
"""

from __future__ import annotations

import dataclasses
import math

from eha_ros.physics.params import ParameterError

__all__ = ['SAFE_ACTIONS', 'SAFE_CODES', 'SAFE_NONE', 'TickWatchdog', 'Transition',
           'timeout_ticks']

#: The plant's safe actions when its commands stop (module docstring).
SAFE_ACTIONS = ('hold', 'null_current', 'stop')
#: No safe action in force (``ActuatorState.SAFE_NONE``).
SAFE_NONE = 0
#: Code of each action (``ActuatorState.SAFE_HOLD``, ``SAFE_NULL_CURRENT``, ``SAFE_STOP``).
SAFE_CODES = {'hold': 1, 'null_current': 2, 'stop': 3}


def timeout_ticks(timeout_s: float, period_ns: int) -> int:
    """The whole ticks of ``period_ns`` that ``timeout_s`` [s] spans, rounded up (at least
    one); a timeout that is not a positive finite number is refused."""
    if isinstance(timeout_s, bool) or not (isinstance(timeout_s, (int, float))
                                           and math.isfinite(timeout_s) and timeout_s > 0):
        raise ParameterError(f'watchdog timeout {timeout_s!r} s must be a positive number of '
                             'seconds')
    if not (isinstance(period_ns, int) and period_ns > 0):
        raise ParameterError(f'watchdog period {period_ns!r} ns must be a positive whole number')
    return max(1, -(-round(timeout_s * 1e9) // period_ns))


@dataclasses.dataclass(frozen=True)
class Transition:
    """The watchdog tripped (``kind == 'tripped'``) or resumed (``'resumed'``) at ``tick``
    (the index of the tick stepped), after ``age`` ticks on a stale input."""

    kind: str
    tick: int
    age: int


class TickWatchdog:
    """Ticks since the last fresh input, and the action in force (module docstring).

    Parameters
    ----------
    timeout_s : float
        How long a node may run on its last input [s] before the action.
    period_ns : int
        Tick period [ns].
    action : str
        What follows the timeout: one of :data:`SAFE_ACTIONS`.
    """

    def __init__(self, timeout_s: float, period_ns: int, action: str = 'null_current'):
        if action not in SAFE_ACTIONS:
            raise ParameterError(f'watchdog action {action!r} must be one of '
                                 f'{", ".join(SAFE_ACTIONS)}')
        self.timeout_s = float(timeout_s)
        self.period_ns = int(period_ns)
        self.timeout_ticks = timeout_ticks(timeout_s, period_ns)
        self.action = action
        self.age = 0
        self.tick = -1
        self.armed = False       # a fresh input has arrived once
        self.tripped_at = None   # tick at which the action in force began
        self.stale_ticks = 0     # ticks run on a stale input, in all
        self.trips = 0

    @property
    def in_force(self) -> str | None:
        """The action in force, or None."""
        return self.action if self.tripped_at is not None else None

    @property
    def code(self) -> int:
        """:data:`SAFE_CODES` of the action in force, :data:`SAFE_NONE` when none is."""
        return SAFE_CODES.get(self.in_force, SAFE_NONE)

    def step(self, fresh: bool, overdue_s: float | None = None) -> Transition | None:
        """One tick, ``fresh`` when its input arrived; ``overdue_s`` (realtime): how long the
        oldest unanswered output has waited [s], which the timeout then counts instead of the
        ticks.  Returns the transition it made, if any."""
        self.tick += 1
        if fresh:
            self.armed = True
            age, self.age = self.age, 0
            if self.tripped_at is not None:
                self.tripped_at = None
                return Transition('resumed', self.tick, age)
            return None
        self.age += 1
        self.stale_ticks += 1
        due = (self.age >= self.timeout_ticks if overdue_s is None
               else overdue_s >= self.timeout_s)
        if self.armed and self.tripped_at is None and due:
            self.tripped_at = self.tick
            self.trips += 1
            return Transition('tripped', self.tick, self.age)
        return None
