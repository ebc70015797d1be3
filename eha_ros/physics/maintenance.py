"""Diagnostic valve test: the characteristic-map sweep run on the plant, tick by tick.

Two procedures (:data:`VALVE_TEST_PROCEDURES`):

``reference``
    The reference's map procedure (section 5.1), reproduced as it is: the spool held at each
    of the 133 positions of :func:`.maps.spool_grid`, the load flow imposed, both chamber
    pressures from zero, P12 read after ``MAP_HOLD_S`` = 1e-2 s.  The diagnostic network
    recognises wear from these curves.  The transient has not settled near null, so the bulk
    modulus (entrained air) enters its curves directly.
``settled``
    A hold long enough to settle: ``SETTLED_POINTS`` = 41 spool positions per curve, each
    held ``SETTLED_HOLD_S`` = 0.1 s, at ``SETTLED_FLOWS_M3_S`` (blocked ports, then three
    flows); 16.4 s in all.  The spool is stepped as on a bench: each point's transient starts
    from the chamber pressures the point before left (:func:`.maps.stepped_trace`; the first
    point of a curve from zero).  The pressures at the end of the hold are then the steady
    map (:func:`.maps.steady_map`) within 2 kPa + 0.1 % for every valve of the tolerances, the
    map the valve model is fitted to, which the bulk modulus does not enter
    (:mod:`eha_ros.health.valve_fit`).  From zero, the near-null points of a tight valve with
    a leaky piston and a high critical flow number ended up to 0.6 MPa short after the hold,
    drifting too slowly for the settle check to see.
A rig reproduces it as a maintenance test - the jack ports switched to a flow-controlled test
circuit, the spool positioned point by point - and the plant does the same when asked: during
the test the jack stays where it is (clamped) and, at every tick, the plant reports the
held spool position, the imposed flow and the chamber pressures of that point's transient at
the tick's time.  The sample at the end of each hold is the map's value (the reference) or
the stepped curve's (settled), bit for bit (same kernel, same step).

Order: for each flow in turn, the spool positions from -stroke to +stroke.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .commands import VALVE_TEST_PROCEDURES, get_scenario
from .maps import spool_grid, stepped_trace, transient_trace
from .params import ParameterError, PlantParams

__all__ = ['MAP_POINTS', 'MAP_HOLD_S', 'SETTLED_POINTS', 'SETTLED_HOLD_S', 'SETTLED_FLOWS_M3_S',
           'VALVE_TEST_PROCEDURES', 'valve_test_schedule', 'ValveTest', 'ValveTestSample',
           'PREFLIGHT_PROFILE',
           'PREFLIGHT_S', 'PREFLIGHT_TICK_S', 'PREFLIGHT_SIGNALS', 'PreflightCheck',
           'preflight_command', 'run_preflight']

#: Spool positions of a curve (the databases' grid).
MAP_POINTS = 133
#: Hold of every point [s]: the reference's map transient.
MAP_HOLD_S = 1e-2
#: Spool positions of a settled curve: the sinh grid of :func:`.maps.spool_grid`, 2.2 um apart
#: at null, where clearance and overlap show.
SETTLED_POINTS = 41
#: Hold of every settled point [s]: stepped from its neighbour's pressures, every point of
#: the tightest valve of the tolerances ends within 2 kPa + 0.1 % of its steady value
#: (``test_valve_fit``); from zero it took seconds near null.
SETTLED_HOLD_S = 0.1
#: Flows of the settled test [m^3/s]: blocked ports (the pressure gain, the clearance and the
#: piston leakage), a small flow (the null region again, at another balance), then half and
#: the whole map flow (the metering edges' discharge, so Khsv).
SETTLED_FLOWS_M3_S = (0.0, 5e-6, 3e-5, 6e-5)


def valve_test_schedule(procedure: str, flows_m3_s=None) -> dict:
    """``{'flows_m3_s', 'hold_s', 'n_points'}`` of a procedure; ``flows_m3_s`` replaces its
    default flows (the reference's: those of the ``valve_test`` scenario)."""
    if procedure == 'settled':
        flows = SETTLED_FLOWS_M3_S if flows_m3_s is None else flows_m3_s
        return {'flows_m3_s': tuple(float(q) for q in flows), 'hold_s': SETTLED_HOLD_S,
                'n_points': SETTLED_POINTS}
    if procedure == 'reference':
        if flows_m3_s is None:
            flows_m3_s = get_scenario('valve_test').valve_test_flows_m3_s
        return {'flows_m3_s': tuple(float(q) for q in flows_m3_s), 'hold_s': MAP_HOLD_S,
                'n_points': MAP_POINTS}
    raise ParameterError(f'valve test procedure {procedure!r} must be one of '
                         f'{", ".join(VALVE_TEST_PROCEDURES)}')


@dataclasses.dataclass(frozen=True)
class ValveTestSample:
    """What the plant reports at one tick of the test."""

    spool_position_m: float
    load_flow_m3_s: float
    p1_pa: float
    p2_pa: float
    point: int          # index of the spool position in the grid
    curve: int          # index of the flow
    point_end: bool     # this sample ends the point's hold: P12 is the map's value


class ValveTest:
    """The tick schedule of a valve test.

    Parameters
    ----------
    flows_m3_s : sequence of float
        Imposed load flows [m^3/s], one curve each.
    tick_ns : int
        Tick period [ns]; the hold must be a whole number of ticks.
    dt_s : float
        Integration step of the map transient [s] (the plant's).
    hold_s : float
        Hold of each point [s].
    n_points : int
        Spool positions per curve.
    procedure : str
        ``'reference'`` or ``'settled'`` (:data:`VALVE_TEST_PROCEDURES`), reported with the
        samples.
    """

    def __init__(self, flows_m3_s, tick_ns: int, dt_s: float, hold_s: float = MAP_HOLD_S,
                 n_points: int = MAP_POINTS, procedure: str = 'reference'):
        if procedure not in VALVE_TEST_PROCEDURES:
            raise ParameterError(f'valve test procedure {procedure!r} must be one of '
                                 f'{", ".join(VALVE_TEST_PROCEDURES)}')
        self.procedure = procedure
        flows = np.asarray(flows_m3_s, dtype=float).ravel()
        if flows.size == 0:
            raise ParameterError('valve test: valve_test_flows_m3_s needs at least one flow')
        if not np.all(np.isfinite(flows)):
            raise ParameterError(f'valve test: valve_test_flows_m3_s = {flows.tolist()} must be '
                                 'finite')
        hold_ns = int(round(hold_s * 1e9))
        if tick_ns <= 0 or hold_ns <= 0 or hold_ns % tick_ns:
            raise ParameterError(f'valve test: the hold of {hold_s:g} s must be a whole number '
                                 f'of ticks of {tick_ns} ns')
        self.flows_m3_s = flows
        self.tick_ns = int(tick_ns)
        self.dt_s = float(dt_s)
        self.n_points = int(n_points)
        steps = self.tick_ns * 1e-9 / self.dt_s
        if abs(steps - round(steps)) > 1e-9 * steps:
            raise ParameterError(f'valve test: the tick of {tick_ns} ns must be a whole number '
                                 f'of steps of {dt_s:g} s')
        self.ticks_per_point = hold_ns // self.tick_ns
        self.n_ticks = flows.size * self.n_points * self.ticks_per_point
        self._trace_key, self._trace = None, None
        self._ends = {}   # (curve, point): chamber pressures at the end of its hold [Pa]

    @property
    def duration_s(self) -> float:
        return self.n_ticks * self.tick_ns * 1e-9

    def grid(self, params: PlantParams) -> np.ndarray:
        return spool_grid(self.n_points, params.spool_stroke_m)

    @classmethod
    def of(cls, procedure: str, tick_ns: int, dt_s: float, flows_m3_s=None) -> 'ValveTest':
        """The test of ``procedure`` (:func:`valve_test_schedule`)."""
        s = valve_test_schedule(procedure, flows_m3_s)
        return cls(s['flows_m3_s'], tick_ns, dt_s, s['hold_s'], s['n_points'], procedure)

    def _start(self, curve: int, point: int, params: PlantParams, steps: int):
        """Where a point's transient starts: zero (the reference's map, and the first point
        of a settled curve), else, for the settled procedure, where the point before ended
        (as a bench steps the spool: :func:`.maps.stepped_trace`).  A point reached without
        its predecessor (a test entered midway) replays the curve up to it."""
        if self.procedure != 'settled' or point == 0:
            return None
        end = self._ends.get((curve, point - 1))
        if end is None:
            xs = self.grid(params)[:point]
            p1, p2 = stepped_trace(xs, float(self.flows_m3_s[curve]), self.ticks_per_point,
                                   steps, params, self.dt_s, first=self.ticks_per_point - 1)
            end = (float(p1[-1, -1]), float(p2[-1, -1]))
        return end

    def sample(self, k: int, params: PlantParams) -> ValveTestSample:
        """The state at the end of tick ``k`` (1 .. ``n_ticks``) with the wear of ``params``."""
        if not 1 <= k <= self.n_ticks:
            raise IndexError(f'valve test tick {k} outside 1..{self.n_ticks}')
        point_global, m = divmod(k - 1, self.ticks_per_point)
        curve, point = divmod(point_global, self.n_points)
        xs = float(self.grid(params)[point])
        q = float(self.flows_m3_s[curve])
        # the point's whole transient once, at its first tick or when the parameters change
        # (another object: the plant replaces its parameters on every change)
        if self._trace_key is None or self._trace_key[0] != point_global or \
                self._trace_key[1] is not params:
            steps = int(round(self.tick_ns * 1e-9 / self.dt_s))
            if point_global == 0:   # a test begins: no pressures carried from another run
                self._ends.clear()
            self._trace = transient_trace(xs, q, self.ticks_per_point, steps, params,
                                          self.dt_s, start_pa=self._start(
                                              curve, point, params, steps))
            self._trace_key = (point_global, params)
            self._ends[(curve, point)] = (float(self._trace[0][-1]),
                                          float(self._trace[1][-1]))
        p1 = float(self._trace[0][m])
        p2 = float(self._trace[1][m])
        if not (math.isfinite(p1) and math.isfinite(p2)):  # transient_map raises first
            raise FloatingPointError('valve test transient is not finite')
        return ValveTestSample(xs, q, p1, p2, point, curve, m == self.ticks_per_point - 1)


# --- pre-flight check ---------------------------------------------------------------------

#: Segments of the pre-flight check's coil-current command: ``(start_s, end_s, kind, a, b)``
#: with currents as fractions of the rated current ``current_limit_a``; ``step``: ``a`` held;
#: ``sine``: ``a sin(2 pi (t - start) / b)``.  What each part makes observable:
#:
#: * 0 A holds (start, between parts, end): the coil current reads the torque motor's offset
#:   (``offset_a``), the spool's drift from null shows it too;
#: * current steps of 30 % and 10 % rated, both signs: the spool's steady position per
#:   current is the torque-motor gain (``demagnetisation``), its first milliseconds the
#:   first-stage drive (``filter_clogging`` lowers the nozzle pressure gain and slows it);
#:   the jack breaks away when P12 AJ exceeds its seals' breakaway (``jack_static_friction_n``);
#: * a 20 % sine at 3.3 Hz and a 5 % sine at 4 Hz: the flapper's deflection while the spool
#:   slides is the force the spool needs (viscous drag, scaled by the first stage's gain, and
#:   ``spool_static_friction_n`` at every reversal, where the spool sticks); the jack reverses
#:   through its friction at every half period.
PREFLIGHT_PROFILE = (
    (0.00, 0.05, 'step', 0.0, 0.0),
    (0.05, 0.10, 'step', 0.3, 0.0),
    (0.10, 0.15, 'step', -0.3, 0.0),
    (0.15, 0.20, 'step', 0.1, 0.0),
    (0.20, 0.25, 'step', -0.1, 0.0),
    (0.25, 0.30, 'step', 0.0, 0.0),
    (0.30, 0.90, 'sine', 0.2, 0.3),
    (0.90, 1.15, 'sine', 0.05, 0.25),
    (1.15, 1.20, 'step', 0.0, 0.0),
)
#: Duration of the pre-flight check [s].
PREFLIGHT_S = 1.2
#: Tick [s] the pre-flight records are defined at (the graph's 1 kHz): the pre-flight network
#: reads one value per tick of this length.
PREFLIGHT_TICK_S = 1e-3
#: Signals the plant reports at every tick of the check (the ActuatorState fields).
PREFLIGHT_SIGNALS = ('coil_current_a', 'spool_position_m', 'flapper_position_m', 'p12_pa',
                     'jack_position_m', 'jack_velocity_m_s')


class PreflightCheck:
    """Tick schedule of the pre-flight check: the jack free, the controller bypassed, the coil
    current commanded open loop along :data:`PREFLIGHT_PROFILE` from the actuator at rest.

    Parameters
    ----------
    tick_ns : int
        Tick period [ns]; the check lasts :data:`PREFLIGHT_S` and every segment boundary must
        fall on a tick.
    current_limit_a : float
        Rated current [A] the profile's fractions refer to.
    """

    def __init__(self, tick_ns: int, current_limit_a: float):
        if tick_ns <= 0:
            raise ParameterError('pre-flight check: the tick period must be positive')
        n = PREFLIGHT_S * 1e9 / tick_ns
        if abs(n - round(n)) > 1e-9 or any(
                abs(b * 1e9 / tick_ns - round(b * 1e9 / tick_ns)) > 1e-9
                for _, b, *_ in PREFLIGHT_PROFILE):
            raise ParameterError(f'pre-flight check: its segments must be whole numbers of '
                                 f'ticks of {tick_ns} ns')
        self.tick_ns = int(tick_ns)
        self.n_ticks = int(round(n))
        self.current_limit_a = float(current_limit_a)
        self.command_a = preflight_command(self.n_ticks, self.tick_ns * 1e-9,
                                           self.current_limit_a)

    @property
    def duration_s(self) -> float:
        return self.n_ticks * self.tick_ns * 1e-9


def preflight_command(n_ticks: int, tick_s: float, current_limit_a: float) -> np.ndarray:
    """Coil-current command [A] held during each tick ``k`` (``t = k tick_s`` at its start)."""
    t = np.arange(n_ticks) * tick_s
    out = np.zeros(n_ticks)
    for t0, t1, kind, a, b in PREFLIGHT_PROFILE:
        m = (t >= t0 - 1e-12) & (t < t1 - 1e-12)
        if kind == 'step':
            out[m] = a
        else:
            out[m] = a * np.sin(2.0 * np.pi * (t[m] - t0) / b)
    return out * current_limit_a


def run_preflight(params: PlantParams, seed: int = 0, tick_s: float = PREFLIGHT_TICK_S,
                  dt_s: float = 1e-6, fluid=None, integrator: str = 'explicit') -> dict:
    """The pre-flight check on the plant alone: arrays (one value per tick, the state at the
    tick's end) of ``command_a`` and :data:`PREFLIGHT_SIGNALS`, bit for bit what the plant node
    gives running it tick by tick, in one kernel call (:meth:`.plant.Plant.advance_currents`).
    Training data for :mod:`eha_ros.health.preflight`.  ``fluid``: a surrogate of the
    fluid-dynamic block (:class:`.loop.FluidBlock`; hf when ``None``); ``integrator`` and
    ``dt_s``: the plant's (:class:`.plant.Plant`)."""
    from .plant import Plant
    from .state import RECORD_FIELDS
    check = PreflightCheck(int(round(tick_s * 1e9)), params.current_limit_a)
    plant = Plant(params, dt_s=dt_s, seed=seed, fluid=fluid, integrator=integrator)
    rec = plant.advance_currents(check.command_a, int(round(tick_s / dt_s)))
    out = {k: rec[:, RECORD_FIELDS.index(k)].copy() for k in PREFLIGHT_SIGNALS}
    out['command_a'] = check.command_a.copy()
    return out
