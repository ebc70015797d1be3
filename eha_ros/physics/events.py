"""Parameter changes during a run (fault injection) on the simulation clock.

An :class:`Event` changes some parameters at a time ``t_s`` [s]; it takes effect at the first
controller tick whose time is at least ``t_s``, before that tick's controller update and plant
steps.  Its text form, for command lines and launch files, is ``'T:name=value,name2=value2'``
(``T`` in seconds, values in the parameter's SI unit)::

    0.1:overlap_supply_m=2.7e-6
    0.25:kp_a_m=20.0,current_limit_a=0.008

Only the parameters in :data:`PLANT_RUNTIME` (wear, degradation, load) and
:data:`CONTROLLER_RUNTIME` (gains) may change; the others are fixed for a run and come from the
physical parameter file.  An :class:`EventSchedule` checks names, times and values before any
run and hands out the events as the clock reaches them.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from numbers import Integral, Real
from typing import Iterable, Mapping

from .params import (SPEC_BY_NAME, ParameterError, PlantParams, params_from_mapping,
                     params_to_dict)

__all__ = ['PLANT_RUNTIME', 'CONTROLLER_RUNTIME', 'SWITCHES', 'EVENT_NODES', 'Event',
           'EventSchedule',
           'parse_event', 'format_event', 'node_events']

#: Plant parameters that may change while it runs: wear, degradation and load.
PLANT_RUNTIME = ('overlap_supply_m', 'overlap_return_m', 'radial_clearance_m',
                 'eccentricity_ratio', 'valve_degradation', 'demagnetisation', 'filter_clogging',
                 'feedback_backlash_m', 'surface_backlash_m', 'jack_static_friction_n',
                 'jack_dynamic_friction_n', 'spool_static_friction_n', 'spool_dynamic_friction_n',
                 'hysteresis_a', 'offset_a', 'leakage_coeff_m3_s_pa', 'external_force_n')

#: Controller parameters that may change while it runs: the PID gains and the current limit.
CONTROLLER_RUNTIME = ('kp_a_m', 'ki_a_m_s', 'kd_a_s_m', 'current_limit_a')

#: Switches an event may set besides the parameters, 0 or 1, with what they do: the node
#: applies them itself (they are no physical parameter).  ``silent``: the controller stops
#: publishing current commands (1: a dropped controller, on the simulation clock) or resumes
#: (0).
SWITCHES = {'silent': 'the controller stops (1) or resumes (0) its current commands'}


def _describe(t_s, changes) -> str:
    return f'{t_s}:' + ','.join(f'{name}={value}' for name, value in changes)


def _problem(t_s, changes) -> str | None:
    """What is wrong with an event's time and changes, or ``None``."""
    if isinstance(t_s, bool) or not isinstance(t_s, Real):
        return f'time {t_s!r} is not a number of seconds'
    if not (math.isfinite(t_s) and t_s >= 0):
        return f'time {t_s} s must be finite and not negative'
    if not changes:
        return 'changes no parameter'
    names = [name for name, _ in changes]
    for name, value in changes:
        if not isinstance(name, str) or not name:
            return f'parameter name {name!r} is not a name'
        if isinstance(value, bool) or not isinstance(value, Real):
            return f'value of {name} = {value!r} is not a number'
        if not math.isfinite(value):
            return f'value of {name} = {value} is not finite'
        if names.count(name) > 1:
            return f'parameter {name} is changed twice'
    return None


@dataclasses.dataclass(frozen=True)
class Event:
    """Parameters ``changes`` (``(name, value)`` pairs, SI units) taking effect at ``t_s`` [s].

    ``changes`` may be given as a mapping; it is kept as a tuple of pairs in the given order,
    so events are hashable and compare by value.
    """

    t_s: float
    changes: tuple

    def __post_init__(self):
        changes = self.changes
        try:
            pairs = tuple((n, v) for n, v in (changes.items() if isinstance(changes, Mapping)
                                              else changes))
        except (TypeError, ValueError):
            raise ParameterError(f'event at {self.t_s!r} s: changes {changes!r} are not '
                                 '(name, value) pairs') from None
        problem = _problem(self.t_s, pairs)
        if problem:
            raise ParameterError(f'event {_describe(self.t_s, pairs)!r}: {problem}')
        object.__setattr__(self, 't_s', float(self.t_s))
        object.__setattr__(self, 'changes', tuple((n, float(v)) for n, v in pairs))

    def as_dict(self) -> dict:
        """``name -> value`` of the changes."""
        return dict(self.changes)


def format_event(ev: Event) -> str:
    """Text form ``'T:name=value,...'`` of an event; :func:`parse_event` reads it back
    exactly (floats written with ``repr``)."""
    return f'{ev.t_s!r}:' + ','.join(f'{name}={value!r}' for name, value in ev.changes)


def parse_event(text: str) -> Event:
    """Read an event from ``'T:name=value'`` or ``'T:name=value,name2=value2'`` (``T`` in
    seconds; whitespace around the parts is ignored).

    Raises
    ------
    ParameterError
        One line naming the text and what is wrong with it.
    """
    def bad(what):
        return ParameterError(f'event {text!r}: {what} (expected T:name=value,...)')

    head, colon, body = str(text).partition(':')
    if not colon:
        raise bad('no colon after the time')
    try:
        t_s = float(head)
    except ValueError:
        raise bad(f'time {head.strip()!r} is not a number') from None
    changes = []
    for item in body.split(','):
        name, eq, value = item.partition('=')
        if not eq:
            raise bad(f'{item.strip()!r} is not name=value')
        try:
            changes.append((name.strip(), float(value)))
        except ValueError:
            raise bad(f'value {value.strip()!r} of {name.strip()} is not a number') from None
    problem = _problem(t_s, changes)
    if problem:
        raise bad(problem)
    return Event(t_s, tuple(changes))


def _refusal(name: str, allowed: tuple) -> str:
    """Why ``name`` may not change in a schedule that allows ``allowed``."""
    if name in SPEC_BY_NAME and name not in PLANT_RUNTIME + CONTROLLER_RUNTIME:
        return (f'parameter {name} is fixed for a run: set it in the physical parameter file '
                '(config/eha_params.yaml) instead')
    near = difflib.get_close_matches(name, allowed, n=3)
    hint = f'; nearest allowed: {", ".join(near)}' if near else ''
    if name in SPEC_BY_NAME:
        return f'parameter {name} may not change in this schedule{hint}'
    return f'unknown parameter {name}{hint}'


class EventSchedule:
    """Parameter changes in time order, checked up front and handed out as the clock
    reaches them.

    Parameters
    ----------
    events : iterable
        :class:`Event` objects, ``(t_s, {name: value})`` pairs or text forms
        (:func:`parse_event`).  Kept sorted by time, stably: events at equal times keep their
        given order, so for the same parameter the later one wins.
    allowed : tuple of str
        Names that may change (default: :data:`PLANT_RUNTIME` + :data:`CONTROLLER_RUNTIME`).
    period_ns : int, optional
        Controller tick period [ns], for :meth:`tick_of`.

    Iteration and ``len`` cover every event; :attr:`pending` those :meth:`due` has not yet
    returned.
    """

    def __init__(self, events: Iterable = (),
                 allowed: tuple = PLANT_RUNTIME + CONTROLLER_RUNTIME,
                 period_ns: int | None = None):
        self.allowed = tuple(allowed)
        bad = [n for n in self.allowed if n not in SPEC_BY_NAME and n not in SWITCHES]
        if bad:
            raise ParameterError(f'allowed names {", ".join(bad)} are not parameters')
        if period_ns is not None and not (isinstance(period_ns, Integral) and period_ns >= 1):
            raise ParameterError(f'period_ns = {period_ns!r} must be a positive whole number '
                                 'of nanoseconds')
        self.period_ns = None if period_ns is None else int(period_ns)
        evs = []
        for item in events:
            if isinstance(item, str):
                item = parse_event(item)
            elif not isinstance(item, Event):
                try:
                    t_s, changes = item
                except (TypeError, ValueError):
                    raise ParameterError(f'event {item!r} is not an Event, a (t_s, {{name: '
                                         'value}}) pair or a text T:name=value') from None
                item = Event(t_s, changes)
            for name, value in item.changes:
                if name not in self.allowed:
                    raise ParameterError(f'event {format_event(item)!r}: '
                                         f'{_refusal(name, self.allowed)}')
                if name in SWITCHES and value not in (0.0, 1.0):
                    raise ParameterError(f'event {format_event(item)!r}: switch {name} must '
                                         'be 0 or 1')
            evs.append(item)
        self._events = tuple(sorted(evs, key=lambda e: e.t_s))
        self._next = 0

    def __len__(self) -> int:
        return len(self._events)

    def __iter__(self):
        return iter(self._events)

    def __repr__(self) -> str:
        return f'EventSchedule({[format_event(e) for e in self._events]!r})'

    @property
    def pending(self) -> tuple:
        """Events not yet returned by :meth:`due`, in time order."""
        return self._events[self._next:]

    def validate(self, params: PlantParams) -> list[PlantParams]:
        """Apply every event in turn to ``params``, refusing a non-physical result.

        Returns
        -------
        list of PlantParams
            The parameters in effect after each event, in the schedule's order.

        Raises
        ------
        ParameterError
            Naming the first event whose changes make the parameters non-physical.
        """
        out = []
        values = params_to_dict(params)
        for ev in self._events:
            values.update((n, v) for n, v in ev.changes if n not in SWITCHES)
            out.append(params_from_mapping(values, source=f'event {format_event(ev)!r}'))
        return out

    def due(self, time_ns: int) -> list[Event]:
        """Remove and return the pending events with ``round(t_s 1e9) <= time_ns`` [ns]: an
        event takes effect at the first tick whose time is at least its own."""
        start = self._next
        while (self._next < len(self._events)
               and round(self._events[self._next].t_s * 1e9) <= time_ns):
            self._next += 1
        return list(self._events[start:self._next])

    def tick_of(self, ev: Event) -> int:
        """Index of the tick at which ``ev`` takes effect, ``ceil(T_ns / period_ns)``."""
        if self.period_ns is None:
            raise ParameterError('the schedule has no period_ns to count ticks with')
        return -(-round(ev.t_s * 1e9) // self.period_ns)


#: The nodes that take events, and the parameters each may change while running.
EVENT_NODES = {'servovalve_plant': PLANT_RUNTIME,
               'controller': CONTROLLER_RUNTIME + ('silent',)}


def node_events(where: str, events) -> tuple:
    """Events addressed to nodes - ``{t_s, node, set: {name: value}}`` mappings (a scenario's
    YAML) or ``(t_s, node, {name: value})`` tuples - checked: the node takes events
    (:data:`EVENT_NODES`), every name is one it may change, times and values are numbers.
    Returns ``((t_s, node, ((name, value), ...)), ...)``.

    Raises
    ------
    ParameterError
        One line starting with ``where``, naming the event and what is wrong.
    """
    out = []
    for item in events or ():
        if isinstance(item, Mapping):
            if set(item) != {'t_s', 'node', 'set'}:
                raise ParameterError(f'{where}: each event needs t_s, node and set (got '
                                     f'{", ".join(sorted(map(str, item)))})')
            item = (item['t_s'], item['node'], item['set'])
        try:
            t_s, node, changes = item
            changes = dict(changes)
        except (TypeError, ValueError):
            raise ParameterError(f'{where}: event {item!r} is not (t_s, node, '
                                 '{name: value})') from None
        if node not in EVENT_NODES:
            raise ParameterError(f'{where}: event at {t_s} s: node {node!r} takes no events '
                                 f'(nodes with events: {", ".join(EVENT_NODES)})')
        try:
            ev, = EventSchedule([(t_s, changes)], allowed=EVENT_NODES[node])
        except ParameterError as exc:
            raise ParameterError(f'{where}: {node}: {exc}') from None
        out.append((ev.t_s, str(node), ev.changes))
    return tuple(out)
