"""The sweep's errors (a leaf: imports nothing of ours)."""

from __future__ import annotations

__all__ = ['SpecError', 'SweepError']


class SpecError(ValueError):
    """A spec that cannot run: one line naming what is wrong."""


class SweepError(RuntimeError):
    """A sweep's output folder, cluster or batch cannot be used (one line)."""
