"""Every plant parameter classified for the diagnosis of a fleet: ``config/tolerances.yaml``.

Each settable parameter (:data:`eha_ros.physics.params.SETTABLE`) has one class
(:data:`CLASSES`): a
condition the test bench measures, an item a test estimates, a nuisance drawn over its range, a
negligible one (the shipped screening shows its whole range moves no estimate by 0.2 of its
stated deviation), or a setting known exactly.  Nuisances and negligibles carry the range a real
unit or its service spans - absolute, a factor on the nominal value (``relative``), or a factor
on another parameter's value (``ratio_of``, the dynamic frictions on their breakaway ones) - and
every entry its reason.
"""

from __future__ import annotations

import dataclasses
import functools

from .params import (DERIVED, SETTABLE, SPEC_BY_NAME, ParameterError, PlantParams, config_dir,
                     default_params, read_yaml, replace)

__all__ = ['CLASSES', 'DRAWN', 'NEGLIGIBLE_SIGMA', 'Tolerance', 'load_tolerances', 'draw_unit',
           'error_shares']

#: The classes, in the order of the file's header.
CLASSES = ('measured', 'estimated', 'nuisance', 'negligible', 'setting')
#: The classes that carry a range and are drawn by the screening and the fleet sets.
DRAWN = ('nuisance', 'negligible')
#: ``negligible``: the parameter's whole range moves every estimate by less than this many of
#: the estimate's stated deviations in the shipped screening.
NEGLIGIBLE_SIGMA = 0.2


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """One parameter's class, range and reason (see the module)."""

    name: str
    klass: str
    reason: str
    lo: float | None = None
    hi: float | None = None
    relative: bool = False
    ratio_of: str | None = None
    trained: bool = False

    def bounds(self, params: PlantParams) -> tuple[float, float]:
        """The absolute ``(lo, hi)`` of the parameter about ``params`` (for ``ratio_of``: at
        the other parameter's value in ``params``)."""
        if self.klass not in DRAWN:
            raise ParameterError(f'tolerances: {self.name} is {self.klass}: it has no range')
        if self.ratio_of:
            ref = getattr(params, self.ratio_of)
        elif self.relative:
            ref = getattr(params, self.name)
        else:
            return self.lo, self.hi
        return self.lo * ref, self.hi * ref


def load_tolerances(path=None) -> dict:
    """``{name: Tolerance}`` of every plant parameter, in schema order.  Refused with a
    one-line :class:`ParameterError`: a parameter missing or unknown, an unknown class, a
    drawn class without a range (or a range outside the parameter's physical limits at
    nominal), a range on a class that has none."""
    path = path or config_dir() / 'tolerances.yaml'
    return _load(str(path))


@functools.lru_cache(maxsize=4)
def _load(path: str) -> dict:
    doc = read_yaml(path, 'tolerances', 'parameter -> {class, range, reason}')
    unknown = sorted(set(doc) - set(SETTABLE))
    if unknown:
        what = 'is not set (it follows from the fluid\'s temperature and condition)' \
            if unknown[0] in DERIVED else 'is no plant parameter'
        raise ParameterError(f'{path}: {unknown[0]} {what}')
    missing = [n for n in SETTABLE if n not in doc]
    if missing:
        raise ParameterError(f'{path}: plant parameter {missing[0]} has no class '
                             f'(one of {", ".join(CLASSES)})')
    p0 = default_params()
    out = {}
    for spec in (SPEC_BY_NAME[n] for n in SETTABLE):
        e, where = doc[spec.name], f'{path}: {spec.name}'
        if not isinstance(e, dict):
            raise ParameterError(f'{where}: expected a mapping with class and reason')
        klass = e.get('class')
        if klass not in CLASSES:
            raise ParameterError(f'{where}: class {klass!r} is not one of {", ".join(CLASSES)}')
        reason = str(e.get('reason') or '').strip()
        if not reason:
            raise ParameterError(f'{where}: no reason')
        if klass not in DRAWN:
            if 'lo' in e or 'hi' in e:
                raise ParameterError(f'{where}: a {klass} parameter has no range')
            out[spec.name] = Tolerance(spec.name, klass, reason)
            continue
        try:
            lo, hi = float(e['lo']), float(e['hi'])
        except (KeyError, TypeError, ValueError):
            raise ParameterError(f'{where}: a {klass} parameter needs numbers lo and hi'
                                 ) from None
        ratio_of = e.get('ratio_of')
        if ratio_of is not None and ratio_of not in SPEC_BY_NAME:
            raise ParameterError(f'{where}: ratio_of names no plant parameter: {ratio_of}')
        if not lo <= hi:
            raise ParameterError(f'{where}: needs lo <= hi')
        t = Tolerance(spec.name, klass, reason, lo, hi, bool(e.get('relative', False)),
                      ratio_of, bool(e.get('trained', False)))
        for v in t.bounds(p0):   # both ends must be physical about the nominal valve
            try:
                replace(p0, **{spec.name: v})
            except ParameterError as exc:
                raise ParameterError(f'{where}: range end {v:g} refused: {exc}') from None
        out[spec.name] = t
    return out


def draw_unit(rng, changes: dict | None = None, params: PlantParams | None = None,
              classes=('nuisance',), only=None, exclude=(),
              tolerances: dict | None = None) -> dict:
    """Plant changes of one unit of a fleet: every parameter of ``classes`` (default the
    nuisances; ``only``: those names of them) drawn uniform over its range about ``params``
    (default nominal; ``exclude``: names left nominal, as parameters a test does not run),
    in the file's order, one ``rng.uniform`` each, then ``changes`` (the
    caller's wear, faults and conditions) on top; a ``ratio_of`` parameter (a dynamic
    friction) is drawn as a factor on its reference's value in the result, so it follows a
    drawn or a given breakaway friction.  The one sampler of the fleet sets, the calibrations
    and the trainings."""
    tol = tolerances or load_tolerances()
    p = params or default_params()
    changes = dict(changes or {})
    out, ratios = {}, []
    for name, t in tol.items():
        if (t.klass not in classes or (only is not None and name not in only)
                or name in exclude):
            continue
        x = float(rng.uniform(0.0, 1.0))
        if t.ratio_of:
            ratios.append((name, t, x))
        else:
            lo, hi = t.bounds(p)
            out[name] = float(lo + x * (hi - lo))
    out.update(changes)
    for name, t, x in ratios:
        if name in changes:
            continue
        ref = out.get(t.ratio_of, getattr(p, t.ratio_of))
        out[name] = float((t.lo + x * (t.hi - t.lo)) * ref)
    return out


def error_shares(errors, units, top: int = 6, tolerances: dict | None = None) -> list:
    """Per column of the signed ``errors`` ``(n, k)`` of a fleet set, how its mean square
    is shared among the parameters drawn for the ``units`` (``n`` dicts of plant changes, as
    :func:`draw_unit` gives): a least-squares fit of the error, linear in every parameter
    that varies over the set (each standardised over the set; a ``ratio_of`` parameter as
    its ratio; one of parameters set equal, as both overlaps), gives parameter ``j`` the
    share ``beta_j**2 / mean(e**2)`` - with independent
    draws, the part of the error's variance that parameter explains alone.  Each entry:
    ``{'bias': mean(e)**2 share, 'parameters': the ``top`` largest shares, name -> share,
    'other_parameters': the sum of the others, 'rest': the remainder (nonlinear effects,
    interactions, noise; 0 where the sample's correlations make the sum exceed 1)}``.
    Needs more units than varying parameters plus one; refused with a ValueError otherwise."""
    import numpy as np
    tol = tolerances or load_tolerances()
    e = np.atleast_2d(np.asarray(errors, dtype=float).T).T
    names = sorted({k for u in units for k in u if k in SPEC_BY_NAME and k != 'seed'})
    cols, kept = [], []
    for name in names:
        ref = getattr(tol.get(name), 'ratio_of', None)
        v = np.array([u.get(name, np.nan) / (u.get(ref, np.nan) if ref else 1.0)
                      for u in units], dtype=float)
        if np.all(np.isfinite(v)) and np.std(v) > 1e-12 * (1.0 + np.abs(np.mean(v))):
            z = (v - v.mean()) / v.std()
            if not any(np.allclose(z, c) for c in cols):   # both overlaps set as one
                cols.append(z)
                kept.append(name)
    if len(units) <= len(kept) + 1:
        raise ValueError(f'error shares: {len(units)} units for {len(kept)} varying '
                         f'parameters: needs more units than parameters plus one')
    a = np.column_stack([np.ones(len(units))] + cols)
    beta, *_ = np.linalg.lstsq(a, e, rcond=None)
    out = []
    for j in range(e.shape[1]):
        ms = float(np.mean(e[:, j] ** 2))
        if ms == 0.0:
            out.append({'bias': 0.0, 'parameters': {}, 'other_parameters': 0.0, 'rest': 0.0})
            continue
        share = beta[1:, j] ** 2 / ms
        order = np.argsort(share)[::-1][:top]
        bias = float(np.mean(e[:, j]) ** 2 / ms)
        out.append({'bias': round(bias, 3),
                    'parameters': {kept[i]: round(float(share[i]), 3) for i in order},
                    'other_parameters': round(float(np.sum(share) - np.sum(share[order])), 3),
                    'rest': round(max(0.0, 1.0 - bias - float(np.sum(share))), 3)})
    return out
