"""The pre-flight check by the split integrator against the explicit 1 us scheme, judged by
the pre-flight network against hf's own yardstick.

Prints one JSON object.  Cases: ``--n`` fleet checks (:func:`eha_ros.training.preflight.cases`,
``fleet``) from stream ``STREAM``, which nothing else draws from.  Each runs as the plant node
runs it (:func:`eha_ros.physics.maintenance.run_preflight`, one tick at a time) at the explicit
1 us step (the reference), and again by:

* hf's yardstick: the explicit scheme at half the step, and with the discharge coefficient
  +0.1 %;
* the split integrator at each of ``--split-dts``.

Per variant and fault: the shift of the network's estimate from the reference's, in units of
the reference's stated deviation (max and RMS over the cases), the largest change of the OOD
score, the cases whose refusal flips, and the wall time of the checks against the reference's
(``speedup``, one process, after a warm-up that compiles).  The reference also runs as the
plant node runs it, one kernel call per tick (``tick_by_tick``): its wall time against the one
call of :func:`run_preflight` (``speedup_of_one_call``) and whether every signal is the same
bit for bit.  With ``--converged-dt`` (default 50 ns) the check also runs at that explicit
step, converged in it, and every variant, the reference too, gets its shift from that
check's estimate (``shift_rms_vs_converged``, same unit): which of the two schemes is nearer
the plant's own solution.  The load averages come with it.

    python bench/preflight_integrator.py [--n 16] [--split-dts 1e-5,2e-5,2.5e-5]
        [--converged-dt 5e-8]
"""

import argparse
import json
import os
import time

import numpy as np

from eha_ros.health.preflight import CONDITION_READINGS, FAULT_NAMES, load_faults
from eha_ros.physics.bench import mean_conditions, measure_conditions
from eha_ros.physics.maintenance import (PREFLIGHT_SIGNALS, PREFLIGHT_TICK_S, PreflightCheck,
                                         run_preflight)
from eha_ros.physics.params import replace
from eha_ros.physics.plant import Plant
from eha_ros.physics.stability import DT_S
from eha_ros.training.preflight import case_params, cases

#: The stream of the bench's cases (used by nothing else).
STREAM = 611


def _variants(split_dts):
    """``name -> (dt_s, integrator, Cd factor)``: hf's yardstick, then the split steps."""
    out = {'explicit@dt=5e-07': (DT_S / 2, 'explicit', 1.0),
           'explicit@cd+0.1%': (DT_S, 'explicit', 1.001)}
    out.update({f'split@dt={d:g}': (d, 'split', 1.0) for d in split_dts})
    return out


def _check(p, seed, dt, integrator, cd_factor):
    if cd_factor != 1.0:
        p = replace(p, discharge_coefficient=p.discharge_coefficient * cd_factor)
    t = time.perf_counter()
    rec = run_preflight(p, seed=seed, dt_s=dt, integrator=integrator)
    return rec, time.perf_counter() - t


def _tick_by_tick(p, seed):
    """The reference check as the plant node steps it: one :meth:`Plant.advance` per tick."""
    t = time.perf_counter()
    check = PreflightCheck(int(round(PREFLIGHT_TICK_S * 1e9)), p.current_limit_a)
    plant = Plant(p, dt_s=DT_S, seed=seed)
    steps = int(round(PREFLIGHT_TICK_S / DT_S))
    out = {k: np.empty(check.n_ticks) for k in PREFLIGHT_SIGNALS}
    for k in range(check.n_ticks):
        plant.advance(float(check.command_a[k]), steps)
        snap = plant.snapshot()
        for name in PREFLIGHT_SIGNALS:
            out[name][k] = snap[name]
    return out, time.perf_counter() - t


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n', type=int, default=16, help='fleet checks')
    ap.add_argument('--split-dts', default='1e-5,2e-5,2.5e-5',
                    help='steps [s] of the split integrator (comma-separated)')
    ap.add_argument('--converged-dt', type=float, default=5e-8,
                    help='explicit step [s] of the converged check (0: none)')
    ap.add_argument('--smoke', action='store_true', help='one check at one step: a check')
    a = ap.parse_args(argv)
    split_dts = [float(x) for x in a.split_dts.split(',') if x.strip()]
    n = a.n
    if a.smoke:
        n, split_dts = 1, split_dts[:1]
    if n < 1:
        ap.error(f'--n {n}: at least one check')
    load_before = os.getloadavg()
    model = load_faults()
    variants = _variants(split_dts)
    conv_key = None
    if a.converged_dt > 0:
        conv_key = f'explicit@dt={a.converged_dt:g}'
        variants[conv_key] = (a.converged_dt, 'explicit', 1.0)
    case_list = cases(n, STREAM, fleet=True)
    p0 = case_params(case_list[0])
    for dt, integ in {(DT_S, 'explicit')} | {v[:2] for v in variants.values()}:
        run_preflight(p0, seed=0, dt_s=dt, integrator=integ)   # compiles (or loads) first
    shifts = {k: [] for k in variants}
    to_conv = {k: [] for k in ['reference', *variants]}
    ood = {k: [] for k in variants}
    flips = {k: 0 for k in variants}
    wall = {k: 0.0 for k in variants}
    wall_ref = 0.0
    wall_ticks = 0.0
    identical = True
    _tick_by_tick(p0, 0)
    for case in case_list:
        p, seed = case_params(case), case[1]
        cond = mean_conditions(measure_conditions(p, seed, CONDITION_READINGS))
        rec, w = _check(p, seed, DT_S, 'explicit', 1.0)
        wall_ref += w
        ticks, w = _tick_by_tick(p, seed)
        wall_ticks += w
        identical &= all(np.array_equal(ticks[k], rec[k]) for k in PREFLIGHT_SIGNALS)
        ref = model.estimate(rec, cond)
        est = {'reference': ref}
        for k, (dt, integ, cd) in variants.items():
            rec, w = _check(p, seed, dt, integ, cd)
            wall[k] += w
            e = est[k] = model.estimate(rec, cond)
            shifts[k].append([(e.values[f] - ref.values[f]) / ref.stds[f] for f in FAULT_NAMES])
            ood[k].append(e.ood_score - ref.ood_score)
            flips[k] += int(bool(e.mismatch) != bool(ref.mismatch))
        if conv_key:
            c = est[conv_key]
            for k, e in est.items():
                to_conv[k].append([(e.values[f] - c.values[f]) / ref.stds[f]
                                   for f in FAULT_NAMES])
    out = {'benchmark': 'preflight_integrator', 'stream': STREAM, 'checks': n,
           'reference': 'explicit, dt = 1e-06 s', 'reference_s_per_check': wall_ref / n,
           'tick_by_tick': {'s_per_check': wall_ticks / n,
                            'speedup_of_one_call': wall_ticks / wall_ref,
                            'identical': bool(identical)},
           'shift_unit': "the reference estimate's stated deviation", 'variants': {}}
    for k in variants:
        s = np.abs(np.array(shifts[k]))
        out['variants'][k] = {
            'shift_max': dict(zip(FAULT_NAMES, np.round(s.max(axis=0), 4).tolist())),
            'shift_rms': dict(zip(FAULT_NAMES,
                                  np.round(np.sqrt((s ** 2).mean(axis=0)), 4).tolist())),
            'ood_score_shift_max': float(np.max(np.abs(ood[k]))),
            'refusal_flips': flips[k],
            'speedup': wall_ref / wall[k]}
    if conv_key:
        out['converged'] = conv_key
        out['shift_rms_vs_converged'] = {
            k: dict(zip(FAULT_NAMES, np.round(np.sqrt((np.array(v) ** 2).mean(axis=0)),
                                              4).tolist())) for k, v in to_conv.items()}
    out.update(load_before=load_before, load_after=os.getloadavg(), smoke=bool(a.smoke))
    print(json.dumps(out, indent=1))
    return out


if __name__ == '__main__':
    main()
