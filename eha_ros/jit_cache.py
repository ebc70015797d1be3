"""The package's numba disk cache, dropped whenever any of its sources changed.

numba checks a cached function against its own source file only (its modification time and
size). The package's kernels inline code across modules: the plant's loop
(:mod:`eha_ros.physics.loop`) into every shipped surrogate's compiled forms, the valve's
steady solver into the maps' kernels. After a change in one module (an upgrade, an edit), an
entry of another would load the old code. So, when ``eha_ros`` is imported, a fingerprint of
every source file (path, size, modification time) is compared with the one stored beside the
cache, and on any difference every cache file of the package is removed before numba reads
one: the kernels then compile once and are cached again.

Where numba keeps the entries: ``__pycache__`` beside each source file, or under
``NUMBA_CACHE_DIR`` when that is set (the same relative layout). Where neither can be
written, numba caches nothing there and nothing is dropped.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ['fingerprint', 'drop_stale_cache', 'CACHE_SUFFIXES', 'STAMP_NAME']

#: numba's cache files: the index and the compiled data of each function.
CACHE_SUFFIXES = ('.nbi', '.nbc')
#: The stored fingerprint, in the package's top ``__pycache__``.
STAMP_NAME = 'numba_sources.txt'


def fingerprint(package_dir: Path) -> str:
    """One line per ``.py`` file below ``package_dir``: relative path, size, mtime [ns]."""
    rows = []
    for path in sorted(package_dir.rglob('*.py')):
        st = path.stat()
        rows.append(f'{path.relative_to(package_dir).as_posix()} {st.st_size} '
                    f'{st.st_mtime_ns}')
    return '\n'.join(rows) + '\n'


def _cache_files(package_dir: Path):
    """The package's numba cache files, where numba keeps them."""
    yield from (p for p in package_dir.rglob('*')
                if p.suffix in CACHE_SUFFIXES and p.parent.name == '__pycache__')
    user = os.environ.get('NUMBA_CACHE_DIR')
    if user:  # numba's user-provided locator: the source folder's absolute path below it
        root = Path(user) / package_dir.resolve().relative_to(package_dir.resolve().anchor)
        if root.is_dir():
            yield from (p for p in root.rglob('*') if p.suffix in CACHE_SUFFIXES)


def drop_stale_cache(package_dir: Path) -> int:
    """Remove every numba cache file of the package when its sources differ from the stored
    fingerprint (or none is stored), then store the current one; returns how many files were
    removed.  A cache folder that cannot be written is left as it is (numba cannot have
    cached there either)."""
    package_dir = Path(package_dir)
    stamp = package_dir / '__pycache__' / STAMP_NAME
    current = fingerprint(package_dir)
    try:
        if stamp.read_text(encoding='utf-8') == current:
            return 0
    except OSError:
        pass
    removed = 0
    for path in list(_cache_files(package_dir)):
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            pass  # another process removed it first
        except OSError:
            return removed
    try:
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f'{STAMP_NAME}.{os.getpid()}')
        tmp.write_text(current, encoding='utf-8')
        os.replace(tmp, stamp)  # whole, for a process reading it at the same moment
    except OSError:
        pass
    return removed
