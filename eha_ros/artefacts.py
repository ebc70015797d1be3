"""Shipped artefacts: the tables and trained networks that inference loads, one ``.npz`` each.

An artefact holds its arrays as ``data_0``, ``data_1``, ... and ``meta`` (a JSON string: what
it is, its inputs and units, how it was built and the hash of the physics parameters it was
built for).  The fluid surrogates keep theirs in ``eha_ros/surrogates/models/``, the health
estimators in ``eha_ros/health/models/``; ``$EHA_ROS_MODELS_DIR`` replaces both folders (one
folder for a rebuilt set).

This is the one place that reads, writes and checks them: :func:`load_artefact` refuses a
missing, corrupt or mismatched file in one line that says how to rebuild it.  No ROS, no
torch.
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import numpy as np

__all__ = ['ArtefactError', 'CachedReader', 'models_dir', 'save_artefact', 'load_artefact',
           'check_hash']


class ArtefactError(ValueError):
    """An artefact (or a database) is missing, corrupt, or was built for other parameters."""


def models_dir(room: str) -> Path:
    """Folder of the artefacts of ``room`` (``'surrogates'`` or ``'health'``);
    ``$EHA_ROS_MODELS_DIR`` overrides it."""
    env = os.environ.get('EHA_ROS_MODELS_DIR')
    return Path(env) if env else Path(__file__).resolve().parent / room / 'models'


def save_artefact(path: Path, data: tuple, meta: dict) -> None:
    """Write ``data`` arrays and ``meta`` to ``path`` (atomically: write, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + '.partial.npz')
    arrays = {f'data_{i}': np.asarray(a) for i, a in enumerate(data)}
    np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
    os.replace(tmp, path)


def load_artefact(path: Path, rebuild: str, error=ArtefactError) -> tuple[tuple, dict]:
    """Read an artefact: ``(data, meta)``.  Missing or corrupt: one-line ``error`` naming the
    file and the command that rebuilds it (``python -m <rebuild>``)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z['meta']))
            n = len([k for k in z.files if k.startswith('data_')])
            data = tuple(np.ascontiguousarray(z[f'data_{i}']) for i in range(n))
    except FileNotFoundError:
        raise error(f'{path}: no such artefact: build it with python -m {rebuild}') from None
    except Exception as exc:
        raise error(f'{path}: corrupt artefact ({type(exc).__name__}): rebuild it with '
                    f'python -m {rebuild}') from None
    return data, meta


def check_hash(meta: dict, key: str, expected: str, what: str, rebuild: str,
               error=ArtefactError) -> None:
    """Refuse an artefact whose ``meta[key]`` (the hash of the parameters it depends on,
    e.g. ``fluid_hash``) is not ``expected``."""
    if meta.get(key) != expected:
        group = key.removesuffix('_hash')
        raise error(f'{what} was built for {group} parameters {meta.get(key)}, these are '
                    f'{expected}: rebuild it with python -m {rebuild}, or use the parameters '
                    'it was built for')


class CachedReader:
    """``reader(path)``: ``read(path)`` once per state of the file, the result kept by the
    resolved path and its modification time (``size`` files), so a rebuilt artefact is read
    again and an unchanged one is not.  A missing file reads as ``read`` says (nothing kept);
    :meth:`clear` forgets every result (for a rewrite within the clock's resolution)."""

    def __init__(self, read, size: int = 4):
        self._read = read
        self._cached = functools.lru_cache(maxsize=size)(self._read_state)

    def _read_state(self, path: str, mtime_ns: int):
        return self._read(Path(path))

    def __call__(self, path: Path):
        path = Path(path).resolve()
        return self._cached(str(path), path.stat().st_mtime_ns if path.is_file() else 0)

    def clear(self) -> None:
        """Forget every result read."""
        self._cached.cache_clear()
