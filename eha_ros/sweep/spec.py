"""A sweep's spec: what to run, checked whole before anything runs, and its cases.

The YAML form (README, "Sweeps")::

    procedure: scenario            # scenario | preflight_check | valve_test
    scenario: sine_0p01_2pi        # a name of config/scenarios.yaml, or a list (an axis)
    models: [hf, dlut]             # hf and any shipped surrogate
    seeds: [0]                     # noise seeds (or an integer n: seeds 0 .. n-1)
    noise: false                   # false: torque-motor noise off (noise_std_a = 0)
    parameters:                    # plant names; each list a grid axis, crossed with the others
      radial_clearance_m: [2.0e-6, 3.0e-6, 4.0e-6]
      overlap_supply_m: [0.0, 1.0e-6]
    random: {n: 1000, seed: 1, ranges: {radial_clearance_m: [1.0e-6, 6.0e-6]}}
    tie: {overlap_return_m: overlap_supply_m}   # a parameter set equal to a swept one
    cases: [{radial_clearance_m: 3.0e-6, seed: 4}, ...]   # explicit points, besides the grid
    compare: yardstick             # scenario: hf's yardstick per case (evaluation.noise_free)
    large_dts: [2.0e-6]            # with the yardstick: hf and dynamic models at these steps
    split_dts: [1.0e-5]            # with the yardstick: the same by the split integrator
    converged_dt: 1.0e-8           # with the yardstick: every case also against hf at this
                                   # step (a converged reference, evaluation.noise_free)
    dt_s: 1.0e-6                   # plant step [s]
    integrator: explicit           # scenario without compare, preflight_check: the plant's
                                   # integrator (explicit | split)
    signals: [jack_position_m]     # trajectories kept per case, every signal_dt_s
    signal_dt_s: 1.0e-3
    metrics: [rms_tracking_error_m]   # a subset of the procedure's metrics (default: all)

A **point** is one parameter set and one seed; its **cases** are the models (and steps) run
at it, one dataset row each.  hf runs once per point and is the reference of every surrogate
case of the point.  A case's id hashes what determines its result: procedure, scenario,
model, step, seed and every plant parameter (so a changed ``config/eha_params.yaml`` changes
the ids).  Everything here runs in the client before a worker starts: an unknown key, model,
scenario or parameter, a value the plant or a model refuses and a sweep larger than
``max_cases`` each raise :class:`SpecError` with one line.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math

import numpy as np

from eha_ros.graph import DYNAMIC_MODELS, MODELS
from eha_ros.physics import ParameterError, default_params, get_scenario, params_to_dict
from eha_ros.physics.maintenance import VALVE_TEST_PROCEDURES
from eha_ros.physics.params import SPEC_BY_NAME, params_from_mapping, read_yaml
from eha_ros.physics.stability import DT_S, EXPLICIT, INTEGRATORS, SPLIT

from eha_ros.procedure import label

from .errors import SpecError
from .procedures import PROCEDURES

__all__ = ['SpecError', 'Spec', 'Point', 'Case', 'PROCEDURES', 'MAX_CASES', 'load_spec',
           'parse_spec', 'case_id']

#: The default guard on a sweep's size (``--max-cases``).
MAX_CASES = 100_000
#: Keys a spec may have.
KEYS = ('procedure', 'scenario', 'models', 'seeds', 'noise', 'parameters', 'random', 'tie',
        'cases', 'compare', 'large_dts', 'dt_s', 'signals', 'signal_dt_s', 'metrics',
        'flows_m3_s', 'valve_test_procedure', 'pressure_noise', 'split_dts', 'integrator',
        'converged_dt')


@dataclasses.dataclass(frozen=True)
class Case:
    """One row of the dataset: a model (at a step) at a point."""

    case_id: str
    model: str
    dt_s: float


@dataclasses.dataclass(frozen=True)
class Point:
    """One parameter set and seed (and scenario); ``inputs`` are the swept plant names and
    their values."""

    point_id: str
    index: int
    inputs: dict
    seed: int
    cases: tuple
    scenario: str | None = None

    def params(self, spec: 'Spec'):
        return spec.point_params(self.inputs)


def _float(name, v, where):
    if isinstance(v, (str, int, float)) and not isinstance(v, bool):
        try:
            return float(v)
        except ValueError:
            pass
    raise SpecError(f'{where}: {name} = {v!r} is not a number')


def _value(name, v, where):
    """A plant value: a number, or a mode name for a mode parameter."""
    spec = SPEC_BY_NAME.get(name)
    if spec is None:
        raise SpecError(f'{where}: unknown parameter {name!r} (not a plant name of '
                        'config/eha_params.yaml)')
    if spec.choices:
        if v not in spec.choices:
            raise SpecError(f'{where}: {name} = {v!r} must be one of {", ".join(spec.choices)}')
        return str(v)
    return _float(name, v, where)


def case_id(procedure: str, scenario, model: str, dt_s: float, seed: int, params,
            integrator: str = EXPLICIT) -> str:
    """The id of a case: a hash of what determines its result (16 hex digits); the
    ``integrator`` enters only where it is not the explicit one, so the ids of explicit runs
    stay what they were before there was a choice."""
    d = params_to_dict(params)
    what = {'procedure': procedure, 'scenario': scenario, 'model': model,
            'dt_s': repr(float(dt_s)), 'seed': int(seed),
            'params': {k: (repr(v) if isinstance(v, float) else v) for k, v in sorted(d.items())}}
    if integrator != EXPLICIT:
        what['integrator'] = integrator
    blob = json.dumps(what, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


@dataclasses.dataclass
class Spec:
    """A parsed, checked spec (see the module's docstring)."""

    procedure: str
    scenarios: tuple
    models: tuple
    seeds: tuple
    noise: bool
    grid: dict
    random: dict | None
    tie: dict
    cases: tuple
    compare: str | None
    large_dts: tuple
    dt_s: float
    signals: tuple
    signal_dt_s: float
    metrics: tuple | None
    flows_m3_s: tuple | None
    raw: dict
    #: The nominal plant parameters (``name -> value``) every point starts from: the
    #: client's, shipped with every batch, so that a worker never uses another config.
    base: dict = dataclasses.field(default_factory=dict)
    source: str = 'spec'
    #: valve_test: ``settled`` or ``reference`` (:data:`eha_ros.physics.maintenance.
    #: VALVE_TEST_PROCEDURES`), and the relative measurement noise on its pressures
    valve_test_procedure: str = 'reference'
    pressure_noise: float = 0.0
    #: with the yardstick: steps [s] at which hf and the dynamic models also run by the split
    #: integrator (models ``<name>@split``); without it: the integrator of every case
    split_dts: tuple = ()
    integrator: str = EXPLICIT
    #: with the yardstick: the step [s] of the converged hf every case is also compared with
    converged_dt: float | None = None
    #: The procedure (:data:`eha_ros.sweep.procedures.PROCEDURES`), built once by
    #: :func:`parse_spec`: it checks the spec, declares the columns and runs the points.
    proc: object = dataclasses.field(default=None, repr=False, compare=False)
    _points: list | None = dataclasses.field(default=None, repr=False)

    # --- the cases ------------------------------------------------------------------------

    @property
    def input_names(self) -> tuple:
        """The plant names a row carries as inputs, in a fixed order."""
        names = [*self.grid, *(self.random['ranges'] if self.random else ()),
                 *(n for c in self.cases for n in c if n != 'seed'), *self.tie]
        return tuple(dict.fromkeys(names))

    def point_params(self, inputs: dict):
        """The plant parameters of a point: the nominal ones with ``inputs`` (and the noise
        switched off without ``noise``)."""
        changes = dict(inputs)
        if not self.noise:
            changes['noise_std_a'] = 0.0
        return params_from_mapping({**self.base, **changes}, source='sweep case')

    def _input_sets(self):
        """``(inputs, seed or None)`` of every point before seeds are crossed in."""
        grid_names = list(self.grid)
        grid = [dict(zip(grid_names, combo))
                for combo in itertools.product(*(self.grid[n] for n in grid_names))]
        draws = [{}]
        if self.random:
            r = self.random
            names = sorted(r['ranges'])
            draws = []
            for i in range(r['n']):
                rng = np.random.default_rng([r['seed'], i])
                draws.append({n: float(rng.uniform(*r['ranges'][n])) for n in names})
        out = [({**g, **d}, None) for g in grid for d in draws] if (self.grid or self.random) \
            else []
        out += [({k: v for k, v in c.items() if k != 'seed'}, c.get('seed')) for c in self.cases]
        return out or [({}, None)]

    def case_models(self) -> list:
        """``(model, dt_s)`` of the cases at a point."""
        out = [(m, self.dt_s) for m in self.models]
        if self.compare == 'yardstick':
            for suffix, dts in (('', self.large_dts), (f'@{SPLIT}', self.split_dts)):
                out += [(m + suffix, dt) for dt in dts for m in ('hf',) + self.models
                        if m == 'hf' or m in DYNAMIC_MODELS]
        return list(dict.fromkeys(out))

    def points(self) -> list:
        """Every point, in a fixed order (inputs, then seeds); computed once."""
        if self._points is not None:
            return self._points
        pts, seen = [], {}
        variants = self.case_models()
        sets = self._input_sets()
        params = []
        for inputs, seed in sets:
            for name, src in self.tie.items():
                inputs[name] = inputs[src]
            try:
                params.append(self.point_params(inputs))
            except ParameterError as exc:
                raise SpecError(f'{self.source}: case {label(inputs)}: {exc}') from None
        for sc in self.scenarios:
            for (inputs, seed), p in zip(sets, params):
                for s in ((seed,) if seed is not None else self.seeds):
                    cases = tuple(Case(case_id(self.procedure, sc, m, dt, s, p,
                                               self.integrator), m, dt)
                                  for m, dt in variants)
                    pid = hashlib.sha256('.'.join(c.case_id for c in cases).encode()
                                         ).hexdigest()
                    if pid in seen:
                        raise SpecError(f'{self.source}: case {label(inputs)}, seed {s} '
                                        f'repeats point {seen[pid]} (every case runs once)')
                    seen[pid] = len(pts)
                    pts.append(Point(pid[:16], len(pts), dict(inputs), int(s), cases, sc))
        self._points = pts
        return pts

    def canonical(self) -> dict:
        """The spec as stored beside its dataset (what ``--resume`` must match)."""
        return dict(sorted(self.raw.items()))


def load_spec(path, max_cases: int = MAX_CASES) -> Spec:
    """Read and check a YAML spec file."""
    try:
        raw = read_yaml(path, 'sweep spec')
    except ParameterError as exc:
        raise SpecError(str(exc)) from None
    return parse_spec(raw, source=str(path), max_cases=max_cases)


def _seeds(v, where):
    if isinstance(v, bool):
        raise SpecError(f'{where}: seeds = {v!r} must be a list of integers or a count')
    if isinstance(v, int):
        if v < 1:
            raise SpecError(f'{where}: seeds = {v} must be at least 1')
        return tuple(range(v))
    if not isinstance(v, list) or not v or not all(
            isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in v):
        raise SpecError(f'{where}: seeds = {v!r} must be a list of non-negative integers or '
                        'a count')
    if len(set(v)) != len(v):
        raise SpecError(f'{where}: seeds {v} repeat a seed')
    return tuple(v)


def _list_of_floats(name, v, where, positive=False):
    if not isinstance(v, list) or not v:
        raise SpecError(f'{where}: {name} must be a non-empty list')
    out = tuple(_float(name, x, where) for x in v)
    if positive and not all(x > 0 and math.isfinite(x) for x in out):
        raise SpecError(f'{where}: {name} = {list(out)} must be positive')
    return out


def _scenarios(raw: dict, procedure: str, where: str) -> tuple:
    """The spec's scenarios (``(None,)`` for a procedure without one), each a known name."""
    scenario = raw.get('scenario')
    scenarios = (None,)
    if procedure == 'scenario':
        if scenario is None:
            raise SpecError(f'{where}: procedure scenario needs a scenario (a name of '
                            'config/scenarios.yaml)')
        scenarios = tuple(scenario) if isinstance(scenario, list) else (scenario,)
        if not scenarios or not all(isinstance(s, str) for s in scenarios):
            raise SpecError(f'{where}: scenario = {scenario!r} must be a scenario name or a '
                            'list of them')
        if len(set(scenarios)) != len(scenarios):
            raise SpecError(f'{where}: scenario {list(scenarios)} repeats a scenario')
        for sc in scenarios:
            try:
                get_scenario(sc)
            except (ParameterError, KeyError) as exc:
                raise SpecError(f'{where}: {exc}') from None
    elif scenario is not None:
        raise SpecError(f'{where}: scenario is only for procedure scenario, not {procedure}')
    return scenarios


def _models_noise_seeds(raw: dict, procedure: str, where: str) -> tuple:
    """``(models, noise, seeds)``: known model names, the noise switch, the noise seeds."""
    models = raw.get('models', ['hf'])
    if isinstance(models, str):
        models = [models]
    if not isinstance(models, list) or not models \
            or not all(isinstance(m, str) for m in models):
        raise SpecError(f'{where}: models = {models!r} must be a list of model names')
    if len(set(models)) != len(models):
        raise SpecError(f'{where}: models {models} repeat a model')
    bad = [m for m in models if m not in MODELS]
    if bad:
        raise SpecError(f'{where}: unknown model {bad[0]!r} (one of {", ".join(MODELS)})')
    if procedure == 'valve_test' and models != ['hf']:
        raise SpecError(f'{where}: procedure valve_test runs the high-fidelity maps only '
                        '(models: [hf])')
    noise = raw.get('noise', False)
    if not isinstance(noise, bool):
        raise SpecError(f'{where}: noise = {noise!r} must be true or false')
    if procedure == 'valve_test' and noise:
        raise SpecError(f'{where}: procedure valve_test has no noise (its maps are the '
                        'noise-free transients)')
    seeds = _seeds(raw.get('seeds', [0]), where)
    # the valve test's seed drives the bench's sensors (conditions, pressure noise)
    if not noise and len(seeds) > 1 and procedure != 'valve_test':
        raise SpecError(f'{where}: {len(seeds)} seeds with noise: false would repeat every '
                        'case (the seed only drives the noise)')
    return models, noise, seeds


def _inputs(raw: dict, where: str) -> tuple:
    """``(grid, random, cases)``: the grid's axes, the random draws, the explicit points."""
    grid = {}
    params = raw.get('parameters') or {}
    if not isinstance(params, dict):
        raise SpecError(f'{where}: parameters must map plant names to lists of values')
    for name, values in params.items():
        if not isinstance(values, list) or not values:
            raise SpecError(f'{where}: parameters.{name} must be a non-empty list (a grid '
                            'axis)')
        grid[name] = tuple(_value(name, v, f'{where}: parameters') for v in values)
        if len(set(grid[name])) != len(grid[name]):
            raise SpecError(f'{where}: parameters.{name} repeats a value')
    random = raw.get('random')
    if random is not None:
        if not isinstance(random, dict) or set(random) - {'n', 'seed', 'ranges'} \
                or not {'n', 'ranges'} <= set(random):
            raise SpecError(f'{where}: random must be {{n, seed, ranges: {{name: [lo, hi]}}}}')
        n, rseed = random['n'], random.get('seed', 0)
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise SpecError(f'{where}: random.n = {n!r} must be a positive integer')
        if not isinstance(rseed, int) or isinstance(rseed, bool) or rseed < 0:
            raise SpecError(f'{where}: random.seed = {rseed!r} must be a non-negative integer')
        ranges = {}
        if not isinstance(random['ranges'], dict) or not random['ranges']:
            raise SpecError(f'{where}: random.ranges must map plant names to [lo, hi]')
        for name, lohi in random['ranges'].items():
            if not isinstance(lohi, list) or len(lohi) != 2:
                raise SpecError(f'{where}: random.ranges.{name} must be [lo, hi]')
            lo, hi = (_value(name, v, f'{where}: random.ranges') for v in lohi)
            if isinstance(lo, str) or not lo < hi:
                raise SpecError(f'{where}: random.ranges.{name} = [{lo}, {hi}] needs lo < hi')
            if name in grid:
                raise SpecError(f'{where}: {name} is both a grid axis and drawn at random')
            ranges[name] = (lo, hi)
        random = {'n': n, 'seed': rseed, 'ranges': ranges}
    cases = []
    for k, c in enumerate(raw.get('cases') or []):
        if not isinstance(c, dict):
            raise SpecError(f'{where}: cases[{k}] must map plant names (and seed) to values')
        at = f'{where}: cases[{k}]'
        cases.append({name: _seeds([v], at)[0] if name == 'seed' else _value(name, v, at)
                      for name, v in c.items()})
    return grid, random, cases


def _tie(raw: dict, swept: set, noise: bool, where: str) -> dict:
    """The tied parameters (each a plant name following a swept one)."""
    tie = raw.get('tie') or {}
    if not isinstance(tie, dict):
        raise SpecError(f'{where}: tie must map a plant name to the swept name it follows')
    for name, src in tie.items():
        if name not in SPEC_BY_NAME:
            raise SpecError(f'{where}: tie: unknown parameter {name!r}')
        if src not in swept:
            raise SpecError(f'{where}: tie.{name} follows {src!r}, which is not swept')
        if name in swept:
            raise SpecError(f'{where}: tie.{name}: {name} is swept itself')
    if not noise and 'noise_std_a' in swept:
        raise SpecError(f'{where}: noise_std_a is swept but noise is false')
    return tie


def _steps(raw: dict, procedure: str, kind, where: str) -> tuple:
    """``(compare, large_dts, split_dts, integrator, dt_s)`` (``kind``: the procedure's
    class)."""
    compare = raw.get('compare')
    if compare not in (None, 'yardstick'):
        raise SpecError(f'{where}: compare = {compare!r} must be yardstick (or absent)')
    if compare and procedure != 'scenario':
        raise SpecError(f'{where}: compare: yardstick is for procedure scenario')
    large_dts = tuple(_list_of_floats('large_dts', raw['large_dts'], where, positive=True)) \
        if raw.get('large_dts') is not None else ()
    if large_dts and compare != 'yardstick':
        raise SpecError(f'{where}: large_dts needs compare: yardstick')
    split_dts = tuple(_list_of_floats('split_dts', raw['split_dts'], where, positive=True)) \
        if raw.get('split_dts') is not None else ()
    if split_dts and compare != 'yardstick':
        raise SpecError(f'{where}: split_dts needs compare: yardstick (without it, set '
                        'integrator: split)')
    integrator = raw.get('integrator', EXPLICIT)
    if integrator not in INTEGRATORS:
        raise SpecError(f'{where}: integrator {integrator!r} is not one of '
                        f'{", ".join(INTEGRATORS)}')
    if integrator != EXPLICIT and (not kind.INTEGRATES or compare):
        takes = ', '.join(n for n, c in PROCEDURES.items() if c.INTEGRATES)
        raise SpecError(f'{where}: integrator: {integrator} is for procedures {takes} (not '
                        'with compare: the yardstick compares by split_dts)')
    dt_s = _float('dt_s', raw.get('dt_s', DT_S), where)
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise SpecError(f'{where}: dt_s = {dt_s} must be a positive step [s]')
    if compare and dt_s != DT_S:
        raise SpecError(f'{where}: compare: yardstick runs at dt_s = {DT_S:g} s')
    return compare, large_dts, split_dts, integrator, dt_s


def _converged_dt(raw: dict, compare, where: str):
    """The converged reference's step [s] (``None``: none): below the comparison's step and
    a whole number of nanoseconds, so that twice it is too."""
    if raw.get('converged_dt') is None:
        return None
    dt = _float('converged_dt', raw['converged_dt'], where)
    if compare != 'yardstick':
        raise SpecError(f'{where}: converged_dt needs compare: yardstick')
    if not (0 < dt < DT_S) or abs(round(dt * 1e9) - dt * 1e9) > 1e-6 * dt * 1e9:
        raise SpecError(f'{where}: converged_dt = {dt:g} s must be a whole number of '
                        f'nanoseconds below the comparison\'s step {DT_S:g} s')
    return dt


def _outputs(raw: dict, procedure: str, kind, compare, where: str) -> tuple:
    """``(signals, signal_dt_s, metrics)``: what the procedure (``kind``) keeps of each
    case."""
    signals = raw.get('signals') or []
    if not isinstance(signals, list) or not all(isinstance(s, str) for s in signals):
        raise SpecError(f'{where}: signals must be a list of signal names')
    bad = [s for s in signals if s not in kind.SIGNALS]
    if bad:
        raise SpecError(f'{where}: unknown signal {bad[0]!r} for procedure {procedure} (one of '
                        f'{", ".join(kind.SIGNALS)})')
    signal_dt_s = _float('signal_dt_s', raw.get('signal_dt_s', 1e-3), where)
    if not signal_dt_s > 0:
        raise SpecError(f'{where}: signal_dt_s = {signal_dt_s} must be positive')
    metrics = raw.get('metrics')
    if metrics is not None:
        if not isinstance(metrics, list) or not all(isinstance(m, str) for m in metrics):
            raise SpecError(f'{where}: metrics must be a list of metric names')
        known = kind.metric_names(compare)
        bad = [m for m in metrics if m not in known]
        if bad:
            raise SpecError(f'{where}: unknown metric {bad[0]!r} for procedure {procedure} '
                            f'(one of {", ".join(known)})')
        metrics = tuple(metrics)
    return signals, signal_dt_s, metrics


def _valve_test(raw: dict, procedure: str, where: str) -> tuple:
    """``(flows_m3_s, valve_test_procedure, pressure_noise)``: the valve test's settings."""
    flows = raw.get('flows_m3_s')
    if flows is not None:
        if procedure != 'valve_test':
            raise SpecError(f'{where}: flows_m3_s is for procedure valve_test')
        flows = _list_of_floats('flows_m3_s', flows, where)
    vtp = raw.get('valve_test_procedure', 'reference')
    pnoise = raw.get('pressure_noise', 0.0)
    if procedure != 'valve_test' and ('valve_test_procedure' in raw or 'pressure_noise' in raw):
        raise SpecError(f'{where}: valve_test_procedure and pressure_noise are for procedure '
                        'valve_test')
    if vtp not in VALVE_TEST_PROCEDURES:
        raise SpecError(f'{where}: valve_test_procedure {vtp!r} must be one of '
                        f'{", ".join(VALVE_TEST_PROCEDURES)}')
    if (isinstance(pnoise, bool) or not isinstance(pnoise, (int, float))
            or not 0.0 <= pnoise <= 0.1):
        raise SpecError(f'{where}: pressure_noise = {pnoise!r} must be a relative level in '
                        '[0, 0.1]')
    return flows, vtp, pnoise


def parse_spec(raw, source: str = 'spec', max_cases: int = MAX_CASES, check: bool = True,
               base: dict | None = None) -> Spec:
    """Check a spec (a mapping, as from YAML) and build :class:`Spec`; every case's parameters
    are checked against the plant's ranges and every model's validity (``check``: a worker
    given a spec the client checked skips it).  ``base``: the nominal parameters
    (default: ``config/eha_params.yaml``)."""
    where = source
    if not isinstance(raw, dict):
        raise SpecError(f'{where}: a spec is a mapping of {", ".join(KEYS[:6])}, ...')
    unknown = [k for k in raw if k not in KEYS]
    if unknown:
        raise SpecError(f'{where}: unknown key {unknown[0]!r} (one of {", ".join(KEYS)})')
    procedure = raw.get('procedure')
    if procedure not in PROCEDURES:
        raise SpecError(f'{where}: procedure = {procedure!r} must be one of '
                        f'{", ".join(PROCEDURES)}')
    scenarios = _scenarios(raw, procedure, where)
    models, noise, seeds = _models_noise_seeds(raw, procedure, where)
    grid, random, cases = _inputs(raw, where)
    swept = set(grid) | set((random or {}).get('ranges', {})) | {
        n for c in cases for n in c if n != 'seed'}
    tie = _tie(raw, swept, noise, where)
    kind = PROCEDURES[procedure]
    compare, large_dts, split_dts, integrator, dt_s = _steps(raw, procedure, kind, where)
    signals, signal_dt_s, metrics = _outputs(raw, procedure, kind, compare, where)
    flows, vtp, pnoise = _valve_test(raw, procedure, where)
    spec = Spec(procedure, scenarios, tuple(models), seeds, noise, grid, random, dict(tie),
                tuple(cases), compare, large_dts, dt_s, tuple(signals), signal_dt_s, metrics,
                flows, dict(raw), valve_test_procedure=vtp, pressure_noise=float(pnoise),
                split_dts=split_dts, integrator=integrator, source=where,
                converged_dt=_converged_dt(raw, compare, where),
                base=dict(params_to_dict(default_params()) if base is None else base))
    spec.proc = kind(spec)
    if check:
        n = count_cases(spec)
        if n > max_cases:
            raise SpecError(f'{where}: {n} cases exceed --max-cases {max_cases}')
        try:
            spec.proc.check(where)
        except ValueError as exc:   # the procedure's one line, naming the spec
            raise SpecError(str(exc)) from None
    return spec


def count_cases(spec: Spec) -> int:
    """The number of cases of ``spec``, counted without building them (the size guard runs
    before the cases are made)."""
    n_inputs = math.prod(len(v) for v in spec.grid.values()) if spec.grid else 0
    if spec.random:
        n_inputs = max(n_inputs, 1) * spec.random['n']
    n_points = n_inputs * len(spec.seeds) + sum(
        1 if 'seed' in c else len(spec.seeds) for c in spec.cases)
    if not (spec.grid or spec.random or spec.cases):   # the nominal point, at every seed
        n_points = len(spec.seeds)
    return n_points * len(spec.case_models()) * len(spec.scenarios)
