"""The sweep's errors and how a case is named in them (a leaf: imports nothing of ours)."""

from __future__ import annotations

__all__ = ['SpecError', 'SweepError', 'label']


class SpecError(ValueError):
    """A spec that cannot run: one line naming what is wrong."""


class SweepError(RuntimeError):
    """A sweep's output folder, cluster or batch cannot be used (one line)."""


def label(inputs: dict) -> str:
    """A case's swept inputs as ``name=value, ...`` (``nominal`` without any)."""
    return ', '.join(f'{k}={v:g}' if isinstance(v, float) else f'{k}={v}'
                     for k, v in inputs.items()) or 'nominal'
