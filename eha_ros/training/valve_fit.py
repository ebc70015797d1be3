"""Calibrate the settled valve test's fit (:mod:`eha_ros.health.valve_fit`) on a drawn
fleet of held-out valves and write ``valve_fit.npz``.

Calibration set
    ``N_CAL`` valves drawn from stream ``SEED_CAL`` (:func:`drifted_cases`, ``fleet``):
    clearance and overlap uniform over :data:`eha_ros.physics.maps.WEAR_RANGES`; the
    measured conditions' true values uniform over the service envelope of
    ``config/test_bench.yaml``; Khsv, jack leakage and bulk modulus uniform over the bench's
    ranges; every other nuisance of ``config/tolerances.yaml`` uniform over its range (the
    unit-to-unit tolerances and the fluid's condition); the bench's sensor errors from the
    case's seed.  Half the valves are measured without pressure noise, half
    with 1 % (two sweeps, :mod:`eha_ros.sweep`).

Calibration
    Per fitted parameter, the factor (at least 1) that puts 95 % of the valves within 2
    standard deviations; the mismatch limit on ``chi`` is 1.5 times the largest ``chi`` of
    the set.  The benchmark's sets (``bench/health.py``) come from other streams.

Build: ``python -m eha_ros.training.valve_fit [--workers N]``.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from eha_ros.artefacts import models_dir, save_artefact
from eha_ros.health.valve_fit import FIT_FILE, FIT_NAMES, read_calibration
from eha_ros.physics import default_params, params_to_dict
from eha_ros.physics.bench import load_bench
from eha_ros.physics.maps import WEAR_RANGES
from eha_ros.physics.tolerances import draw_unit

__all__ = ['N_CAL', 'SEED_CAL', 'VALVE_NUISANCE', 'drifted_cases', 'run_cases',
           'calibrate', 'build_artefact']

# Run as a script, this module is the main module the sweep's spawned workers import again
# before their single-thread settings apply: numba's pool must start with the same setting.
if __name__ in ('__main__', '__mp_main__'):
    os.environ.setdefault('NUMBA_NUM_THREADS', '1')

N_CAL = 200
SEED_CAL = 32
#: The nuisances of ``config/test_bench.yaml`` the valve test's maps depend on.
VALVE_NUISANCE = ('bulk_modulus_pa', 'valve_degradation', 'leakage_coeff_m3_s_pa')
_CHI_MARGIN = 1.5
#: Nuisances the settled valve test does not run: the torque motor's current noise (the
#: test's pressures have their own, ``pressure_noise``).
NOT_IN_TEST = ('noise_std_a', 'noise_sample_time_s')


def drifted_cases(n: int, stream: int, *, wear: bool = True, drift: bool = True,
                  overrides: dict | None = None, fleet: bool = False) -> list:
    """``n`` valve-test cases (plant parameters and ``seed``) from ``default_rng([stream,
    i])``: wear uniform (or nominal), conditions and nuisances uniform over their envelopes
    (or nominal); ``fleet``: then every nuisance of ``config/tolerances.yaml`` uniform over
    its range (:func:`eha_ros.physics.tolerances.draw_unit`, after the seed: the other
    draws are those of the set without it); then ``overrides`` (plant names)."""
    p = default_params()
    b = load_bench()
    out = []
    for i in range(n):
        rng = np.random.default_rng([stream, i])
        c = {}
        if wear:
            c['radial_clearance_m'] = float(rng.uniform(*WEAR_RANGES['radial_clearance_m']))
            c['overlap_supply_m'] = float(rng.uniform(*WEAR_RANGES['overlap_m']))
        t = p.fluid_temperature_k
        if drift:
            c['supply_pressure_pa'] = float(rng.uniform(0.95, 1.05) * p.supply_pressure_pa)
            c['return_pressure_pa'] = float(rng.uniform(3e5, 1e6))
            lo, hi = b.service['fluid_temperature_k']
            t = float(rng.uniform(lo + 1.0, hi - 1.0))
            for name in VALVE_NUISANCE:
                c[name] = float(rng.uniform(*b.nuisance_range(name, p)))
        seed = int(rng.integers(0, 2 ** 31 - 1))
        if fleet:
            c = draw_unit(rng, c, p, exclude=NOT_IN_TEST)
        over = dict(overrides or {})
        t = float(over.pop('fluid_temperature_k', t))
        if drift or t != p.fluid_temperature_k:
            c['fluid_temperature_k'] = t
        c.update(over)
        if 'overlap_supply_m' in c:
            c['overlap_return_m'] = c['overlap_supply_m']
        c['seed'] = seed
        out.append(c)
    return out


def run_cases(cases: list, procedure: str = 'settled', pressure_noise: float = 0.0,
              workers: int = 2, out: Path | None = None):
    """The valve test of every case as one sweep; the dataset as a pyarrow table in case
    order."""
    from eha_ros.sweep import parse_spec, read_dataset, run_sweep
    raw = {'procedure': 'valve_test', 'models': ['hf'], 'valve_test_procedure': procedure,
           'pressure_noise': pressure_noise, 'cases': cases}
    spec = parse_spec(raw, source=f'valve-test cases ({procedure})',
                      base=params_to_dict(default_params()))
    ids = [pt.cases[0].case_id for pt in spec.points()]
    with tempfile.TemporaryDirectory(prefix='eha-valve-') as tmp:
        folder = Path(out) if out is not None else Path(tmp) / 'sweep'
        run_sweep(spec, folder, workers=workers, in_process=workers <= 1)
        t = read_dataset(folder)
    row = {c: k for k, c in enumerate(t.column('case_id').to_pylist())}
    return t.take([row[i] for i in ids])


def calibrate(table, cases, factors_used) -> tuple:
    """``(factors, chi_limit, figures)`` from a calibration table (estimates made with
    ``factors_used``); rows that flag a mismatch are left out of the factors."""
    ok = np.array(table.column('status').to_pylist()) == 'ok'
    if ok.sum() < 0.9 * len(cases):
        errors = [e for e in table.column('error').to_pylist() if e]
        raise RuntimeError(f'valve-fit calibration: {len(cases) - int(ok.sum())} of '
                           f'{len(cases)} tests failed, the first: {errors[:1]}')
    mis = np.array(table.column('mismatch').to_pylist(), dtype=bool) & ok
    keep = ok & ~mis
    p = default_params()
    truth = np.array([[c.get(n, getattr(p, n)) for n in FIT_NAMES] for c in cases])
    est = np.stack([np.array(table.column(k).to_pylist(), dtype=float) for k in (
        'est_radial_clearance_m', 'est_overlap_m', 'est_valve_degradation',
        'est_leakage_coeff_m3_s_pa')], axis=1)
    std = np.stack([np.array(table.column(k).to_pylist(), dtype=float) for k in (
        'est_radial_clearance_std_m', 'est_overlap_std_m', 'est_valve_degradation_std',
        'est_leakage_coeff_m3_s_pa_std')], axis=1)
    raw_std = std / np.asarray(factors_used)
    ratio = np.abs(est - truth)[keep] / np.maximum(raw_std[keep], 1e-300)
    factors = np.maximum(1.0, np.quantile(ratio, 0.95, axis=0) / 2.0)
    chi = np.array(table.column('chi').to_pylist(), dtype=float)[ok]
    figures = {'cases': int(len(cases)), 'ok': int(ok.sum()), 'mismatch_flagged': int(mis.sum()),
               'chi_max': float(chi.max()), 'chi_median': float(np.median(chi)),
               'ratio_q95': dict(zip(FIT_NAMES, np.quantile(ratio, 0.95, axis=0).tolist()))}
    return factors, _CHI_MARGIN * float(chi.max()), figures


def build_artefact(workers: int = 2, out: Path | None = None, progress=print) -> Path:
    """Calibrate on the drifted held-out set (module docstring) and save ``valve_fit.npz``."""
    shipped = models_dir('health') / FIT_FILE
    path = Path(out) if out is not None else shipped
    t0 = time.perf_counter()
    ident = np.ones(len(FIT_NAMES))
    meta = {'kind': 'valve_fit', 'format': 2}
    # the estimates run with factors 1 and no chi limit: the sweep's workers load the shipped
    # file, which holds that stage only while the sweeps run (restored if they fail)
    before = shipped.read_bytes() if shipped.is_file() else None
    save_artefact(shipped, (ident, np.array([np.inf])), dict(meta, stage='uncalibrated'))
    read_calibration.clear()
    done = False
    try:
        half = N_CAL // 2
        cases = drifted_cases(N_CAL, SEED_CAL, fleet=True)
        clean = run_cases(cases[:half], workers=workers)
        noisy = run_cases(cases[half:], pressure_noise=0.01, workers=workers)
        done = True
    finally:
        if not done or path != shipped:
            if before is None:
                shipped.unlink()
            else:
                shipped.write_bytes(before)
            read_calibration.clear()
    import pyarrow as pa
    table = pa.concat_tables([clean, noisy])
    factors, chi_limit, figures = calibrate(table, cases, ident)
    b = load_bench()
    meta.update({
        'stage': 'calibrated', 'fit': list(FIT_NAMES),
        'calibration_set': {'n': N_CAL, 'stream': SEED_CAL, 'pressure_noise': [0.0, 0.01],
                            'fleet': 'every nuisance of config/tolerances.yaml',
                            'wear_ranges': {k: list(v) for k, v in WEAR_RANGES.items()},
                            'service': {k: list(v) for k, v in b.service.items()},
                            'nuisance': {k: list(b.nuisance_range(k)) for k in VALVE_NUISANCE}},
        'factors': dict(zip(FIT_NAMES, factors.round(3).tolist())),
        'chi_limit': chi_limit, 'chi_margin': _CHI_MARGIN, 'figures': figures,
        'build_s': round(time.perf_counter() - t0, 1)})
    save_artefact(path, (factors, np.array([chi_limit])), meta)
    read_calibration.clear()
    progress(f'{path}: factors {meta["factors"]}, chi limit {chi_limit:.3g} '
             f'({figures})')
    return path


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog='python -m eha_ros.training.valve_fit',
                                 description='calibrate the settled valve test\'s fit')
    ap.add_argument('--workers', type=int, default=2, help='sweep workers (1: in process)')
    args = ap.parse_args(argv)
    build_artefact(workers=args.workers)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
