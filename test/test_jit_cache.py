"""The package's numba cache is dropped when any of its sources changed (eha_ros.jit_cache):
numba itself checks a cached function against its own file only."""

import os
import subprocess
import sys
import textwrap

from eha_ros.jit_cache import drop_stale_cache, STAMP_NAME

_HELPER = '''
from numba import njit


@njit(cache=True, inline='always')
def gain():
    return {value}
'''
_KERNEL = '''
from numba import njit

from .helper import gain


@njit(cache=True)
def kernel(x):
    return gain() * x
'''
_RUN = '''
import sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
if sys.argv[2] == 'guarded':
    from eha_ros.jit_cache import drop_stale_cache
    drop_stale_cache(Path(sys.argv[1]) / 'pkg')
from pkg.kernel import kernel
print(kernel(1.0))
'''


def _package(root, value):
    pkg = root / 'pkg'
    pkg.mkdir(exist_ok=True)
    (pkg / '__init__.py').write_text('')
    (pkg / 'helper.py').write_text(_HELPER.format(value=value))
    (pkg / 'kernel.py').write_text(_KERNEL)
    return pkg


def _run(root, mode):
    env = dict(os.environ)
    env.pop('NUMBA_CACHE_DIR', None)
    out = subprocess.run([sys.executable, '-c', _RUN, str(root), mode], capture_output=True,
                         text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return float(out.stdout.split()[-1])


def test_a_changed_module_reaches_a_cached_kernel_that_inlines_it(tmp_path):
    """A kernel cached on disk that inlines a helper of another module: after the helper
    changes, numba alone still loads the old code from the cache; with the package's cache
    dropped on a changed fingerprint, the new code runs."""
    for mode in ('plain', 'guarded'):
        root = tmp_path / mode
        root.mkdir()
        pkg = _package(root, 2.0)
        assert _run(root, mode) == 2.0
        helper = pkg / 'helper.py'
        helper.write_text(_HELPER.format(value=3.0))
        st = helper.stat()
        os.utime(helper, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # a later edit
        expected = 2.0 if mode == 'plain' else 3.0  # numba's own check misses the change
        assert _run(root, mode) == expected, mode


def test_cache_files_go_only_when_a_source_changed(tmp_path, monkeypatch):
    """No fingerprint stored: every cache file goes (its provenance is unknown); the same
    sources: nothing goes; one file changed: every cache file of every folder goes, under
    NUMBA_CACHE_DIR too, and nothing else does."""
    pkg = _package(tmp_path, 1.0)
    user = tmp_path / 'user_cache'
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(user))
    mirrored = user / pkg.resolve().relative_to(pkg.resolve().anchor)

    def plant():
        files = [pkg / '__pycache__' / 'kernel.kernel-8.py311.nbi',
                 pkg / '__pycache__' / 'kernel.kernel-8.py311.1.nbc',
                 mirrored / 'helper.gain-5.py311.nbi']
        for f in files:
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_bytes(b'x')
        return files

    keep = pkg / '__pycache__' / 'kernel.cpython-311.pyc'
    keep.parent.mkdir(parents=True, exist_ok=True)
    keep.write_bytes(b'pyc')
    files = plant()
    assert drop_stale_cache(pkg) == 3 and not any(f.exists() for f in files)
    assert (pkg / '__pycache__' / STAMP_NAME).is_file()
    files = plant()
    assert drop_stale_cache(pkg) == 0 and all(f.exists() for f in files)
    (pkg / 'helper.py').write_text(textwrap.dedent(_HELPER.format(value=1.5)))
    assert drop_stale_cache(pkg) == 3 and not any(f.exists() for f in files)
    assert keep.exists()
    assert drop_stale_cache(pkg) == 0


# --- numba's copy of an inlined callee ---------------------------------------------------------

_NESTED = '''
import sys
if sys.argv[1] == 'shared':
    import eha_ros.physics  # noqa: F401  (installs the shared copy)
from numba import njit
from numba.core import inline_closurecall, ir

copies = [0]
plain = ir.Var.__deepcopy__


def counted(self, memo):
    copies[0] += 1
    return plain(self, memo)


ir.Var.__deepcopy__ = counted


@njit(inline='always')
def leaf(x, k):
    y = 0.0
    for i in range(k):
        if x > i:
            y += x - i
        else:
            y -= 0.5 * x
    return y


@njit(inline='always')
def middle(x, k):
    a = leaf(x, k)
    b = leaf(a, k + 1) if a > 0 else leaf(-a, k)
    return a + b


@njit
def top(x):
    return middle(x, 3) + middle(2.0 * x, 4) + middle(-x, 5)


print(getattr(inline_closurecall.InlineWorker.inline_ir, 'shared_copy', False),
      repr(top(1.25)), copies[0])
'''


def _nested(mode: str):
    r = subprocess.run([sys.executable, '-c', _NESTED, mode], capture_output=True, text=True,
                       timeout=300, cwd='/')
    assert r.returncode == 0, r.stderr
    shared, value, copies = r.stdout.split()
    return shared == 'True', value, int(copies)


def test_inlined_callees_are_copied_with_one_scope_and_compile_to_the_same_code():
    """eha_ros.physics makes numba copy an inlined callee's IR with one memo for all its
    blocks (on the pinned numba; the test fails if the copy it replaces is no longer
    there): a nested inline='always' kernel gives the same result from far fewer variable
    copies (a count, not a time: the compile itself is about 3x faster, jit_cache)."""
    shared, value, copies = _nested('shared')
    plain, plain_value, plain_copies = _nested('plain')
    assert shared and not plain
    assert value == plain_value
    assert copies * 3 < plain_copies, (copies, plain_copies)


def test_the_shared_copy_replaces_only_the_code_it_was_written_for():
    import inspect

    from numba.core.inline_closurecall import InlineWorker

    import eha_ros.physics  # noqa: F401  (installs it)
    from eha_ros.jit_cache import shared_copy_source
    patched = InlineWorker.inline_ir
    assert patched.shared_copy
    assert shared_copy_source('def inline_ir(self):\n    return None\n') is None
    # numba's own method as it ships: replaced at one place, line for line
    lines, first = inspect.getsourcelines(patched)   # numba's file, at numba's line numbers
    source = textwrap.dedent(''.join(lines))
    assert source.startswith('def inline_ir(') and 'new_block = copy.deepcopy' in source
    new = shared_copy_source(source)
    assert new.count('\n') == source.count('\n')
    assert 'kernel_copy.blocks = copy.deepcopy(the_ir.blocks)' in new
    assert 'new_block = copy.deepcopy' not in new
    assert patched.__code__.co_firstlineno == first


_BLAS_PROCESS = '''
import sys
import numpy as np
from numba import njit
from eha_ros.physics import default_params, simulate
from eha_ros.jit_cache import defer_blas_probe
simulate(default_params(), 'step_0p1', duration_s=0.002, controller_period_s=1e-3,
         record_dt_s=None)
import numba.np.arraymath as arraymath
from numba.np import linalg
print(defer_blas_probe(), 'scipy.linalg' in sys.modules, arraymath._HAVE_BLAS,
      arraymath.ensure_blas is linalg.ensure_blas)
linalg.ensure_blas()   # numba's own probe: the same answer
dot = njit(lambda a, b: np.dot(a, b))   # a kernel calling BLAS: numba's own check at compile
print(dot(np.arange(3.0), np.arange(3.0)), 'scipy.linalg' in sys.modules)
'''


def test_a_kernel_loads_without_scipy_linalg_and_blas_still_works():
    """A fresh process runs the plant without importing scipy.linalg (numba's import-time
    probe looks for the file); the probe's answer is numba's own, and a kernel that calls
    BLAS compiles and runs, numba then importing scipy.linalg as it always did."""
    out = subprocess.run([sys.executable, '-c', _BLAS_PROCESS], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split('\n')[:2] == ['True False True True', '5.0 True']


def test_the_blas_probe_refuses_where_scipy_has_no_blas(monkeypatch):
    import importlib.util

    import pytest

    from eha_ros.jit_cache import _blas_files_present
    _blas_files_present()   # installed here
    monkeypatch.setattr(importlib.util, 'find_spec', lambda name: None)
    with pytest.raises(ImportError, match='scipy 0.16'):
        _blas_files_present()
