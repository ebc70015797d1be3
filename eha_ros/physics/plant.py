"""The actuator plant and the closed loop: state layout, fixed-step kernels, public wrappers.

One plant step of ``dt`` is a forward-Euler step of the reference's block diagram: torque
motor (hysteresis, offset, noise, saturation, force), metering-edge flows, spool (Borello,
flow force), first stage, jack (Borello), chamber pressures (cavitation clip), surface play,
all evaluated at the state at the start of the step; the two second-order bodies (flapper,
jack) update velocity before position (semi-implicit Euler).

The controller runs every ``controller_period_s`` (a whole number of plant steps; by default
every step, as the reference's continuous-time PID) on the quantised sensor reading, and holds
its current in between, which is what the ROS graph does at its tick rate.

Randomness stays outside the kernels: the torque-motor noise is a sequence of samples drawn
from ``numpy.random.Generator(seed)`` and held for ``noise_sample_time_s`` each; sample ``k``
covers ``[k ts, (k+1) ts)``.  Time is ``n * dt`` with an integer step counter ``n`` and ``dt``
in whole nanoseconds, so a run advanced in chunks (the ROS plant) is bit-identical to one
advanced at once.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
from numba import njit

from .commands import Scenario, command_value, get_scenario
from .events import EventSchedule
from .jack import jack_step, quantise, surface_position
from .params import ParameterError, PlantParams, default_params
from .servovalve import (coil_current, flapper_damping, flapper_step, magnetic_stiffness,
                         spool_gains, spool_step, torque_motor_force)
from .valve import (chamber_step, net_flow, orifice_flow, steady_pressures, valve_coefficients,
                    valve_constants)

__all__ = ['STATE_NAMES', 'RECORD_FIELDS', 'SimulationDiverged', 'SimResult', 'NoiseSource',
           'Plant', 'PositionController', 'simulate', 'initial_state', 'stability_limit',
           'stability_limits', 'check_dt']

STATE_NAMES = ('hysteresis_state_a', 'flapper_position_m', 'flapper_velocity_m_s',
               'spool_position_m', 'spool_velocity_m_s', 'p1_unclipped_pa', 'p2_unclipped_pa',
               'p1_pa', 'p2_pa', 'jack_position_m', 'jack_velocity_m_s', 'surface_position_m',
               'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n', 'q1l_m3_s',
               'q2l_m3_s')
(S_PLAY, S_XF, S_VF, S_XS, S_VS, S_P1T, S_P2T, S_P1, S_P2, S_XJ, S_VJ, S_SURF, S_QJ, S_ICOIL,
 S_FTM, S_Q1L, S_Q2L) = range(len(STATE_NAMES))
N_STATE = len(STATE_NAMES)

RECORD_FIELDS = ('time_s', 'command_m', 'current_command_a', 'coil_current_a',
                 'torque_motor_force_n', 'flapper_position_m', 'spool_position_m', 'p1_pa',
                 'p2_pa', 'p12_pa', 'load_flow_m3_s', 'jack_position_m', 'jack_velocity_m_s',
                 'surface_position_m', 'jack_position_measured_m')
N_REC = len(RECORD_FIELDS)

# state entries watched for divergence, in the order they are reported
_WATCHED = (S_XF, S_VF, S_XS, S_P1T, S_P2T, S_XJ, S_VJ)
_DIVERGED_ABS = 1e12  # any watched state beyond this (in SI units) has diverged


class SimulationDiverged(RuntimeError):
    """A state became NaN, infinite or absurdly large."""


# --- kernels ------------------------------------------------------------------------------------

@njit(cache=True, inline='always')
def _pid(ctrl, error, period, inv_period, p):
    """PID on the position error with conditional-integration anti-windup; ctrl is
    [integral, previous error, has previous]."""
    d = (error - ctrl[1]) * inv_period if ctrl[2] != 0.0 else 0.0
    integ = ctrl[0] + error * period
    u = p.kp_a_m * error + p.ki_a_m_s * integ + p.kd_a_s_m * d
    lim = p.current_limit_a
    if u > lim:
        u = lim
    elif u < -lim:
        u = -lim
    else:
        ctrl[0] = integ
    ctrl[1] = error
    ctrl[2] = 1.0
    return u


@njit(cache=True)
def _record(rec, row, t, r, i_cmd, s, p):
    rec[row, 0] = t
    rec[row, 1] = r
    rec[row, 2] = i_cmd
    rec[row, 3] = s[S_ICOIL]
    rec[row, 4] = s[S_FTM]
    rec[row, 5] = s[S_XF]
    rec[row, 6] = s[S_XS]
    rec[row, 7] = s[S_P1]
    rec[row, 8] = s[S_P2]
    rec[row, 9] = s[S_P1] - s[S_P2]
    rec[row, 10] = s[S_QJ]
    rec[row, 11] = s[S_XJ]
    rec[row, 12] = s[S_VJ]
    rec[row, 13] = s[S_SURF]
    rec[row, 14] = quantise(s[S_SURF], p.sensor_resolution_m)


@njit(cache=True)
def _save(s, y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f, q1l, q2l):
    s[S_PLAY] = y
    s[S_XF] = xf
    s[S_VF] = vf
    s[S_XS] = xs
    s[S_VS] = vs
    s[S_P1T] = p1t
    s[S_P2T] = p2t
    s[S_P1] = p1
    s[S_P2] = p2
    s[S_XJ] = xj
    s[S_VJ] = vj
    s[S_SURF] = surf
    s[S_QJ] = qj
    s[S_ICOIL] = i
    s[S_FTM] = f
    s[S_Q1L] = q1l
    s[S_Q2L] = q2l


@njit(cache=True)
def no_fluid_block(data, xs_m, q_m3_s, overlap_m, clearance_m):
    """Placeholder algebraic fluid function of the other paths (never called there)."""
    return 0.0


@njit(cache=True)
def no_flows_block(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m):
    """Placeholder metering-edge function of the other paths (never called there)."""
    return 0.0, 0.0


NO_FLUID_DATA = (np.zeros(1),)


@njit  # not cached on disk: see below
def _run(s, ctrl, i_cmd, p, kind, args, com_t, com_v, noise, noise_dt, n0, dt, dt_ns, n_steps,
         steps_per_tick, rec_every, rec_wait, rec, fluid_fn, flows_fn, fluid_data, fluid_mode):
    """Advance the plant state ``s`` (in place) by ``n_steps`` steps of ``dt``.

    ``fluid_mode`` 0: the high-fidelity fluid block.  1 (algebraic surrogate): the block is
    replaced by ``P12 = fluid_fn(fluid_data, XS, QJ, overlap, clearance)`` with the load flow
    imposed by the jack, ``QJ = AJ dXJ/dt``; P1, P2 are then reported as mid-pressure +- P12/2.
    2 (dynamic surrogate): only the metering-edge flows come from the surrogate,
    ``(Q1L, Q2L) = flows_fn(fluid_data, XS, P1, P2, OSSV, ORSV)``; chambers, leakage,
    cavitation clip and jack stay the high-fidelity ones.

    ``steps_per_tick = 0``: open loop, the coil current command ``i_cmd`` is held.  Otherwise
    the controller (state ``ctrl``) runs every ``steps_per_tick`` steps on the quantised
    sensor against the command ``(kind, args, com_t, com_v)``, and every ``rec_every``-th
    tick, the first after ``rec_wait`` unrecorded ticks, is recorded into ``rec`` (from its
    row 0) before the plant moves on.

    ``noise[k]`` is the noise sample covering ``[k noise_dt, (k+1) noise_dt)``; ``n0`` is the
    global index of the first step.  The time of step ``n`` is ``(n dt_ns) 1e-9`` s, from the
    integer nanoseconds a ROS clock carries, so the graph evaluates commands at the same
    times bit for bit.  Returns ``(status, steps done, rows recorded, i_cmd)``:
    status 0, or 1 + the index into ``_WATCHED`` of the first state that diverged.

    Not cached on disk: ``fluid_fn`` (a numba function passed as an argument) is typed by its
    object, not its code, so a cache entry keyed by it never matches in another process and,
    once that object is gone, breaks the saving of the cache index for every later entry.  The
    blocks it calls are cached; this function compiles in a few seconds per process.
    """
    cf = flapper_damping(p)
    drive, c_eq = spool_gains(p)
    kvol = p.bulk_modulus_pa / p.chamber_volume_m3
    ps = p.supply_pressure_pa
    pr = p.return_pressure_pa
    pvap = p.vapour_pressure_pa
    aj = p.jack_area_m2
    clk = p.leakage_coeff_m3_s_pa
    q = p.sensor_resolution_m
    vc = valve_constants(p)
    lap = p.overlap_supply_m
    lap_r = p.overlap_return_m
    clr = p.radial_clearance_m
    pmid = 0.5 * (ps + pr)
    steps_per_noise = dt / noise_dt
    period = steps_per_tick * dt
    inv_period = 1.0 / period if steps_per_tick > 0 else 0.0
    y = s[S_PLAY]
    xf = s[S_XF]
    vf = s[S_VF]
    xs = s[S_XS]
    vs = s[S_VS]
    p1t = s[S_P1T]
    p2t = s[S_P2T]
    p1 = s[S_P1]
    p2 = s[S_P2]
    xj = s[S_XJ]
    vj = s[S_VJ]
    surf = s[S_SURF]
    qj = s[S_QJ]
    i = s[S_ICOIL]
    f = s[S_FTM]
    q1l = s[S_Q1L]
    q2l = s[S_Q2L]
    status = 0
    done = 0
    row = 0
    until_tick = 0
    until_rec = rec_wait
    for j in range(n_steps):
        n = n0 + j
        if steps_per_tick > 0:
            if until_tick == 0:
                until_tick = steps_per_tick
                t = (n * dt_ns) * 1e-9
                r = command_value(kind, args, com_t, com_v, t)
                i_cmd = _pid(ctrl, r - quantise(surf, q), period, inv_period, p)
                if until_rec == 0:
                    until_rec = rec_every
                    _save(s, y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f,
                          q1l, q2l)
                    _record(rec, row, t, r, i_cmd, s, p)
                    row += 1
                until_rec -= 1
            until_tick -= 1
        # every derivative from the state at the start of the step (forward Euler, as a
        # fixed-step ode1 solver evaluates a block diagram); the blocks are then independent
        # within a step, which lets the processor overlap them
        k = int(n * steps_per_noise)
        y, i = coil_current(y, i_cmd, noise[k], p)
        f = torque_motor_force(i, xf, p)
        if fluid_mode == 1:
            qj = aj * vj
            q1l = qj
            q2l = qj
            p12 = fluid_fn(fluid_data, xs, qj, lap, clr)
            p1 = pmid + 0.5 * p12
            p2 = pmid - 0.5 * p12
        else:
            if fluid_mode == 2:
                q1l, q2l = flows_fn(fluid_data, xs, p1, p2, lap, lap_r)
            else:
                (rl1s, bl1s, r41s, rl1r, bl1r, r41r,
                 rl2s, bl2s, r42s, rl2r, bl2r, r42r) = valve_coefficients(xs, vc)
                q1l = net_flow(ps - p1, rl1s, bl1s, r41s, p1 - pr, rl1r, bl1r, r41r)
                q2l = net_flow(p2 - pr, rl2r, bl2r, r42r, ps - p2, rl2s, bl2s, r42s)
            qj = 0.5 * (q1l + q2l)
            p12 = p1 - p2
        xs_old = xs
        xs, vs = spool_step(xs, vs, xf, qj, drive, c_eq, p, dt)
        xf, vf = flapper_step(xf, vf, xs_old, f, cf, p, dt)
        qm = aj * vj + clk * p12
        xj, vj = jack_step(xj, vj, p12, p, dt)
        if fluid_mode == 1:
            p1t = p1  # the surrogate's pressures at the start of this step
            p2t = p2
        else:
            p1t, p2t, p1, p2 = chamber_step(p1t, p2t, q1l, q2l, qm, kvol, pvap, dt)
        surf = surface_position(surf, xj, p)
        done = j + 1
        chk = xf + vf + xs + p1t + p2t + xj + vj
        if not (abs(chk) < _DIVERGED_ABS):
            vals = (xf, vf, xs, p1t, p2t, xj, vj)
            status = len(vals)
            for m in range(len(vals)):
                if not (abs(vals[m]) < _DIVERGED_ABS):
                    status = m + 1
                    break
            break
    _save(s, y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f, q1l, q2l)
    return status, done, row, i_cmd


_EMPTY = np.zeros(0)
_EMPTY_ARGS = np.zeros(8)


# --- wrappers -----------------------------------------------------------------------------------

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


def _edge_conductance_max(p: PlantParams) -> float:
    """Largest flow conductance dQ/dp [m^3/(s Pa)] of one chamber, over the spool stroke."""
    worst = 0.0
    dp_ref = 0.0 if p.cd_model == 0.0 else 1e-3 * (p.supply_pressure_pa - p.return_pressure_pa)
    for xs in (-p.spool_stroke_m, 0.0, p.spool_stroke_m):
        co = valve_coefficients(xs, valve_constants(p))
        g = 0.0
        for e in range(4):
            rl, bl, r4 = co[3 * e], co[3 * e + 1], co[3 * e + 2]
            dp = max(dp_ref, 1.0)
            g_e = orifice_flow(dp, rl, bl, r4) / dp if dp_ref else 2.0 / (
                rl + math.sqrt(rl * rl + bl + r4 * dp))
            g = max(g, g_e)
        worst = max(worst, 2.0 * g)
    return worst


def stability_limits(p: PlantParams, fluid=None) -> list[tuple[float, str]]:
    """Per block, the largest stable step [s] of its linearisation under the explicit scheme.

    With a surrogate ``fluid`` the chamber bound is replaced by the surrogate's own feedback
    bound (``fluid.stability_limit(p)``): for an algebraic ``P12(XS, Q)`` the jack sees
    ``AJ^2 dP12/dQ`` as a damper, for a dynamic one its flows' conductance sets the chamber
    bound as the valve's does.

    The semi-implicit Euler oscillator ``w dt < min(1/zeta, 2 (sqrt(zeta^2 + 1) - zeta))`` for
    the first stage, ``w dt < 2`` for the jack on its hydraulic spring, ``dt < 2 tau`` for the
    chamber pressures (largest valve conductance: full stroke, vanishing drop), the massless
    spool and the jack's viscous decay.  The chamber bound is conservative: the orifice
    conductance falls as the drop grows, so beyond it the pressures chatter before they
    diverge.
    """
    limits = []
    k_m = magnetic_stiffness(p) if p.torque_motor_model == 1.0 else 0.0
    k_f = p.flapper_stiffness_n_m + p.feedback_spring_stiffness_n_m - k_m
    if k_f <= 0:
        raise ParameterError('parameter flapper_stiffness_n_m must exceed the magnetic '
                             f'negative stiffness {k_m:.4g} N/m less the feedback spring')
    w_f = math.sqrt(k_f / p.flapper_mass_kg)
    z_f = p.flapper_damping_ratio * math.sqrt(
        (p.flapper_stiffness_n_m + p.feedback_spring_stiffness_n_m) / k_f)
    limits.append((min(1.0 / z_f, 2.0 * (math.sqrt(z_f ** 2 + 1) - z_f)) / w_f,
                   'first stage (flapper) oscillator'))
    k_h = 2.0 * p.bulk_modulus_pa * p.jack_area_m2 ** 2 / p.chamber_volume_m3
    w_h = math.sqrt((k_h + p.aero_stiffness_n_m) / p.jack_mass_kg)
    limits.append((2.0 / w_h, 'jack hydraulic spring'))
    if p.jack_viscous_n_s_m > 0:
        limits.append((2.0 * p.jack_mass_kg / p.jack_viscous_n_s_m, 'jack viscous damping'))
    g = _edge_conductance_max(p)
    limits.append((2.0 * p.chamber_volume_m3 / (p.bulk_modulus_pa * g),
                   'chamber pressures (Bet/Vol x valve conductance)'))
    drive, c_eq = spool_gains(p)
    if drive > 0 and c_eq > 0:
        # quasi-static flapper: XS' = drive/c_eq * (F - KSF XS)/(KF + KSF)
        rate = drive / c_eq * p.feedback_spring_stiffness_n_m / k_f
        limits.append((2.0 / rate, 'second stage (spool) lag'))
    if fluid is not None and hasattr(fluid, 'stability_limit'):
        limits = [x for x in limits if not x[1].startswith('chamber')]
        limits.append(fluid.stability_limit(p))
    return limits


def stability_limit(p: PlantParams, fluid=None) -> tuple[float, str]:
    """Largest stable plant step [s] and the block that sets it (see
    :func:`stability_limits`)."""
    return min(stability_limits(p, fluid), key=lambda x: x[0])


def _fluid_args(fluid, p: PlantParams):
    """``(P12 kernel, flows kernel, kernel data, mode)`` of ``_run`` for a fluid block
    (``None``: hf)."""
    if fluid is None:
        return no_fluid_block, no_flows_block, NO_FLUID_DATA, 0
    try:
        kernel = fluid.kernel
        family = 'dynamic' if fluid.kernel_output == 'chamber_flows' else 'algebraic'
        data = fluid.prepare(p) if hasattr(fluid, 'prepare') else fluid.data
    except AttributeError:
        raise ParameterError('fluid must provide kernel and data (a FluidSurrogate)') from None
    except ValueError as exc:  # a surrogate refusing these parameters
        raise ParameterError(str(exc)) from None
    if family == 'dynamic':
        return no_fluid_block, kernel, tuple(data), 2
    return kernel, no_flows_block, tuple(data), 1


def dt_to_ns(dt_s: float) -> int:
    """The step as a whole number of nanoseconds (ROS time resolution); refuses others."""
    dt_ns = int(round(dt_s * 1e9))
    if dt_ns < 1 or abs(dt_ns * 1e-9 - dt_s) > 1e-6 * dt_s:
        raise ParameterError(f'dt_s = {dt_s:g} s must be a whole number of nanoseconds')
    return dt_ns


def check_dt(p: PlantParams, dt_s: float, fluid=None) -> None:
    """Refuse a non-positive step or one beyond the stability limit, with the bound of what
    a surrogate ``fluid`` feeds back in place of the chamber bound (:func:`stability_limits`)."""
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise ParameterError(f'dt_s = {dt_s} must be a positive number of seconds')
    dt_to_ns(dt_s)
    lim, block = stability_limit(p, fluid)
    if dt_s > lim:
        raise ParameterError(f'dt_s = {dt_s:g} s exceeds the stability limit {lim:.3g} s set '
                             f'by the {block}')


def initial_state(p: PlantParams) -> np.ndarray:
    """Plant at rest at null: spool and flapper centred, chamber pressures at their steady
    values for a centred spool and no flow."""
    s = np.zeros(N_STATE)
    p1, p2 = steady_pressures(0.0, 0.0, p, 10.0 * p.supply_pressure_pa)
    s[S_P1T] = s[S_P1] = p1
    s[S_P2T] = s[S_P2] = p2
    return s


def _diverged(p_status: int, t_s: float) -> SimulationDiverged:
    name = STATE_NAMES[_WATCHED[p_status - 1]]
    return SimulationDiverged(f'simulation diverged: state {name} became non-finite or '
                              f'exceeded {_DIVERGED_ABS:g} at t = {t_s:.6g} s')


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

    def __getitem__(self, key):
        return self.data[key]

    @property
    def t(self):
        return self.data['time_s']


class Plant:
    """The actuator plant advanced by a held coil-current command, for stepping from outside
    (the ROS plant node).  ``advance`` over several calls is bit-identical to one call."""

    def __init__(self, params: PlantParams | None = None, dt_s: float = 1e-6, seed: int = 0,
                 fluid=None):
        self.params = params if params is not None else default_params()
        self.fluid = fluid
        (self.fluid_fn, self.flows_fn, self.fluid_data,
         self.fluid_mode) = _fluid_args(fluid, self.params)
        check_dt(self.params, dt_s, fluid)
        self.dt_s = float(dt_s)
        self.dt_ns = dt_to_ns(dt_s)
        self.seed = int(seed)
        self.reset()

    def reset(self):
        self.state = initial_state(self.params)
        self._ctrl = np.zeros(3)
        self.steps = 0
        self.noise = NoiseSource(self.params.noise_std_a, self.params.noise_sample_time_s,
                                 self.seed)

    def set_params(self, params: PlantParams):
        """Change parameters (wear, degradation) from the next step on."""
        data = _fluid_args(self.fluid, params)[2]  # a dynamic surrogate's data per wear
        check_dt(params, self.dt_s, self.fluid)
        if (params.noise_std_a != self.params.noise_std_a
                or params.noise_sample_time_s != self.params.noise_sample_time_s):
            raise ParameterError('noise_std_a and noise_sample_time_s cannot change during a '
                                 'run')
        self.params = params
        self.fluid_data = data

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
        status, done, _, _ = _run(self.state, self._ctrl, float(current_command_a),
                                  self.params, 0, _EMPTY_ARGS, _EMPTY, _EMPTY, noise,
                                  self.params.noise_sample_time_s, self.steps, self.dt_s,
                                  self.dt_ns, int(n_steps), 0, 1, 0, _EMPTY.reshape(0, N_REC),
                                  self.fluid_fn, self.flows_fn, self.fluid_data,
                                  self.fluid_mode)
        self.steps += done
        if status:
            raise _diverged(status, self.time_s)

    def hold(self, n_steps: int) -> None:
        """Advance the clock ``n_steps`` steps with the actuator frozen (a valve test: the jack
        clamped, the valve on its test circuit, see :mod:`.valve_test`)."""
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
        return float(_pid(self._ctrl, float(command_m) - float(measured_m), self.period_s,
                          self._inv, self.params))


def simulate(params: PlantParams | None = None, scenario='step_0p1', duration_s=None,
             dt_s: float = 1e-6, seed: int = 0, controller_period_s: float | None = None,
             record_dt_s: float | None = 1e-4, fluid=None, events=None) -> SimResult:
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
    fluid : optional
        A surrogate of the fluid-dynamic block (:func:`eha_ros.surrogates.registry.load_surrogate`):
        algebraic, ``kernel(data, xs_m, q_m3_s, overlap_m, clearance_m) -> p12_pa``, or dynamic
        (``family = 'dynamic'``), the metering-edge flows only (see ``_run``); the
        high-fidelity block when ``None``.
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
    fluid_fn, flows_fn, fluid_data, fluid_mode = _fluid_args(fluid, p)
    check_dt(p, dt_s, fluid)
    dt_ns = dt_to_ns(dt_s)
    period = dt_s if controller_period_s is None else float(controller_period_s)
    steps_per_tick = int(round(period / dt_s))
    if steps_per_tick < 1 or abs(steps_per_tick * dt_s - period) > 1e-9 * period:
        raise ParameterError(f'controller_period_s = {period:g} s must be a whole multiple of '
                             f'dt_s = {dt_s:g} s')
    n_ticks = int(round(duration / period))
    if record_dt_s is None:
        rec_every = 1
    else:
        rec_every = max(1, int(round(record_dt_s / period)))
    # the run in segments of constant parameters: tick -> (parameters, fluid data) from it on
    if isinstance(events, EventSchedule):
        events = list(events)
    schedule = EventSchedule([(t, dict(changes)) for t, _, changes in sc.events]
                             + list(events or ()), period_ns=steps_per_tick * dt_ns)
    segments = {0: (p, fluid_data)}
    applied = []
    for ev, q in zip(schedule, schedule.validate(p)):
        k = schedule.tick_of(ev)
        if k < n_ticks:
            data = _fluid_args(fluid, q)[2]
            check_dt(q, dt_s, fluid)
            segments[k] = (q, data)
            applied.append({'tick': k, 'time_s': (k * steps_per_tick * dt_ns) * 1e-9,
                            'changes': ev.as_dict()})
    n_rows = n_ticks // rec_every + 2
    rec = np.full((n_rows, N_REC), np.nan)
    state = initial_state(p)
    ctrl = np.zeros(3)
    noise = NoiseSource(p.noise_std_a, p.noise_sample_time_s, seed)
    samples = noise.samples_until(n_ticks * steps_per_tick * dt_s)
    kind, args, com_t, com_v = sc.arrays()
    t0 = time.perf_counter()
    rows, i_cmd = 0, 0.0
    ends = list(segments)[1:] + [n_ticks]
    for (k0, (q, data)), k1 in zip(segments.items(), ends):
        n0 = k0 * steps_per_tick
        status, done, new_rows, i_cmd = _run(
            state, ctrl, i_cmd, q, kind, args, com_t, com_v, samples, p.noise_sample_time_s,
            n0, dt_s, dt_ns, (k1 - k0) * steps_per_tick, steps_per_tick, rec_every,
            -k0 % rec_every, rec[rows:], fluid_fn, flows_fn, data, fluid_mode)
        rows += new_rows
        if status:
            raise _diverged(status, ((n0 + done) * dt_ns) * 1e-9)
    wall = time.perf_counter() - t0
    if n_ticks % rec_every == 0:  # close the record with the final state
        t_end = (n_ticks * steps_per_tick * dt_ns) * 1e-9
        _record(rec, rows, t_end, sc.value(t_end), i_cmd, state, q)
        rows += 1
    data = {name: rec[:rows, j].copy() for j, name in enumerate(RECORD_FIELDS)}
    return SimResult(data=data, params=p, scenario=sc, dt_s=float(dt_s),
                     controller_period_s=steps_per_tick * dt_s, seed=int(seed),
                     wall_time_s=wall, events=applied)
