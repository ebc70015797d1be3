"""The package's structure: no import circle, and inference never loads training code or torch.

The circle check reads every import statement of the installed package, function-level (lazy)
imports included, so a circle hidden behind a lazy import is found too.
"""

import ast
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
