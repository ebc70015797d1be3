"""The actuator plant and the closed loop: the public wrappers around the kernel.

One plant step of ``dt`` is a forward-Euler step of the reference's block diagram: torque
motor (hysteresis, offset, noise, saturation, force), metering-edge flows, spool (Borello,
flow force), first stage, jack (Borello), chamber pressures (cavitation clip), surface play,
all evaluated at the state at the start of the step; the two second-order bodies (flapper,
jack) update velocity before position (semi-implicit Euler).  That is the ``explicit``
integrator, the reference's and the default; ``split`` takes the jack and its chambers as a
Stormer-Verlet pair with linearly implicit pressures and places friction transitions and end
stops on 1 us substeps, which holds the in-loop bounds at 10-25 us steps (:func:`.loop.advance`,
``bench/inloop.py``).

The controller runs every ``controller_period_s`` (a whole number of plant steps; by default
every step, as the reference's continuous-time PID) on the quantised sensor reading, and holds
its current in between, which is what the ROS graph does at its tick rate.

Randomness stays outside the kernels: the torque-motor noise is a sequence of samples drawn
from ``numpy.random.Generator(seed)`` and held for ``noise_sample_time_s`` each; sample ``k``
covers ``[k ts, (k+1) ts)``.  Time is ``n * dt`` with an integer step counter ``n`` and ``dt``
in whole nanoseconds, so a run advanced in chunks (the ROS plant) is bit-identical to one
advanced at once.

Named ``plant`` for what it offers: :class:`Plant` (stepped from outside),
:class:`PositionController`, :func:`simulate`, with the :class:`NoiseSource` they draw.  The
parts live by role: the state layout in :mod:`.state`, the kernel and the surrogate interface
in :mod:`.loop`, the step's stability in :mod:`.stability`.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .commands import COM, Scenario, get_scenario
from .events import EventSchedule
from .jack import quantise
from .loop import (OPEN_LOOP, Clock, ClosedLoop, FluidBlock, diverged, fluid_kernels, pid,
                   record, run)
from .params import ParameterError, PlantParams, default_params
from .stability import DT_S, EXPLICIT, check_dt, dt_to_ns, integrator_substeps
from .state import N_REC, RECORD_FIELDS, S_SURF, STATE_NAMES, initial_state

__all__ = ['NoiseSource', 'SimResult', 'Plant', 'PositionController', 'simulate']


class NoiseSource:
    """Band-limited white current noise: held Gaussian samples from a seeded generator.

    Samples are drawn in order and kept, so any run with the same seed sees the same noise
    whatever the chunks it is advanced in.
    """

    def __init__(self, std_a: float, sample_time_s: float, seed: int):
        self.std_a = float(std_a)
        self.sample_time_s = float(sample_time_s)
        self._rng = np.random.default_rng(seed)
        self._samples = np.zeros(0)

    def samples_until(self, t_end_s: float) -> np.ndarray:
        """All samples covering ``[0, t_end_s]`` (drawing more as needed)."""
        need = int(t_end_s / self.sample_time_s) + 2
        if need > self._samples.size:
            extra = max(need - self._samples.size, 1024)
            new = self._rng.standard_normal(extra) * self.std_a
            self._samples = np.concatenate([self._samples, new])
        return self._samples


@dataclasses.dataclass
class SimResult:
    """Time histories of a closed-loop run; ``data[field]`` for each of ``RECORD_FIELDS``.

    ``params`` are those the run started with; ``events`` lists the parameter changes that
    took effect, in order, as ``{'tick': k, 'time_s': tick time [s], 'changes': {name:
    value}}``.
    """

    data: dict
    params: PlantParams
    scenario: Scenario
    dt_s: float
    controller_period_s: float
    seed: int
    wall_time_s: float
    events: list = dataclasses.field(default_factory=list)
    integrator: str = EXPLICIT

    def __getitem__(self, key):
        return self.data[key]

    @property
    def t(self):
        return self.data['time_s']


class Plant:
    """The actuator plant advanced by a held coil-current command, for stepping from outside
    (the ROS plant node), by the ``integrator`` of :func:`simulate`.  ``advance`` over several
    calls is bit-identical to one call."""

    def __init__(self, params: PlantParams | None = None, dt_s: float = DT_S, seed: int = 0,
                 fluid: FluidBlock | None = None, integrator: str = EXPLICIT):
        self.params = params if params is not None else default_params()
        self.fluid = fluid
        self._kernels = fluid_kernels(fluid, self.params)
        self.substeps = integrator_substeps(integrator, dt_s)
        check_dt(self.params, dt_s, fluid, integrator)
        self.dt_s = float(dt_s)
        self.dt_ns = dt_to_ns(dt_s)
        self.integrator = integrator
        self.seed = int(seed)
        self.reset()

    def reset(self):
        self.state = initial_state(self.params)
        self.steps = 0
        self.noise = NoiseSource(self.params.noise_std_a, self.params.noise_sample_time_s,
                                 self.seed)

    def set_params(self, params: PlantParams):
        """Change parameters (wear, degradation) from the next step on."""
        kernels = fluid_kernels(self.fluid, params)  # a dynamic surrogate's data per wear
        check_dt(params, self.dt_s, self.fluid, self.integrator)
        if (params.noise_std_a != self.params.noise_std_a
                or params.noise_sample_time_s != self.params.noise_sample_time_s):
            raise ParameterError('noise_std_a and noise_sample_time_s cannot change during a '
                                 'run')
        self.params = params
        self._kernels = kernels

    @property
    def time_ns(self) -> int:
        """Simulated time [ns] (exact integer)."""
        return self.steps * self.dt_ns

    @property
    def time_s(self) -> float:
        """Simulated time [s], ``time_ns * 1e-9`` as the kernels compute it."""
        return self.time_ns * 1e-9

    def advance(self, current_command_a: float, n_steps: int) -> None:
        """Advance ``n_steps`` plant steps with the coil current command held."""
        if not math.isfinite(current_command_a):
            raise ParameterError(f'current command {current_command_a} A is not finite')
        t_end = (self.steps + n_steps) * self.dt_s
        noise = self.noise.samples_until(t_end)
        clock = Clock(self.steps, int(n_steps), self.dt_s, self.dt_ns, noise,
                      self.params.noise_sample_time_s, self.substeps)
        status, done, _, _ = run(self.state, float(current_command_a), self.params, clock,
                                 OPEN_LOOP, *self._kernels)
        self.steps += done
        if status:
            raise diverged(status, self.time_s)

    def advance_currents(self, currents_a, steps_per_tick: int) -> np.ndarray:
        """Advance one tick of ``steps_per_tick`` steps per current command of
        ``currents_a`` [A], each held over its tick, in one kernel call: the same states, bit
        for bit, as :meth:`advance` called once per tick.  Returns the record
        (:data:`.state.RECORD_FIELDS`, one row per tick: the state at the tick's end, its
        time, and in ``command_m`` and ``current_command_a`` the current held over it)."""
        cur = np.ascontiguousarray(currents_a, dtype=float)
        if cur.ndim != 1 or cur.size == 0 or not np.all(np.isfinite(cur)):
            raise ParameterError('current commands must be a non-empty 1-D array of finite '
                                 'values [A]')
        n, steps = cur.size, int(steps_per_tick)
        if steps < 1:
            raise ParameterError(f'steps_per_tick = {steps_per_tick} must be at least 1')
        tick_ns = steps * self.dt_ns
        t0 = self.steps * self.dt_ns
        # tick k falls due at t0 + k tick_ns; its current is due half a tick before, so that
        # the kernel's table lookup (the value last due) never hangs on a rounding of the time
        com_t = (t0 + (np.arange(n) - 0.5) * tick_ns) * 1e-9
        rec = np.full((n, N_REC), np.nan)
        noise = self.noise.samples_until((self.steps + n * steps) * self.dt_s)
        clock = Clock(self.steps, n * steps, self.dt_s, self.dt_ns, noise,
                      self.params.noise_sample_time_s, self.substeps)
        loop = ClosedLoop(np.zeros(0), COM, OPEN_LOOP.args, com_t, cur, steps, 1, 1, rec)
        status, done, rows, i_cmd = run(self.state, 0.0, self.params, clock, loop,
                                        *self._kernels)
        self.steps += done
        if status:
            raise diverged(status, self.time_s)
        record(rec, rows, self.time_s, i_cmd, i_cmd, self.state, self.params)
        # each row's commands: the current held over its tick (the kernel writes the next's)
        rec[:, RECORD_FIELDS.index('command_m')] = cur
        rec[:, RECORD_FIELDS.index('current_command_a')] = cur
        return rec

    def hold(self, n_steps: int) -> None:
        """Advance the clock ``n_steps`` steps with the actuator frozen (a valve test: the jack
        clamped, the valve on its test circuit, see :mod:`.maintenance`)."""
        if n_steps < 0:
            raise ValueError('n_steps must not be negative')
        self.steps += int(n_steps)

    def measured_position_m(self) -> float:
        return float(quantise(self.state[S_SURF], self.params.sensor_resolution_m))

    def snapshot(self) -> dict:
        """Named copy of the state."""
        d = {name: float(v) for name, v in zip(STATE_NAMES, self.state)}
        d['p12_pa'] = d['p1_pa'] - d['p2_pa']
        d['jack_position_measured_m'] = self.measured_position_m()
        d['time_s'] = self.time_s
        return d


class PositionController:
    """The closed loop's PID, for running it outside the plant (the ROS controller node).

    Same arithmetic as inside :func:`simulate`, so a loop closed through this class and
    :class:`Plant` reproduces :func:`simulate` bit for bit.
    """

    def __init__(self, params: PlantParams | None = None, period_s: float = 1e-3):
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ParameterError(f'controller period {period_s} s must be positive')
        self.params = params if params is not None else default_params()
        self.period_s = float(period_s)
        self._inv = 1.0 / self.period_s
        self.reset()

    def reset(self):
        self._ctrl = np.zeros(3)

    def update(self, command_m: float, measured_m: float) -> float:
        """Coil current command [A] for this tick."""
        return float(pid(self._ctrl, float(command_m) - float(measured_m), self.period_s,
                         self._inv, self.params))


def simulate(params: PlantParams | None = None, scenario='step_0p1', duration_s=None,
             dt_s: float = DT_S, seed: int = 0, controller_period_s: float | None = None,
             record_dt_s: float | None = 1e-4, fluid: FluidBlock | None = None,
             events=None, integrator: str = EXPLICIT) -> SimResult:
    """Closed-loop run: ``(params, scenario, duration, dt, seed) -> time histories``.

    Parameters
    ----------
    params : PlantParams, optional
        Physical parameters (default: ``config/eha_params.yaml``).
    scenario : str or Scenario
        Command; a name from ``config/scenarios.yaml`` or a :class:`Scenario`.
    duration_s : float, optional
        Simulated time [s] (default: the scenario's).
    dt_s : float
        Plant step [s] (1 us, as the reference).
    seed : int
        Seed of the torque-motor noise.
    controller_period_s : float, optional
        Controller sample period [s], a whole number of plant steps (default: every step).
    record_dt_s : float, optional
        Recording interval [s], a whole number of controller periods (default 0.1 ms, or the
        controller period if longer; ``None``: every controller tick).
    fluid : FluidBlock, optional
        A surrogate of the fluid-dynamic block (:func:`eha_ros.surrogates.registry.load_surrogate`,
        see :class:`.loop.FluidBlock`): algebraic, its kernel gives P12, or dynamic, the
        metering-edge flows only (see :func:`.loop.advance`); the high-fidelity block when
        ``None``.
    integrator : str
        ``explicit`` (the reference's scheme, the default) or ``split`` (the jack and its
        chambers as a Stormer-Verlet pair with linearly implicit pressures, events in 1 us
        substeps: the larger steps, see :func:`.loop.advance` and ``bench/inloop.py``).
    events : optional
        Parameter changes during the run, after the scenario's own events: an
        :class:`~.events.EventSchedule` or what one is
        built from (events, ``(t_s, {name: value})`` pairs, ``'T:name=value'`` texts) of the
        parameters in ``PLANT_RUNTIME`` and ``CONTROLLER_RUNTIME``.  Each takes effect at the
        first controller tick whose time is at least ``t_s``, before that tick's controller
        update and plant steps, as :meth:`Plant.set_params` and a new
        ``PositionController.params`` between ticks would; the plant starts at rest for
        ``params`` whatever changes at t = 0.  All are checked (ranges, stability limit, a
        surrogate's validity) before the run; those due after its end are not applied.
    """
    p = params if params is not None else default_params()
    sc = get_scenario(scenario)
    duration = float(sc.duration_s if duration_s is None else duration_s)
    if not (duration > 0 and math.isfinite(duration)):
        raise ParameterError(f'duration_s = {duration_s} must be a positive number of seconds')
    kernels = fluid_kernels(fluid, p)
    substeps = integrator_substeps(integrator, dt_s)
    check_dt(p, dt_s, fluid, integrator)
    dt_ns = dt_to_ns(dt_s)
    period = dt_s if controller_period_s is None else float(controller_period_s)
    steps_per_tick = int(round(period / dt_s))
    if steps_per_tick < 1 or abs(steps_per_tick * dt_s - period) > 1e-9 * period:
        raise ParameterError(f'controller_period_s = {period:g} s must be a whole multiple of '
                             f'dt_s = {dt_s:g} s')
    n_ticks = int(round(duration / period))
    rec_every = 1 if record_dt_s is None else max(1, int(round(record_dt_s / period)))
    # the run in segments of constant parameters: tick -> (parameters, kernels) from it on
    schedule = EventSchedule([(t, dict(changes)) for t, _, changes in sc.events]
                             + list(events or ()), period_ns=steps_per_tick * dt_ns)
    segments = {0: (p, kernels)}
    applied = []
    for ev, q in zip(schedule, schedule.validate(p)):
        k = schedule.tick_of(ev)
        if k < n_ticks:
            kernels = fluid_kernels(fluid, q)
            check_dt(q, dt_s, fluid, integrator)
            segments[k] = (q, kernels)
            applied.append({'tick': k, 'time_s': (k * steps_per_tick * dt_ns) * 1e-9,
                            'changes': ev.as_dict()})
    n_rows = n_ticks // rec_every + 2
    rec = np.full((n_rows, N_REC), np.nan)
    state = initial_state(p)
    ctrl = np.zeros(3)
    samples = NoiseSource(p.noise_std_a, p.noise_sample_time_s, seed).samples_until(
        n_ticks * steps_per_tick * dt_s)
    kind, args, com_t, com_v = sc.arrays()
    t0 = time.perf_counter()
    rows, i_cmd = 0, 0.0
    ends = list(segments)[1:] + [n_ticks]
    for (k0, (q, kernels)), k1 in zip(segments.items(), ends):
        n0 = k0 * steps_per_tick
        clock = Clock(n0, (k1 - k0) * steps_per_tick, dt_s, dt_ns, samples,
                      p.noise_sample_time_s, substeps)
        loop = ClosedLoop(ctrl, kind, args, com_t, com_v, steps_per_tick, rec_every,
                          -k0 % rec_every, rec[rows:])
        status, done, new_rows, i_cmd = run(state, i_cmd, q, clock, loop, *kernels)
        rows += new_rows
        if status:
            raise diverged(status, ((n0 + done) * dt_ns) * 1e-9)
    wall = time.perf_counter() - t0
    if n_ticks % rec_every == 0:  # close the record with the final state
        t_end = (n_ticks * steps_per_tick * dt_ns) * 1e-9
        record(rec, rows, t_end, sc.value(t_end), i_cmd, state, q)
        rows += 1
    data = {name: rec[:rows, j].copy() for j, name in enumerate(RECORD_FIELDS)}
    return SimResult(data=data, params=p, scenario=sc, dt_s=float(dt_s),
                     controller_period_s=steps_per_tick * dt_s, seed=int(seed),
                     wall_time_s=wall, events=applied, integrator=integrator)
