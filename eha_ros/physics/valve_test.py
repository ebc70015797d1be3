"""Diagnostic valve test: the characteristic-map sweep run on the plant, tick by tick.

The diagnostic network recognises wear from the curves of the reference's map procedure
(section 5.1): the spool held at each of the 133 positions of :func:`.maps.spool_grid`, the
load flow imposed, both chamber pressures from zero, P12 read after ``MAP_HOLD_S`` = 1e-2 s.
A rig reproduces it as a maintenance test - the jack ports switched to a flow-controlled test
circuit, the spool positioned point by point - and the plant does the same when asked: during
the test the jack stays where it is (clamped) and, at every tick, the plant reports the
held spool position, the imposed flow and the chamber pressures of that point's transient at
the tick's time.  The sample at the end of each hold is the map's value, bit for bit (same
kernel, same step).

Order: for each flow in turn, the spool positions from -stroke to +stroke.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .maps import spool_grid, transient_map
from .params import ParameterError, PlantParams

__all__ = ['MAP_POINTS', 'MAP_HOLD_S', 'ValveTest', 'ValveTestSample']

#: Spool positions of a curve (the databases' grid).
MAP_POINTS = 133
#: Hold of every point [s]: the reference's map transient.
MAP_HOLD_S = 1e-2


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
    """

    def __init__(self, flows_m3_s, tick_ns: int, dt_s: float, hold_s: float = MAP_HOLD_S,
                 n_points: int = MAP_POINTS):
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
        self.ticks_per_point = hold_ns // self.tick_ns
        self.n_ticks = flows.size * self.n_points * self.ticks_per_point

    @property
    def duration_s(self) -> float:
        return self.n_ticks * self.tick_ns * 1e-9

    def grid(self, params: PlantParams) -> np.ndarray:
        return spool_grid(self.n_points, params.spool_stroke_m)

    def sample(self, k: int, params: PlantParams) -> ValveTestSample:
        """The state at the end of tick ``k`` (1 .. ``n_ticks``) with the wear of ``params``."""
        if not 1 <= k <= self.n_ticks:
            raise IndexError(f'valve test tick {k} outside 1..{self.n_ticks}')
        point_global, m = divmod(k - 1, self.ticks_per_point)
        curve, point = divmod(point_global, self.n_points)
        xs = float(self.grid(params)[point])
        q = float(self.flows_m3_s[curve])
        t_end = (m + 1) * self.tick_ns * 1e-9
        r = transient_map(xs, q, params=params, t_end_s=t_end, dt_s=self.dt_s)
        p1 = float(r['p1_pa'])
        p2 = float(r['p2_pa'])
        if not (math.isfinite(p1) and math.isfinite(p2)):  # transient_map raises first
            raise FloatingPointError('valve test transient is not finite')
        return ValveTestSample(xs, q, p1, p2, point, curve, m == self.ticks_per_point - 1)
