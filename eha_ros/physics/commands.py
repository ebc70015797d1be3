"""Position commands (step, ramp, sine, chirp, Com) and the named scenarios of ``config/``.

A waveform is an integer kind plus a fixed float64 parameter vector, so one numba function
evaluates any of them::

    step   r = A                         for t >= t0
    ramp   r = A min(1, (t - t0)/T_ramp) for t >= t0     (reaches A after T_ramp, then holds)
    sine   r = A sin(w (t - t0))         for t >= t0     (w in rad/s)
    chirp  r = A sin(2 pi (f0 tau + (f1 - f0) tau^2 / (2 T)))   tau = t - t0 in [0, T]
    com    r = values[k] for the last times[k] <= t      (successive steps, any amplitudes)

and r = 0 before ``t0``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np
from numba import njit

from .params import ParameterError, config_dir, read_yaml

__all__ = ['Scenario', 'WAVEFORMS', 'command_value', 'load_scenarios', 'get_scenario']

#: Valve-test procedures a scenario may name (:mod:`.maintenance`): the settled test, and the
#: reference's 10 ms map transient.
VALVE_TEST_PROCEDURES = ('settled', 'reference')

WAVEFORMS = ('step', 'ramp', 'sine', 'chirp', 'com')
STEP, RAMP, SINE, CHIRP, COM = range(5)
# indices into the parameter vector
A_AMP, A_T0, A_W, A_TRAMP, A_F0, A_F1, A_TSWEEP = range(7)
N_ARGS = 8


@njit(cache=True, inline='always')
def command_value(kind, args, com_t, com_v, t):
    """Jack position command [m] at time ``t`` [s]."""
    if kind == COM:
        r = 0.0
        for k in range(com_t.size):
            if com_t[k] <= t:
                r = com_v[k]
            else:
                break
        return r
    tau = t - args[A_T0]
    if tau < 0.0:
        return 0.0
    amp = args[A_AMP]
    if kind == STEP:
        return amp
    if kind == RAMP:
        tr = args[A_TRAMP]
        return amp if tau >= tr else amp * tau / tr
    if kind == SINE:
        return amp * math.sin(args[A_W] * tau)
    # chirp
    ts = args[A_TSWEEP]
    if tau > ts:
        tau = ts
    f0 = args[A_F0]
    f1 = args[A_F1]
    return amp * math.sin(2.0 * math.pi * (f0 * tau + 0.5 * (f1 - f0) * tau * tau / ts))


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A named command: waveform, its parameters and how long to simulate it."""

    name: str
    waveform: str
    duration_s: float
    amplitude_m: float = 0.0
    start_s: float = 0.0
    frequency_rad_s: float = 0.0
    ramp_time_s: float = 0.0
    f0_hz: float = 0.0
    f1_hz: float = 0.0
    sweep_time_s: float = 0.0
    com_times_s: tuple = ()
    com_values_m: tuple = ()
    valve_test_flows_m3_s: tuple = ()
    valve_test_procedure: str = 'reference'
    preflight_check: bool = False
    description: str = ''
    events: tuple = ()

    def __post_init__(self):
        where = f'scenario {self.name}'
        if self.waveform not in WAVEFORMS:
            raise ParameterError(f'{where}: unknown waveform {self.waveform!r} '
                                 f'(one of {", ".join(WAVEFORMS)})')
        numbers = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                   if f.type == 'float'}
        for key, value in numbers.items():
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ParameterError(f'{where}: {key} = {value!r} is not a finite number')
        if self.duration_s <= 0:
            raise ParameterError(f'{where}: duration_s must be positive')
        if self.start_s < 0:
            raise ParameterError(f'{where}: start_s must not be negative')
        if self.waveform == 'ramp' and self.ramp_time_s <= 0:
            raise ParameterError(f'{where}: ramp needs a positive ramp_time_s')
        if self.waveform == 'sine' and self.frequency_rad_s <= 0:
            raise ParameterError(f'{where}: sine needs a positive frequency_rad_s')
        if self.waveform == 'chirp' and (self.sweep_time_s <= 0 or self.f0_hz < 0
                                         or self.f1_hz <= 0):
            raise ParameterError(f'{where}: chirp needs f0_hz >= 0, f1_hz > 0 and a positive '
                                 'sweep_time_s')
        if self.waveform == 'com':
            t = np.asarray(self.com_times_s, dtype=float)
            v = np.asarray(self.com_values_m, dtype=float)
            if t.size == 0 or t.size != v.size:
                raise ParameterError(f'{where}: com needs com_times_s and com_values_m of '
                                     'equal, non-zero length')
            if np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t)) or not np.all(
                    np.isfinite(v)):
                raise ParameterError(f'{where}: com_times_s must be finite and increasing')
        if not np.all(np.isfinite(np.asarray(self.valve_test_flows_m3_s, dtype=float))):
            raise ParameterError(f'{where}: valve_test_flows_m3_s must be finite')
        if self.valve_test_procedure not in VALVE_TEST_PROCEDURES:
            raise ParameterError(f'{where}: valve_test_procedure {self.valve_test_procedure!r} '
                                 f'must be one of {", ".join(VALVE_TEST_PROCEDURES)}')
        from .events import node_events
        object.__setattr__(self, 'events', node_events(where, self.events))

    @property
    def valve_test(self) -> bool:
        """The plant runs the diagnostic valve test (:mod:`.valve_test`) first, at these
        flows; the command (the jack held) applies after it."""
        return len(self.valve_test_flows_m3_s) > 0

    def arrays(self):
        """(kind, args, com_t, com_v) as :func:`command_value` takes them."""
        args = np.zeros(N_ARGS)
        args[[A_AMP, A_T0, A_W, A_TRAMP, A_F0, A_F1, A_TSWEEP]] = (
            self.amplitude_m, self.start_s, self.frequency_rad_s, self.ramp_time_s, self.f0_hz,
            self.f1_hz, self.sweep_time_s)
        com_t = np.asarray(self.com_times_s if self.waveform == 'com' else (), dtype=float)
        com_v = np.asarray(self.com_values_m if self.waveform == 'com' else (), dtype=float)
        return WAVEFORMS.index(self.waveform), args, com_t, com_v

    def value(self, t_s):
        """Command [m] at time(s) ``t_s``."""
        kind, args, ct, cv = self.arrays()
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        out = np.array([command_value(kind, args, ct, cv, ti) for ti in t])
        return out if np.ndim(t_s) else float(out[0])


_FIELDS = {f.name for f in dataclasses.fields(Scenario)} - {'name'}
_TUPLES = ('com_times_s', 'com_values_m', 'valve_test_flows_m3_s')


def load_scenarios(path: Path | str | None = None) -> dict[str, Scenario]:
    """All scenarios of ``config/scenarios.yaml`` (or ``path``) by name.  The file is parsed
    once per version (path, modification time and size): every :func:`simulate` looks its
    scenario up, and parsing the YAML costs about 50 ms."""
    path = Path(path) if path is not None else config_dir() / 'scenarios.yaml'
    try:
        st = path.stat()
    except OSError:
        return _parse_scenarios(path)   # read_yaml names what is wrong
    return dict(_cached_scenarios(str(path), st.st_mtime_ns, st.st_size))


@functools.lru_cache(maxsize=8)
def _cached_scenarios(path: str, mtime_ns: int, size: int) -> dict[str, Scenario]:
    return _parse_scenarios(Path(path))


def _parse_scenarios(path: Path) -> dict[str, Scenario]:
    doc = read_yaml(path, 'scenario', 'name -> scenario')
    out = {}
    for name, entry in doc.items():
        if not isinstance(entry, dict):
            raise ParameterError(f'{path}: scenario {name} must be a mapping')
        unknown = sorted(set(entry) - _FIELDS)
        if unknown:
            raise ParameterError(f'{path}: scenario {name}: unknown field {unknown[0]}')
        kw = dict(entry)
        for key in _TUPLES:
            if key in kw:
                try:
                    kw[key] = tuple(float(x) for x in kw[key])
                except (TypeError, ValueError):
                    raise ParameterError(f'{path}: scenario {name}: {key} must be a list of '
                                         'numbers') from None
        if not isinstance(kw.get('preflight_check', False), bool):
            raise ParameterError(f'{path}: scenario {name}: preflight_check must be true or '
                                 'false')
        for key, value in list(kw.items()):
            if key not in ('waveform', 'description', 'preflight_check', 'events',
                           'valve_test_procedure') + _TUPLES:
                try:
                    kw[key] = float(value)
                except (TypeError, ValueError):
                    raise ParameterError(f'{path}: scenario {name}: {key} = {value!r} is not a '
                                         'number') from None
        if 'waveform' not in kw or 'duration_s' not in kw:
            raise ParameterError(f'{path}: scenario {name} needs waveform and duration_s')
        out[str(name)] = Scenario(name=str(name), **kw)
    return out


def get_scenario(name_or_scenario, path=None) -> Scenario:
    """A :class:`Scenario` by name (from ``config/scenarios.yaml``), or the object itself."""
    if isinstance(name_or_scenario, Scenario):
        return name_or_scenario
    scenarios = load_scenarios(path)
    try:
        return scenarios[name_or_scenario]
    except KeyError:
        raise ParameterError(f'unknown scenario {name_or_scenario!r} (known: '
                             f'{", ".join(sorted(scenarios))})') from None
