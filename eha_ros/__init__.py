"""Electro-hydraulic servo actuator (EHA) with a flapper-nozzle servovalve, on ROS 2.

Subpackages: ``physics`` (plant models, numpy/numba only), ``surrogates``, ``nodes``,
``recording``, ``tools`` (command-line tools), ``graph`` (the node graph's vocabulary) and
``msg`` (the ROS 2 message classes, generated from ``msg/*.msg`` when the package is built).
"""

import importlib.abc
from pathlib import Path
import sys

from .jit_cache import drop_stale_cache

__version__ = '0.1.0'


class _NoGeneratedMessages(importlib.abc.MetaPathFinder):
    """Explains, instead of a bare ModuleNotFoundError, why ``eha_ros.msg`` is missing when
    ``eha_ros`` was imported from the source tree (which has no generated messages)."""

    def __init__(self, package_dir: Path):
        self.package_dir = package_dir

    def find_spec(self, name, path=None, target=None):
        if name == 'eha_ros.msg' or name.startswith('eha_ros.msg.'):
            raise ModuleNotFoundError(
                f'{name} is generated when the package is built and exists only in the '
                f'installed eha_ros, but eha_ros was imported from the source tree '
                f'{self.package_dir} (the current directory, first on sys.path, shadows the '
                f'installed package). Run from another directory (cd /tmp), or use the '
                f"installed tools: .venv/bin/pytest, .venv/bin/<console script>, 'make test'.",
                name=name)
        return None


# before any kernel is compiled or loaded: numba's cache entries of a changed package go
drop_stale_cache(Path(__file__).parent)

if not (Path(__file__).parent / 'msg' / '__init__.py').is_file():
    sys.meta_path.append(_NoGeneratedMessages(Path(__file__).parent))
