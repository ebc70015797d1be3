"""Alias of :mod:`eha_ros.graph`, the graph's vocabulary (kept for existing imports)."""

from eha_ros.graph import *  # noqa: F401,F403
from eha_ros.graph import __all__  # noqa: F401
