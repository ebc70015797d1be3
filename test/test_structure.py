"""The package's structure: no import circle, and inference never loads training code or torch.

The circle check reads every import statement of the installed package, function-level (lazy)
imports included, so a circle hidden behind a lazy import is found too.
"""

import ast
import functools
import re
import subprocess
import sys
from pathlib import Path

import eha_ros

ROOT = Path(eha_ros.__file__).resolve().parent
#: Generated message classes: not written here.
GENERATED = ('eha_ros.msg',)
#: What inference is: the plant, the surrogates, the health estimators and the nodes.
INFERENCE = ('eha_ros.physics', 'eha_ros.surrogates', 'eha_ros.health', 'eha_ros.nodes',
             'eha_ros.artefacts', 'eha_ros.mlp', 'eha_ros.graph')


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob('*.py'):
        parts = path.relative_to(ROOT.parent).with_suffix('').parts
        name = '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)
        if not name.startswith(GENERATED):
            out[name] = path
    return out


def _imports(name: str, path: Path, modules: dict) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its body."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                up = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(up + ([base] if base else []))
            found.add(base)
            found.update(f'{base}.{a.name}' for a in node.names)
    return {m for m in found if m in modules and m != name}


def _circles(graph: dict) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _graph() -> dict:
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        # a package's face (__init__) hands names on; an import of a submodule does not
        # run through its parent's body here
        graph[name] = {m for m in _imports(name, path, modules)
                       if not (modules[m].name == '__init__.py' and name.startswith(m + '.'))}
    return graph


def test_the_circle_finder_finds_a_circle():
    assert _circles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]
    assert _circles({'a': {'b'}, 'b': set()}) == []


def test_no_import_circle_in_the_package():
    graph = _graph()
    assert len(graph) > 50  # the walk saw the package
    assert 'eha_ros.surrogates.base' in graph['eha_ros.surrogates.registry']
    assert _circles(graph) == []


def _rooms(graph: dict) -> dict:
    """The imports between the package's rooms: each sub-package (``eha_ros.nodes``) and each
    top-level module (``eha_ros.graph``) is one room."""
    def room(m):
        return '.'.join(m.split('.')[:2])
    out = {}
    for name, deps in graph.items():
        out.setdefault(room(name), set()).update(room(d) for d in deps
                                                 if room(d) != room(name))
    return out


def test_the_room_graph_joins_modules_into_their_packages():
    assert _rooms({'eha_ros.a.x': {'eha_ros.b.y', 'eha_ros.a.z'}, 'eha_ros.a.z': set(),
                   'eha_ros.b.y': {'eha_ros.c'}, 'eha_ros.c': set()}) == {
        'eha_ros.a': {'eha_ros.b'}, 'eha_ros.b': {'eha_ros.c'}, 'eha_ros.c': set()}


def test_no_circle_between_the_packages_rooms():
    """Two sub-packages that import each other (through different modules: no module circle)
    stand on no floor of their own, as ``recording/`` and ``nodes/`` did while the recorder node
    lived in ``recording/`` and the Foxglove bridge read ``recording.definitions``."""
    rooms = _rooms(_graph())
    assert {'eha_ros.nodes', 'eha_ros.recording'} <= rooms['eha_ros.harness']
    assert _circles(rooms) == []


def test_surrogate_base_is_a_leaf_of_its_package():
    assert not {m for m in _graph()['eha_ros.surrogates.base']
                if m.startswith('eha_ros.surrogates')}


def test_inference_imports_neither_training_nor_torch():
    """Import every inference module, load every shipped artefact and run each estimator
    once, in a fresh interpreter: neither torch, scipy's optimisers nor eha_ros.training may
    be loaded."""
    names = sorted(m for m in _modules() if m.startswith(INFERENCE))
    code = '\n'.join([
        'import importlib, sys',
        *(f'importlib.import_module({m!r})' for m in names),
        'from eha_ros.surrogates.registry import load_surrogate, shipped_surrogates',
        'for n in shipped_surrogates(): load_surrogate(n)',
        'from eha_ros.health.valve_test import load_diagnostic',
        'from eha_ros.health.preflight import load_faults',
        'from eha_ros.health.steady_table import load_steady_table',
        'load_diagnostic(); load_faults(); load_steady_table()',
        'bad = sorted(m for m in sys.modules if m.split(".")[0] == "torch"',
        '             or m.startswith(("eha_ros.training", "scipy.optimize")))',
        'print(len(sys.modules), bad)',
    ])
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=300, cwd=str(ROOT.parent.parent))
    assert out.returncode == 0, out.stderr[-2000:]
    n, bad = out.stdout.split(' ', 1)
    assert int(n) > 100 and bad.strip() == '[]', out.stdout


def _private_imports(path: Path) -> list[str]:
    """``module.name`` of every private name (``_x``, not dunder) that ``path`` imports from
    another eha_ros module, relative imports included."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and (node.level or (node.module or '').startswith(
                'eha_ros')):
            out += [f'{"." * node.level}{node.module or ""}.{a.name}' for a in node.names
                    if a.name.startswith('_') and not a.name.startswith('__')]
    return out


def test_the_private_import_finder_finds_one(tmp_path):
    src = tmp_path / 'm.py'
    src.write_text('from eha_ros.a import b, _c as d\nfrom .e import _f\nfrom os import _g\n'
                   'from eha_ros.h import i as _i\n')
    assert _private_imports(src) == ['eha_ros.a._c', '.e._f']


def test_no_private_name_crosses_a_module():
    """What another module needs is public: no ``from eha_ros... import _name`` in the package
    or the benches."""
    benches = sorted((Path(__file__).resolve().parents[1] / 'bench').glob('*.py'))
    assert len(benches) > 5  # the walk saw the benches
    found = {str(p): _private_imports(p) for p in [*_modules().values(), *benches]}
    assert {p: names for p, names in found.items() if names} == {}


def _top_names(path: Path) -> set[str]:
    """Names a module defines or imports at its top level, and its classes' members
    (``Class.member``)."""
    out = set()
    for n in ast.parse(path.read_text(), str(path)).body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(n.name)
            if isinstance(n, ast.ClassDef):
                for m in n.body:
                    targets = ([m] if isinstance(m, (ast.FunctionDef, ast.AsyncFunctionDef))
                               else m.targets if isinstance(m, ast.Assign)
                               else [m.target] if isinstance(m, ast.AnnAssign) else [])
                    out.update(f'{n.name}.{getattr(t, "name", getattr(t, "id", ""))}'
                               for t in targets)
        elif isinstance(n, (ast.Assign, ast.AnnAssign)):
            for t in (n.targets if isinstance(n, ast.Assign) else [n.target]):
                out.update(e.id for e in ast.walk(t) if isinstance(e, ast.Name))
        elif isinstance(n, (ast.Import, ast.ImportFrom)):
            out.update((a.asname or a.name).split('.')[0] for a in n.names)
    return out


def _unresolved(ref: str, here: str, modules: dict, names) -> bool:
    """Whether the reference ``ref`` names nothing: ``eha_ros.x.y`` absolute; ``.x.y`` as
    Sphinx resolves it (in the module ``here`` first, else as the suffix of a full name)."""
    parts = ref.lstrip('.').split('.')

    def holds(mod, rest):
        return not rest or rest[0] in names(mod) or '.'.join(rest[:2]) in names(mod)

    if not ref.startswith('.'):
        return not any(holds('.'.join(parts[:k]), parts[k:])
                       for k in range(len(parts), 0, -1) if '.'.join(parts[:k]) in modules)
    if holds(here, parts):
        return False
    for k in range(len(parts), 0, -1):
        suffix = '.' + '.'.join(parts[:k])
        if any(m.endswith(suffix) and holds(m, parts[k:]) for m in modules):
            return False
    return True


def test_the_reference_checker_tells_stale_from_live():
    modules = _modules()
    names = functools.lru_cache(None)(lambda m: _top_names(modules[m]))
    here = 'eha_ros.physics.plant'
    for live in ('eha_ros.physics.loop', 'eha_ros.physics.loop.advance', '.loop.advance',
                 '.base.relative_error', 'eha_ros.surrogates.base.FluidSurrogate.p12',
                 'simulate'.join(['.', ''])):
        assert not _unresolved(live, here, modules, names), live
    for stale in ('eha_ros.physics.no_such_module', 'eha_ros.physics.loop.no_such',
                  '.dynamic_train',
                  '.health.InServiceEstimator', 'eha_ros.physics.fluid.FluidBlock'):
        assert _unresolved(stale, here, modules, names), stale


def test_docstrings_name_what_exists():
    """Every ``eha_ros.x`` and every Sphinx cross-reference to ``.x`` in the package's source
    names a module, or a name of one, that exists."""
    modules = _modules()
    names = functools.lru_cache(None)(lambda m: _top_names(modules[m]))
    absolute = re.compile(r'\beha_ros(?:\.[A-Za-z_]\w*)+')
    relative = re.compile(r':(?:mod|func|class|data|meth|attr|exc):`~?(\.[A-Za-z_][\w.]*)`')
    stale = []
    for mod, path in sorted(modules.items()):
        text = path.read_text()
        refs = [m.group(0) for m in absolute.finditer(text)]
        refs += [m.group(1).rstrip('.') for m in relative.finditer(text)]
        stale += [f'{mod}: {r}' for r in refs
                  if r != 'eha_ros.__file__' and not r.startswith(GENERATED)
                  and _unresolved(r, mod, modules, names)]
    assert stale == []
