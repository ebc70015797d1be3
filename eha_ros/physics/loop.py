"""The plant's fixed-step kernel: :func:`advance` moves the state on by a number of steps, open
or closed loop, with the high-fidelity fluid block or a surrogate's kernel, and :func:`run`
calls its compiled forms; :class:`FluidBlock`, what a surrogate provides to be that kernel.

Named ``loop`` for the time loop it holds (and the closed loop it may run): its arguments are
grouped in named tuples (numba tuples): :class:`Clock` (which steps, of what length, under
which noise), :class:`ClosedLoop` (controller, command and record; :data:`OPEN_LOOP` for the
coil current held); a surrogate's kernel comes in the place of what it gives (``None`` for the
high-fidelity block: a ``None`` argument removes its branches when the kernel is compiled).
An open and a closed loop share one compiled kernel (per fluid block).
"""

from __future__ import annotations

from collections import namedtuple
from typing import Callable, Protocol, runtime_checkable

import numpy as np
from numba import njit

from .commands import command_value
from .jack import jack_step, jack_step_trapezoid, quantise, surface_position
from .params import ParameterError, PlantParams
from .servovalve import (coil_current, flapper_damping, flapper_step, spool_gains, spool_step,
                         torque_motor_force)
from .state import (N_REC, S_FTM, S_ICOIL, S_P1, S_P1T, S_P2, S_P2T, S_PLAY, S_Q1L, S_Q2L,
                    S_QJ, S_SURF, S_VF, S_VJ, S_VS, S_XF, S_XJ, S_XS, STATE_NAMES)
from .valve import (chamber_step, chamber_step_implicit, net_flow, net_flow_conductance,
                    valve_coefficients, valve_constants)

__all__ = ['Clock', 'ClosedLoop', 'OPEN_LOOP', 'P12', 'CHAMBER_FLOWS', 'FluidBlock',
           'fluid_kernels', 'advance', 'run', 'pid', 'record',
           'SimulationDiverged', 'diverged']

# state entries watched for divergence, in the order they are reported
_WATCHED = (S_XF, S_VF, S_XS, S_P1T, S_P2T, S_XJ, S_VJ)
_DIVERGED_ABS = 1e12  # any watched state beyond this (in SI units) has diverged


class SimulationDiverged(RuntimeError):
    """A state became NaN, infinite or absurdly large."""


def diverged(status: int, t_s: float) -> SimulationDiverged:
    """The error for a non-zero ``status`` of :func:`run` at time ``t_s``."""
    name = STATE_NAMES[_WATCHED[status - 1]]
    return SimulationDiverged(f'simulation diverged: state {name} became non-finite or '
                              f'exceeded {_DIVERGED_ABS:g} at t = {t_s:.6g} s')


#: ``n_steps`` steps from the global step ``n0``, of ``dt`` s (``dt_ns`` whole ns), under the
#: noise samples ``noise[k]`` (:class:`.plant.NoiseSource`), each over ``[k, k+1) noise_dt``,
#: by the integrator ``substeps`` (0: explicit; ``m >= 1``: split, events in ``m`` substeps;
#: see :func:`run`).
Clock = namedtuple('Clock', 'n0 n_steps dt dt_ns noise noise_dt substeps')
#: The controller (state ``ctrl``, see :func:`pid`) every ``steps_per_tick`` steps against the
#: command ``(kind, args, com_t, com_v)``; every ``rec_every``-th tick, the first after
#: ``rec_wait`` unrecorded ticks, recorded into ``rec`` from its row 0.  An empty ``ctrl``: no
#: controller, the command is the coil current command itself [A] (a scripted current, as a
#: check drives the valve: :meth:`.plant.Plant.advance_currents`).
ClosedLoop = namedtuple('ClosedLoop', 'ctrl kind args com_t com_v steps_per_tick rec_every '
                        'rec_wait rec')
#: The open loop: no controller ticks, nothing recorded (the arrays are never read).
OPEN_LOOP = ClosedLoop(np.zeros(3), 0, np.zeros(8), np.zeros(0), np.zeros(0), 0, 1, 0,
                       np.zeros((0, N_REC)))


#: ``kernel_output`` of an algebraic surrogate:
#: ``kernel(data, xs_m, q_m3_s, overlap_m, clearance_m) -> P12 [Pa]``.
P12 = 'p12'
#: ``kernel_output`` of a dynamic surrogate:
#: ``kernel(data, xs_m, p1_pa, p2_pa, lap_supply_m, lap_return_m) -> (Q1L, Q2L) [m^3/s]``.
CHAMBER_FLOWS = 'chamber_flows'


@runtime_checkable
class FluidBlock(Protocol):
    """A surrogate of the fluid-dynamic block, as the plant calls it.

    Optionally also ``loops``: its own ``(explicit, split)`` compiled forms of the loop
    (:func:`fluid_kernels`), so that the plant's kernel with it loads from the disk cache.
    """

    name: str
    #: the numba kernel, called inside the plant's loop (signature after ``kernel_output``)
    kernel: Callable
    #: :data:`P12` or :data:`CHAMBER_FLOWS`
    kernel_output: str

    def prepare(self, p: PlantParams) -> tuple:
        """The kernel's data for the parameters ``p``; ValueError if it refuses them."""

    def stability_limit(self, p: PlantParams) -> tuple[float, str]:
        """``(dt_s, reason)``: the largest stable step under this block's feedback, in place
        of the high-fidelity chamber bound."""

    def check_params(self, p: PlantParams) -> None:
        """Refuse parameters the block was not built for (ValueError)."""


def fluid_kernels(fluid: FluidBlock | None, p: PlantParams) -> tuple:
    """``(p12_fn, flows_fn, data, loops)`` of :func:`run` for ``fluid`` at the parameters
    ``p``: its kernel in the place its ``kernel_output`` names (``None`` in the other), the
    kernel's data and the block's optional ``loops`` (its own compiled forms, :func:`run`);
    ``(None, None, (), None)`` for the high-fidelity block (``fluid`` ``None``)."""
    if fluid is None:
        return None, None, (), None
    if not isinstance(fluid, FluidBlock) or fluid.kernel_output not in (P12, CHAMBER_FLOWS):
        raise ParameterError(f'fluid must be a FluidBlock with kernel_output {P12!r} or '
                             f'{CHAMBER_FLOWS!r}')
    try:
        data = tuple(fluid.prepare(p))
    except ValueError as exc:  # a surrogate refusing these parameters
        raise ParameterError(str(exc)) from None
    loops = getattr(fluid, 'loops', None)
    if loops is not None and (len(loops) != 2 or not all(callable(f) for f in loops)):
        raise ParameterError(f'fluid {fluid.name!r}: loops must be None or two compiled '
                             'forms (explicit, split)')
    if fluid.kernel_output == P12:
        return fluid.kernel, None, data, loops
    return None, fluid.kernel, data, loops


@njit(cache=True, inline='always')
def pid(ctrl, error, period, inv_period, p):
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
def record(rec, row, t, r, i_cmd, s, p):
    """Row ``row`` of ``rec`` (:data:`.state.RECORD_FIELDS`) at time ``t``, command ``r``."""
    values = (t, r, i_cmd, s[S_ICOIL], s[S_FTM], s[S_XF], s[S_XS], s[S_P1], s[S_P2],
              s[S_P1] - s[S_P2], s[S_QJ], s[S_XJ], s[S_VJ], s[S_SURF],
              quantise(s[S_SURF], p.sensor_resolution_m))
    for k in range(len(values)):
        rec[row, k] = values[k]


@njit(cache=True)
def _save(s, *values):
    """``s[:] = values``, given in the order of :data:`.state.STATE_NAMES`."""
    for k in range(len(values)):
        s[k] = values[k]


# _step and _event take the state as scalars, not as an array or a tuple, so that numba,
# inlining them into the loop, keeps every state in a register from step to step.
@njit(cache=True, inline='always')
def _step(y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, i_cmd, noise_a, p, c, p12_fn,
          flows_fn, data, dt, split):
    """One step of the plant (see :func:`run`): explicit, or with ``split`` the jack and its
    chambers as a Stormer-Verlet pair with linearly implicit pressures; ``c`` the
    step-independent constants of :func:`_constants`.  Returns the new state (in the order
    of :data:`.state.STATE_NAMES`)."""
    cf, drive, c_eq, kvol, ps, pr, pvap, aj, clk, vc, lap, lap_r, clr, pmid = c
    g1 = 0.0
    g2 = 0.0
    y, i = coil_current(y, i_cmd, noise_a, p)
    f = torque_motor_force(i, xf, p)
    if p12_fn is not None:
        qj = aj * vj
        q1l = qj
        q2l = qj
        p12 = p12_fn(data, xs, qj, lap, clr)
        p1 = pmid + 0.5 * p12
        p2 = pmid - 0.5 * p12
    else:
        if flows_fn is not None:
            q1l, q2l = flows_fn(data, xs, p1, p2, lap, lap_r)
        else:
            (rl1s, bl1s, r41s, rl1r, bl1r, r41r,
             rl2s, bl2s, r42s, rl2r, bl2r, r42r) = valve_coefficients(xs, vc)
            if split:  # with the chambers' conductances, for their linearly implicit step
                q1l, g1 = net_flow_conductance(ps - p1, rl1s, bl1s, r41s, p1 - pr, rl1r, bl1r,
                                               r41r)
                q2l, g2 = net_flow_conductance(p2 - pr, rl2r, bl2r, r42r, ps - p2, rl2s, bl2s,
                                               r42s)
            else:
                q1l = net_flow(ps - p1, rl1s, bl1s, r41s, p1 - pr, rl1r, bl1r, r41r)
                q2l = net_flow(p2 - pr, rl2r, bl2r, r42r, ps - p2, rl2s, bl2s, r42s)
        qj = 0.5 * (q1l + q2l)
        p12 = p1 - p2
    xs_old = xs
    xs, vs = spool_step(xs, vs, xf, qj, drive, c_eq, p, dt)
    xf, vf = flapper_step(xf, vf, xs_old, f, cf, p, dt)
    if not split:  # every derivative from the state at the start of the step
        qm = aj * vj + clk * p12
        xj, vj = jack_step(xj, vj, p12, p, dt)
        if p12_fn is not None:
            p1t = p1  # the surrogate's pressures at the start of this step
            p2t = p2
        else:
            p1t, p2t, p1, p2 = chamber_step(p1t, p2t, q1l, q2l, qm, kvol, pvap, dt)
    elif p12_fn is not None:
        xj, vj = jack_step_trapezoid(xj, vj, p12, p, dt)
        p1t = p1
        p2t = p2
    else:
        # the jack and its chambers as a Stormer-Verlet pair: the pressures half a step on
        # with the jack's velocity at the start, the jack a whole step on that load pressure
        # (its position by the trapezoid rule), the pressures the whole step with the volume
        # the jack swept; each pressure linearly implicit in itself (a dynamic surrogate's
        # conductance is not known: 0, its chambers then explicit but for the leakage)
        r1 = kvol * (g1 + clk)
        r2 = kvol * (g2 + clk)
        qm = aj * vj + clk * p12
        _, _, ph1, ph2 = chamber_step_implicit(p1t, p2t, q1l, q2l, qm, kvol, pvap,
                                               0.5 * dt, r1, r2)
        p12h = ph1 - ph2
        xj_old = xj
        xj, vj = jack_step_trapezoid(xj, vj, p12h, p, dt)
        qm = aj * (xj - xj_old) / dt + clk * p12h
        p1t, p2t, p1, p2 = chamber_step_implicit(p1t, p2t, q1l, q2l, qm, kvol, pvap, dt, r1,
                                                 r2)
    surf = surface_position(surf, xj, p)
    return y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f, q1l, q2l


@njit(cache=True, inline='always')
def _event(xf, vf0, vf, xs, vs0, vs, xj, vj0, vj, p1, p2, qj, c, p):
    """Whether a step from the velocities ``*0`` to the state given holds an event whose
    instant the step cannot place: a friction transition of the spool or the jack (stuck to
    moving, moving to stopped), a body at its end stop, or a stuck body whose active force
    at the end of the step exceeds its breakaway friction (it breaks away within the step,
    though the explicit step, which evaluates the force at its start, keeps it stuck)."""
    if (vs0 == 0.0) != (vs == 0.0) or (vj0 == 0.0) != (vj == 0.0):
        return True
    if (abs(xs) >= p.spool_stroke_m or abs(xj) >= p.jack_stroke_m
            or abs(xf) >= p.flapper_stroke_m):
        return True
    if vj == 0.0:
        f = ((p1 - p2) * c[7] - p.aero_stiffness_n_m * xj - p.external_force_n)
        if abs(f) > p.jack_static_friction_n:
            return True
    if vs == 0.0:
        f = c[1] * xf - p.flow_force_coeff_n_s_m3 * qj
        if abs(f) > p.spool_static_friction_n:
            return True
    return False


@njit(cache=True, inline='always')
def _constants(p):
    """The step-independent constants of :func:`_step`."""
    drive, c_eq = spool_gains(p)
    ps = p.supply_pressure_pa
    pr = p.return_pressure_pa
    return (flapper_damping(p), drive, c_eq, p.bulk_modulus_pa / p.chamber_volume_m3, ps, pr,
            p.vapour_pressure_pa, p.jack_area_m2, p.leakage_coeff_m3_s_pa, valve_constants(p),
            p.overlap_supply_m, p.overlap_return_m, p.radial_clearance_m, 0.5 * (ps + pr))


@njit(inline='always')
def advance(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data, split):
    """Advance the plant state ``s`` (in place) by ``clock.n_steps`` steps of ``clock.dt``.

    Fluid block (:func:`fluid_kernels`): the high-fidelity one when both kernels are
    ``None``.  ``p12_fn`` (an algebraic surrogate): the block is replaced by ``P12 =
    p12_fn(data, XS, QJ, overlap, clearance)`` with the load flow imposed by the jack, ``QJ =
    AJ dXJ/dt``; P1, P2 are then reported as mid-pressure +- P12/2.  ``flows_fn`` (a dynamic
    surrogate): only the metering-edge flows come from the surrogate, ``(Q1L, Q2L) =
    flows_fn(data, XS, P1, P2, OSSV, ORSV)``; chambers, leakage, cavitation clip and jack stay
    the high-fidelity ones.  (The kernels and their data are arguments of their own, not a
    tuple's: numba types a tuple of arrays at a call much faster than a named tuple.)

    Integrator (``clock.substeps``, :func:`.stability.integrator_substeps`):

    * ``0``, explicit (the reference's scheme): every derivative from the state at the start
      of the step, as a fixed-step ode1 solver evaluates a block diagram; the two
      second-order bodies update velocity before position.
    * ``m >= 1``, split: the electromechanics as above; the jack and its two chambers as a
      Stormer-Verlet pair (pressures half a step with the jack's velocity at the start, the
      jack a step on that load pressure with its position by the trapezoid rule, the
      pressures a step with the volume the jack swept), each chamber pressure linearly
      implicit in itself (its valve conductance and leakage: Rosenbrock-Euler on the
      diagonal, so the chambers set no step bound); and a step that holds an event it cannot
      place (:func:`_event`: a friction transition, an end stop, a breakaway due within the
      step) is taken again from its start as ``m`` such steps of ``dt / m``.  Why (measured,
      ``bench/inloop.py``): the smooth model is not stiff along the runs (largest
      eigenvalue of the frictionless Jacobian about 5.3e3 1/s), but the forward-Euler
      coupling of jack and chambers gains energy in the hydraulic spring, about
      ``(w_h dt)^2`` per step, which at 10 us lengthens every stick-slip slide by about 1 %;
      friction sticking then turns that into a different hold.

    ``loop`` :data:`OPEN_LOOP`: the coil current command ``i_cmd`` is held.  Otherwise the
    controller runs every ``loop.steps_per_tick`` steps on the quantised sensor and the
    ticks are recorded as :class:`ClosedLoop` says, each before the plant moves on.

    The time of step ``n`` is ``(n dt_ns) 1e-9`` s, from the integer nanoseconds a ROS clock
    carries, so the graph evaluates commands at the same times bit for bit.  Returns
    ``(status, steps done, rows recorded, i_cmd)``: status 0, or 1 + the index into
    ``_WATCHED`` of the first state that diverged.

    Inlined into its compiled forms, explicit or split with ``split`` a constant of each
    (:func:`run`).
    """
    # everything out of the tuples once, before the loop (an array taken from a tuple is
    # reference-counted at each access)
    n0, n_steps, dt, dt_ns, noise, noise_dt, substeps = clock
    ctrl, kind, args, com_t, com_v, steps_per_tick, rec_every, rec_wait, rec = loop
    c = _constants(p)
    q = p.sensor_resolution_m
    steps_per_noise = dt / noise_dt
    sub_dt = dt / max(substeps, 1)
    subs_per_noise = sub_dt / noise_dt
    # the state read element by element: unpacking the array (``y, xf, ... = s``) made the
    # loop 15 % slower with the 1 kHz controller (bench/plant_rtf.py --against d4243cf)
    y, xf, vf, xs, vs, p1t = s[S_PLAY], s[S_XF], s[S_VF], s[S_XS], s[S_VS], s[S_P1T]
    p2t, p1, p2, xj, vj, surf = s[S_P2T], s[S_P1], s[S_P2], s[S_XJ], s[S_VJ], s[S_SURF]
    qj, i, f, q1l, q2l = s[S_QJ], s[S_ICOIL], s[S_FTM], s[S_Q1L], s[S_Q2L]
    status = 0
    done = 0
    row = 0
    period = steps_per_tick * dt
    inv_period = 1.0 / period if steps_per_tick > 0 else 0.0
    until_tick = 0
    until_rec = rec_wait
    for j in range(n_steps):
        n = n0 + j
        if steps_per_tick > 0:
            if until_tick == 0:
                until_tick = steps_per_tick
                t = (n * dt_ns) * 1e-9
                r = command_value(kind, args, com_t, com_v, t)
                if ctrl.size > 0:
                    i_cmd = pid(ctrl, r - quantise(surf, q), period, inv_period, p)
                else:  # no controller: the command is the current
                    i_cmd = r
                if until_rec == 0:
                    until_rec = rec_every
                    _save(s, y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f,
                          q1l, q2l)
                    record(rec, row, t, r, i_cmd, s, p)
                    row += 1
                until_rec -= 1
            until_tick -= 1
        k = int(n * steps_per_noise)
        (y1, xf1, vf1, xs1, vs1, p1t1, p2t1, p11, p21, xj1, vj1, surf1, qj1, i1, f1, q1l1,
         q2l1) = _step(y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, i_cmd, noise[k], p,
                       c, p12_fn, flows_fn, data, dt, split)
        # ``split`` first: a constant of each compiled form, so the explicit form holds no
        # substep code (bench/plant_rtf.py --against: 10 % faster with the 1 kHz controller)
        if split and substeps > 1 and _event(xf1, vf, vf1, xs1, vs, vs1, xj1, vj, vj1, p11,
                                             p21, qj1, c, p):
            for m in range(substeps):
                k = int((n * substeps + m) * subs_per_noise)
                (y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f, q1l,
                 q2l) = _step(y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, i_cmd,
                              noise[k], p, c, p12_fn, flows_fn, data, sub_dt, True)
        else:
            (y, xf, vf, xs, vs, p1t, p2t, p1, p2, xj, vj, surf, qj, i, f, q1l,
             q2l) = (y1, xf1, vf1, xs1, vs1, p1t1, p2t1, p11, p21, xj1, vj1, surf1, qj1, i1,
                     f1, q1l1, q2l1)
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


# The high-fidelity block's two compiled forms (cached on disk: every argument is typed by its
# value) and the fallback forms of a kernel passed in an argument (not cached, see advance).

@njit(cache=True)
def _run_hf(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data):
    return advance(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data, False)


@njit(cache=True)
def _run_split_hf(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data):
    return advance(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data, True)


@njit
def _run_kernel(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data):
    return advance(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data, False)


@njit
def _run_split_kernel(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data):
    return advance(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data, True)


def run(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data, loops=None):
    """The plant's kernel (:func:`advance`), explicit or split as ``clock.substeps`` says, by
    compiled forms cached on disk (a process loads them: compiling takes tens of seconds): the
    high-fidelity block's (both kernels ``None``), or a surrogate's own ``loops``
    (``(explicit, split)``, each ``form(s, i_cmd, p, clock, loop, data)``;
    :data:`eha_ros.surrogates.base.Forms`).
    Any other kernel is typed by its object, so an entry keyed by it would never match in
    another process and breaks the saving of the cache index: its forms are not cached."""
    split = clock.substeps > 0
    if loops is not None:
        return loops[split](s, i_cmd, p, clock, loop, data)
    if p12_fn is None and flows_fn is None:
        form = _run_split_hf if split else _run_hf
    else:
        form = _run_split_kernel if split else _run_kernel
    return form(s, i_cmd, p, clock, loop, p12_fn, flows_fn, data)
