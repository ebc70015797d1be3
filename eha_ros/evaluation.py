"""Surrogates in the closed loop against the high-fidelity (hf) plant, judged against hf's own
sensitivity (the yardstick): the measurement behind ``bench/inloop.py`` and the comparison part
of ``eha-campaign``.  Physics only (:func:`eha_ros.physics.simulate`), controller at 1 kHz,
every tick recorded.

Noise-free (torque-motor noise off, so differences are model differences), per case = scenario
x wear point (:func:`noise_free`):

* ``jack`` / ``p12``: relative Euclidean-norm error (:func:`.base.relative_error`) of the jack
  position / load pressure against hf at dt = 1 us;
* ``yardstick``: the largest change of hf itself under perturbations no surrogate could
  resolve: hf at half the step (0.5 us) and hf with the discharge coefficient changed by up to
  +-0.1 % (:data:`CD_STEPS`: the interval sampled, not only its ends);
* bounds: ``jack <= max(1 %, 2 x yardstick)`` and ``p12 <= max(5 %, 2 x yardstick)``;
* features a user reads off the plots (:func:`features`), each model's deviation from hf
  beside the yardstick's spread (the largest deviation of the perturbed hf runs).

With noise (:func:`with_noise`): each model with seed k against hf with seed k, averaged over
the seeds, beside hf's seed-to-seed spread (hf seed k against hf seed k+1, averaged); goal:
model error <= 1.5 x spread.  Every mean comes with its standard error: on small-signal holds
these errors are heavy-tailed (a late stick-slip step happens in one run and not in the other:
on ``step_0p1`` single pairs of hf seeds differ by 0.1-19 % in P12), so a mean over few seeds is
itself uncertain by tens of percent and the comparison needs many seeds (``bench/inloop.py``
runs 20).

Larger steps (``large_dts``): the dynamic surrogates, and hf itself as the control, at steps
above 1 us against hf at 1 us with the same bounds, so the largest step at which a plant stays
stable and accurate is measured, not assumed (:func:`largest_steps`).

Integrators (``split_dts``): hf and the dynamic surrogates also by the ``split`` integrator
(:func:`eha_ros.physics.loop.advance`) at each of these steps, keys ``'<model>@split@dt=<step>'``,
against the same hf at 1 us (explicit) with the same bounds; :func:`largest_steps` gives the
largest step of each (model, integrator).

Converged reference (``converged_dt``): hf explicit at a far smaller step (``bench/inloop.py``:
10 ns), the plant's own solution with the step's error gone.  hf at 1 us is itself a
first-order solution: where the loop is chaotic (a stuck jack within nanometres of half a
sensor quantum, a breakaway that comes a tick sooner or later) its step error alone can exceed
the bounds, and a more accurate integrator is then judged wrong for being closer to the
solution.  So every run is also compared with the converged hf, under the same bounds
(``models[...]['converged']``; hf at 1 us itself under ``converged['hf']``), and the converged
run is checked against hf at twice its step (``converged['check']``; ``settled`` where that
moves it by at most :data:`SETTLED_FRACTION` of each bound, so that the comparison does not
rest on an unconverged reference).  :func:`converged_summary` counts the cases.

Cost: wall seconds per simulated second of every run against hf's.
"""

from __future__ import annotations

import itertools

import numpy as np

from eha_ros.graph import DYNAMIC_MODELS
from eha_ros.physics import simulate
from eha_ros.physics.params import replace
from eha_ros.physics.stability import DT_S, EXPLICIT, SPLIT

from eha_ros.surrogates.base import relative_error

#: The cases beyond the reference's nine: two large signals (1 mm and 0.3 mm steps) and a
#: chirp.  (The reference's nine include the small signals, run at every wear point.)
EXTRA_SCENARIOS = ('step_1mm', 'step_0p3mm', 'chirp_0p1')
#: Wear points (overlap of both edges, clearance) [m] of the in-loop comparison: nominal; two
#: off the grids of every table (the algebraic tables' DB1 grid, 2 um / 1.25 um steps; the
#: dynamic table's log-spaced clearance); six drawn at random, uniformly over the whole
#: range the plant accepts for the dynamic surrogates (``WEAR_RANGES``: overlap -2..6 um,
#: clearance 1..6 um), by ``rng = np.random.default_rng(2026)``, overlaps
#: ``rng.uniform(-2e-6, 6e-6, 6)`` then clearances ``rng.uniform(1e-6, 6e-6, 6)``; and two
#: worn holds, where a 1 mm step ends with the jack stuck a sensor quantum from the command
#: and hf's own hold pressure flips by a third between two sticking points under a change of
#: Cd of 5e-5 (the yardstick, not a surrogate, sets the P12 bound there): ``worn_hold`` at
#: overlap 0.3 um, clearance 3.7 um, and ``worn_hold_b`` drawn over the worn corner (overlap
#: -0.5..1 um, clearance 3..6 um) by ``rng = np.random.default_rng([0x40D1, 2])``, overlaps
#: ``rng.uniform(-0.5e-6, 1e-6, 8)`` then clearances ``rng.uniform(3e-6, 6e-6, 8)``, the
#: fourth pair.  All rounded to 0.01 um and written out (so they never move with numpy's
#: generator).
WEAR_POINTS = {'nominal': None, 'worn_a': (3.1e-6, 3.9e-6), 'worn_b': (-0.7e-6, 1.6e-6),
               'rand_1': (-0.57e-6, 5.53e-6), 'rand_2': (3.12e-6, 1.89e-6),
               'rand_3': (1.74e-6, 4.26e-6), 'rand_4': (0.96e-6, 2.49e-6),
               'rand_5': (0.84e-6, 5.83e-6), 'rand_6': (4.32e-6, 5.6e-6),
               'worn_hold': (0.3e-6, 3.7e-6), 'worn_hold_b': (0.14e-6, 4.08e-6)}
CONTROLLER_PERIOD_S = 1e-3
#: Relative changes of the discharge coefficient in hf's yardstick, each of both signs: the
#: interval +-0.1 % sampled at three magnitudes.  Where the loop is chaotic (a stick-slip
#: episode that comes or not on a rounding) hf's response is not monotonic in Cd, and the ends
#: of the interval alone can understate hf's own sensitivity by an order of magnitude.
CD_STEPS = (2e-4, 5e-4, 1e-3)
#: Jack displacement per controller tick [m] below which the jack counts as stuck (1 nm per
#: ms = 1 um/s; the sensor quantum is 1 um).
STUCK_M = 1e-9
#: The converged reference is ``settled`` in a case where hf at twice its step is within this
#: fraction of each bound of it.
SETTLED_FRACTION = 0.1


def features(r) -> dict:
    """What a user reads off the plots of a run (``r`` a :class:`SimResult` recorded every
    tick).

    ``rms_tracking_error_m``: RMS of command minus jack position (the loop's accuracy);
    ``final_position_m``: jack position at the end (where a small command leaves it, within
    the friction band); ``stick_slip_steps``: number of motion episodes (runs of ticks in which
    the jack moves more than :data:`STUCK_M`) - a jerky small-signal response is a sequence of
    them; ``mean_step_m``: mean displacement per episode; ``p12_rms_pa``, ``p12_peak_pa``: RMS
    and largest magnitude of the load pressure (the force the jack makes).
    """
    x = r['jack_position_m']
    moving = np.abs(np.diff(x)) > STUCK_M
    starts = np.flatnonzero(moving & ~np.concatenate([[False], moving[:-1]]))
    ends = np.flatnonzero(moving & ~np.concatenate([moving[1:], [False]]))
    steps = np.abs(x[ends + 1] - x[starts]) if starts.size else np.zeros(0)
    p12 = r['p12_pa']
    return {'rms_tracking_error_m': float(np.sqrt(np.mean((r['command_m'] - x) ** 2))),
            'final_position_m': float(x[-1]),
            'stick_slip_steps': int(starts.size),
            'mean_step_m': float(steps.mean()) if steps.size else 0.0,
            'p12_rms_pa': float(np.sqrt(np.mean(p12 ** 2))),
            'p12_peak_pa': float(np.max(np.abs(p12)))}


def run(p, scenario, fluid=None, dt=DT_S, seed=0, integrator=EXPLICIT):
    """One closed-loop run as the comparison makes it (controller 1 kHz, every tick)."""
    return simulate(p, scenario, dt_s=dt, seed=seed, controller_period_s=CONTROLLER_PERIOD_S,
                    record_dt_s=None, fluid=fluid, integrator=integrator)


def model_integrator(name: str) -> tuple:
    """``(model, integrator)`` of a model name with an optional ``@split``: ``'hf@split'`` is
    hf by the split integrator, ``'dlut'`` dlut by the explicit one."""
    base, sep, integ = name.partition('@')
    if not sep:
        return name, EXPLICIT
    if integ != SPLIT:
        raise ValueError(f'model {name!r}: {integ!r} is not an integrator (only @{SPLIT})')
    return base, SPLIT


def _errors(r, ref) -> dict:
    return {'jack': relative_error(r['jack_position_m'], ref['jack_position_m']),
            'p12': relative_error(r['p12_pa'], ref['p12_pa'])}


def _cost(r) -> float:
    return r.wall_time_s / float(r.t[-1])


def model_result(jack, p12, meets, f, f_ref, spread, cost) -> dict:
    """One model's entry of :func:`noise_free`'s ``models``: its errors ``jack`` and ``p12``,
    whether they ``meets`` the bounds, its features ``f`` and their deviation from hf's
    ``f_ref`` against the yardstick's ``spread`` (within it, within twice it) and its
    ``cost`` [wall s per simulated s]."""
    dev = {k: abs(f[k] - f_ref[k]) for k in f}
    return {'jack': jack, 'p12': p12, 'meets': meets, 'features': f,
            'feature_deviation': dev,
            'features_within_spread': {k: bool(dev[k] <= spread[k] * (1 + 1e-9)) for k in dev},
            'features_within_2x_spread': {k: bool(dev[k] <= 2 * spread[k] + 1e-30)
                                          for k in dev},
            'cost_s_per_s': cost}


def _against(r, ref, bound) -> dict:
    e = _errors(r, ref)
    return {**e, 'meets': bool(e['jack'] <= bound['jack'] and e['p12'] <= bound['p12'])}


def noise_free(p, scenario, surrogates, large_dts=(), keep_runs=False, split_dts=(),
               converged_dt=None):
    """One case: hf, the yardstick runs and every surrogate (``{name: surrogate}``), at the
    parameters ``p`` (noise should be off); hf and the dynamic surrogates also at each step of
    ``large_dts`` [s] (keys ``'<model>@dt=<step>'``) and by the split integrator at each step
    of ``split_dts`` (keys ``'<model>@split@dt=<step>'``); with ``converged_dt`` [s] every run
    also against hf explicit at that step (module docstring).  With ``keep_runs`` the
    :class:`SimResult` objects are returned under ``'runs'`` (for plots)."""
    ref = run(p, scenario)
    cd = p.discharge_coefficient
    pert = {'half_step': run(p, scenario, dt=0.5 * DT_S)}
    for step in CD_STEPS:
        for sign, tag in ((1.0, 'plus'), (-1.0, 'minus')):
            pert[f'cd_{tag}_{100 * step:g}%'] = run(
                replace(p, discharge_coefficient=cd * (1.0 + sign * step)), scenario)
    f_ref = features(ref)
    yard = {k: _errors(r, ref) for k, r in pert.items()}
    yard_jack = max(v['jack'] for v in yard.values())
    yard_p12 = max(v['p12'] for v in yard.values())
    f_pert = {k: features(r) for k, r in pert.items()}
    spread = {f: max(abs(fp[f] - f_ref[f]) for fp in f_pert.values()) for f in f_ref}
    out = {'yardstick': {'jack': yard_jack, 'p12': yard_p12, 'runs': yard,
                         # the bound is hf's own sensitivity, not the floor, where these hold
                         'sets_bound': {'jack': 2 * yard_jack > 0.01,
                                        'p12': 2 * yard_p12 > 0.05}},
           'bound': {'jack': max(0.01, 2 * yard_jack), 'p12': max(0.05, 2 * yard_p12)},
           'hf_features': f_ref, 'feature_spread': spread,
           'hf_cost_s_per_s': _cost(ref), 'models': {}}
    kept = {'hf': ref, **pert}
    conv = None
    if converged_dt is not None:
        conv = run(p, scenario, dt=float(converged_dt))
        check = _against(run(p, scenario, dt=2.0 * float(converged_dt)), conv,
                         {q: SETTLED_FRACTION * b for q, b in out['bound'].items()})
        out['converged'] = {'dt_s': float(converged_dt), 'hf': _against(ref, conv, out['bound']),
                            'check': {q: check[q] for q in ('jack', 'p12')},
                            'settled': check['meets']}
    for name, s in [('hf', None)] + list(surrogates.items()):
        runs = {} if name == 'hf' else {name: (None, EXPLICIT)}
        if name == 'hf' or name in DYNAMIC_MODELS:
            runs.update({f'{name}@dt={dt:g}': (float(dt), EXPLICIT) for dt in large_dts})
            runs.update({f'{name}@{SPLIT}@dt={dt:g}': (float(dt), SPLIT) for dt in split_dts})
        for key, (dt, integ) in runs.items():
            try:
                r = run(p, scenario, s, dt=dt or DT_S, integrator=integ)
            except Exception as exc:  # a diverging or refused run is a result too
                out['models'][key] = {'error': f'{type(exc).__name__}: {exc}'}
                continue
            kept[key] = r
            e = _against(r, ref, out['bound'])
            out['models'][key] = model_result(e['jack'], e['p12'], e['meets'], features(r),
                                              f_ref, spread, _cost(r))
            if conv is not None:
                out['models'][key]['converged'] = _against(r, conv, out['bound'])
    if keep_runs:
        out['runs'] = kept
    return out


def mean_sem(errs) -> dict:
    """Mean of each quantity over the seeds with its standard error (``_sem``) and the values."""
    out = {}
    for q in ('jack', 'p12'):
        v = np.array([e[q] for e in errs])
        out[q] = float(v.mean())
        out[f'{q}_sem'] = float(v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else None
        out[f'{q}_per_seed'] = [float(x) for x in v]
    return out


def with_noise(p, scenario, surrogates, seeds=5):
    """hf's seed-to-seed spread and each model's error against hf with the same seed, at the
    parameters ``p`` (noise on), seeds ``0 .. seeds - 1`` (hf also ``seeds``); every mean with
    its standard error.  For reference also hf with the discharge coefficient +0.1 % against
    hf, same seeds: how far a perturbation no model could resolve moves hf under the same
    noise."""
    hf = [run(p, scenario, seed=k) for k in range(seeds + 1)]
    spread = [_errors(hf[k + 1], hf[k]) for k in range(seeds)]
    pc = replace(p, discharge_coefficient=p.discharge_coefficient * 1.001)
    same = [_errors(run(pc, scenario, seed=k), hf[k]) for k in range(seeds)]
    out = {'seeds': int(seeds), 'hf_seed_to_seed': mean_sem(spread),
           'hf_cd_plus_0.1%_same_seed': mean_sem(same), 'models': {}}
    limit = {q: 1.5 * out['hf_seed_to_seed'][q] for q in ('jack', 'p12')}
    for name, s in surrogates.items():
        try:
            errs = [_errors(run(p, scenario, s, seed=k), hf[k]) for k in range(seeds)]
        except Exception as exc:
            out['models'][name] = {'error': f'{type(exc).__name__}: {exc}'}
            continue
        m = mean_sem(errs)
        m['meets'] = bool(m['jack'] <= limit['jack'] and m['p12'] <= limit['p12'])
        out['models'][name] = m
    return out


def largest_steps(summary) -> dict:
    """Per model run at several steps (summary keys ``model`` at 1 us and ``model@dt=X``; and
    per model by the split integrator, ``model@split@dt=X``, under ``model@split``): the
    largest step [s] at which it meets the bounds in every case - and at every smaller step
    tried - with its median cost per simulated second against hf at 1 us (``None``: not even
    at the smallest step tried, 1 us for the explicit scheme)."""
    steps = {}
    for key, row in summary.items():
        name, _, dt = key.partition('@dt=')
        steps.setdefault(name, {})[float(dt) if dt else DT_S] = row
    out = {}
    for name, rows in steps.items():
        if len(rows) < 2 and name != 'hf' and not name.endswith(f'@{SPLIT}'):
            continue
        if name == 'hf':
            rows = {DT_S: {'cases_meeting_bounds': 1, 'cases': 1, 'median_cost_vs_hf': 1.0},
                    **rows}
        met = list(itertools.takewhile(
            lambda dt: rows[dt]['cases_meeting_bounds'] == rows[dt]['cases'], sorted(rows)))
        best = met[-1] if met else None
        out[name] = {'steps_tried_s': sorted(rows),
                     'largest_step_s': best,
                     'median_cost_vs_hf_at_it': (None if best is None
                                                 else rows[best]['median_cost_vs_hf'])}
    return out


def converged_summary(result) -> dict | None:
    """Per model (hf at 1 us as ``'hf'``), the noise-free cases against the converged
    reference under the same bounds, in the rows :func:`largest_steps` reads: cases,
    ``cases_meeting_bounds``, ``cases_failing``, ``median_cost_vs_hf``; with
    ``cases_unsettled``, the cases whose reference moved by more than
    :data:`SETTLED_FRACTION` of a bound at twice its step (each model's count includes
    them: a verdict there rests on an unconverged reference).  ``None`` without a converged
    reference."""
    cases = {n: c for n, c in result['noise_free'].items() if 'converged' in c}
    if not cases:
        return None
    unsettled = sorted(n for n, c in cases.items() if not c['converged']['settled'])
    rows = {'hf': [(n, c['converged']['hf'], 1.0) for n, c in cases.items()]}
    for n, c in cases.items():
        for m, r in c['models'].items():
            rows.setdefault(m, []).append(
                (n, r.get('converged'), r['cost_s_per_s'] / c['hf_cost_s_per_s']
                 if 'cost_s_per_s' in r else None))
    out = {}
    for m, got in rows.items():
        failed = [n for n, r, _ in got if r is None or not r['meets']]
        costs = [k for _, _, k in got if k is not None]
        out[m] = {'cases': len(got), 'cases_meeting_bounds': len(got) - len(failed),
                  'cases_failing': failed, 'cases_unsettled': unsettled,
                  **{f'worst_{q}_over_bound': max(
                      (r[q] / cases[n]['bound'][q] for n, r, _ in got if r is not None),
                      default=None) for q in ('jack', 'p12')},
                  'median_cost_vs_hf': float(np.median(costs)) if costs else None}
    return out


def summarise(result) -> dict:
    """Per model: cases meeting the noise-free bounds, worst ratios error / bound, features
    within the yardstick's spread, noise goals met, median cost against hf."""
    out = {}
    keys = sorted({k for c in result['noise_free'].values() for k in c['models']})
    for m in keys:
        cases = [(name, c, c['models'][m]) for name, c in result['noise_free'].items()
                 if m in c['models']]
        ok = [(c, r) for _, c, r in cases if 'error' not in r]
        failed = [name for name, _, r in cases if 'error' in r or not r['meets']]
        feat = [all(r['features_within_2x_spread'].values()) for _, r in ok]
        feat1 = [all(r['features_within_spread'].values()) for _, r in ok]
        row = {'cases': len(cases), 'cases_meeting_bounds': len(cases) - len(failed),
               'cases_failing': failed,
               **{f'worst_{q}_over_bound': max((r[q] / c['bound'][q] for c, r in ok),
                                               default=None) for q in ('jack', 'p12')},
               'cases_all_features_within_spread': int(sum(feat1)),
               'cases_all_features_within_2x_spread': int(sum(feat)),
               'median_cost_vs_hf': float(np.median([r['cost_s_per_s'] / c['hf_cost_s_per_s']
                                                     for c, r in ok])) if ok else None}
        noise = [(sc, c['models'][m]) for sc, c in result['noise'].items() if m in c['models']]
        if noise:
            row['noise_scenarios_meeting'] = sum(1 for _, r in noise if r.get('meets'))
            row['noise_scenarios'] = len(noise)
            row['noise_failing'] = [sc for sc, r in noise if not r.get('meets')]
        out[m] = row
    return out
