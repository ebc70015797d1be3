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

The kernels also compile faster here (:func:`share_inline_copies`, installed by
:mod:`eha_ros.physics` before any kernel compiles): numba, inlining a function
(``inline='always'``), copies the callee's IR block by block, each block with a deep copy of
its own of the function's whole scope; one copy of the scope shared by all the blocks, as the
original IR has it, makes the same code in about a third of the time
(``bench/first_run.py --cold --inline-copy both``: 0.30-0.40 of it, per shipped model).
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path
import textwrap

__all__ = ['fingerprint', 'drop_stale_cache', 'share_inline_copies', 'defer_blas_probe',
           'CACHE_SUFFIXES', 'STAMP_NAME']

#: numba's cache files: the index and the compiled data of each function.
CACHE_SUFFIXES = ('.nbi', '.nbc')
#: The stored fingerprint, in the package's top ``__pycache__``.
STAMP_NAME = 'numba_sources.txt'


def fingerprint(package_dir: Path) -> str:
    """One line per ``.py`` file below ``package_dir``: relative path, size, mtime [ns]."""
    rows = [(path, path.stat()) for path in sorted(package_dir.rglob('*.py'))]
    return '\n'.join(f'{path.relative_to(package_dir).as_posix()} {st.st_size} '
                     f'{st.st_mtime_ns}' for path, st in rows) + '\n'


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


#: The copy of a callee's IR in numba's ``InlineWorker.inline_ir`` (numba 0.68): a deep copy
#: per block, each with a memo of its own, so each block copies the whole scope (every
#: variable of the function) again, and nested inlining copies what it inlined at each level.
_PER_BLOCK_COPY = (
    'for block_label, block in the_ir.blocks.items():',
    '    new_block = copy.deepcopy(the_ir.blocks[block_label])',
    '    kernel_copy.blocks[block_label] = new_block',
)
#: The same copy in one deep copy with one memo: the blocks share one copy of the scope.
_SHARED_COPY = 'kernel_copy.blocks = copy.deepcopy(the_ir.blocks)'


def shared_copy_source(source: str) -> str | None:
    """``source`` (of ``InlineWorker.inline_ir``, dedented) with the per-block copy replaced
    by the shared one, line for line (blank lines fill the difference: tracebacks keep
    numba's line numbers); ``None`` where the per-block copy is not found as written."""
    lines = source.split('\n')
    k = len(_PER_BLOCK_COPY)
    for n in range(len(lines) - k + 1):
        indent = lines[n][:len(lines[n]) - len(lines[n].lstrip())]
        if all(lines[n + m] == indent + text for m, text in enumerate(_PER_BLOCK_COPY)):
            return '\n'.join(lines[:n] + [indent + _SHARED_COPY] + [''] * (k - 1)
                             + lines[n + k:])
    return None


def share_inline_copies() -> bool:
    """Make numba copy an inlined callee's IR with one memo for all its blocks
    (:data:`_SHARED_COPY`); returns whether that copy is in force.

    Why: the plant's loop inlines its blocks two and three levels deep, and the per-block copy
    took about three quarters of the compile time of each of its forms (cProfile of the first
    ``simulate``).  Measured on the 14 shipped forms (hf and the six surrogates, explicit and
    split), each compiled in a fresh cache: 14-20 s a form before, 4-6 s after, with the
    results identical bit for bit.  Only the copy changes: the callee is the same IR, its
    blocks sharing one scope as the original's do.  Where numba's code differs from the one
    this was written for (another version), nothing is changed and numba compiles as it
    does (more slowly); ``test_jit_cache`` fails on the pinned version if it stops applying.
    """
    # numba here, not at the top: importing eha_ros (the recorder, the tools) needs no numba
    from numba.core import inline_closurecall
    worker = inline_closurecall.InlineWorker
    if getattr(worker.inline_ir, 'shared_copy', False):
        return True
    try:
        lines, first = inspect.getsourcelines(worker.inline_ir)
    except (OSError, TypeError):  # no source to read (a frozen or stripped install)
        return False
    patched = shared_copy_source(textwrap.dedent(''.join(lines)))
    if patched is None:
        return False
    names = {}
    exec(compile('\n' * (first - 1) + patched, inspect.getsourcefile(worker.inline_ir),
                 'exec'), vars(inline_closurecall), names)
    inline_ir = names['inline_ir']
    inline_ir.__qualname__ = worker.inline_ir.__qualname__
    inline_ir.shared_copy = True
    worker.inline_ir = inline_ir
    return True


def _blas_files_present() -> None:
    """numba's BLAS probe, by the files: raises ``ImportError`` (as numba's ``ensure_blas``
    does) unless scipy's ``linalg/cython_blas`` extension is installed, without importing
    it."""
    import importlib.util
    spec = importlib.util.find_spec('scipy')
    folders = (spec.submodule_search_locations or []) if spec else []
    if not any(any(Path(d, 'linalg').glob('cython_blas*')) for d in folders):
        raise ImportError('scipy 0.16+ is required for linear algebra')


def defer_blas_probe() -> bool:
    """Make numba's import-time BLAS probe look for scipy's BLAS module instead of importing
    it; returns whether that probe is in force.

    Why: numba's CPU target, at the first compile or cache load of a process, imports
    ``numba.np.arraymath``, which probes for BLAS by importing ``scipy.linalg`` (0.2-0.5 s of
    CPU here: most of a node's first kernel load).  The answer only chooses how
    ``np.convolve`` and ``np.correlate`` are compiled; the file gives the same answer.  Every
    later ``ensure_blas`` (a kernel that calls BLAS, at its compile) is numba's own: it
    imports ``scipy.linalg`` and checks its integer width as before.  Where numba's target
    does not import ``arraymath`` as written for (another version), nothing changes.
    """
    import sys
    from numba.core import cpu
    original = cpu.CPUContext.load_additional_registries
    if getattr(original, 'deferred_blas_probe', False):
        return True
    try:
        if 'arraymath' not in inspect.getsource(original):
            return False
    except (OSError, TypeError):  # no source to read (a frozen or stripped install)
        return False

    def load_additional_registries(self):
        if 'numba.np.arraymath' in sys.modules:  # probed already, in this process
            return original(self)
        from numba.np import linalg
        ensure_blas = linalg.ensure_blas
        linalg.ensure_blas = _blas_files_present  # what arraymath's import binds and calls
        try:
            return original(self)
        finally:
            linalg.ensure_blas = ensure_blas
            arraymath = sys.modules.get('numba.np.arraymath')
            if getattr(arraymath, 'ensure_blas', None) is _blas_files_present:
                arraymath.ensure_blas = ensure_blas

    load_additional_registries.deferred_blas_probe = True
    cpu.CPUContext.load_additional_registries = load_additional_registries
    return True
