"""Every bench runs: ``bench/<name>.py --smoke`` for each script of the folder (a new bench is
covered without anyone listing it), and the pin files agree.

A smoke run is the bench's own code path on a tiny case; it prints the bench's JSON with
``"smoke": true`` (so that nobody quotes its numbers). The test checks that the script exits 0,
that its last JSON object says it is a smoke run of that bench, and that no case in it reports
an error. It asserts nothing about the figures: those are measured, not tested.
"""

import json
from pathlib import Path
import re
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = ROOT / 'bench'
#: Every bench script (helpers would start with ``_``; there are none today).
BENCHES = sorted(p.stem for p in BENCH_DIR.glob('*.py') if not p.name.startswith('_'))
#: A smoke run is a few seconds to a minute here; far beyond that, something is stuck.
SMOKE_TIMEOUT_S = 600


def last_json(text: str) -> dict:
    """The last JSON object printed (compact on one line, or indented over several)."""
    lines = text.splitlines()
    for k in range(len(lines) - 1, -1, -1):
        if lines[k].startswith('{'):
            try:
                return json.loads('\n'.join(lines[k:]))
            except ValueError:
                continue
    raise AssertionError(f'no JSON object in the output:\n{text[-2000:]}')


def errors_in(obj, path='') -> list:
    """Paths of every ``error`` entry in a bench's JSON that is neither empty nor 0."""
    found = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k == 'error' and v not in (None, '', [], 0):  # 0: a count of errors
                found.append(f'{path}/{k}: {v}')
            else:
                found += errors_in(v, f'{path}/{k}')
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            found += errors_in(v, f'{path}[{i}]')
    return found


@pytest.fixture(scope='session')
def bench_data_dir(tmp_path_factory):
    """Map databases of the benches, built once per test process (not in ``~/.cache``)."""
    return tmp_path_factory.mktemp('bench-data')


def test_every_bench_is_collected():
    assert len(BENCHES) >= 16 and 'plant_rtf' in BENCHES and 'sweep' in BENCHES


@pytest.mark.parametrize('name', BENCHES)
def test_bench_smoke(name, ros_env, bench_data_dir, tmp_path):
    env = dict(ros_env, EHA_ROS_DATA_DIR=str(bench_data_dir), MPLBACKEND='Agg')
    r = subprocess.run([sys.executable, str(BENCH_DIR / f'{name}.py'), '--smoke'],
                       cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=SMOKE_TIMEOUT_S)
    assert r.returncode == 0, f'bench/{name}.py --smoke exit {r.returncode}:\n{r.stderr[-4000:]}'
    out = last_json(r.stdout)
    assert out.get('smoke') is True, f'bench/{name}.py --smoke does not say it is a smoke run'
    assert out.get('benchmark', '').startswith(name), out.get('benchmark')
    assert errors_in(out) == []


def test_smoke_json_checks_can_fail():
    """The two checks above find what they are meant to find."""
    assert last_json('progress\n{"a": 1}\n{\n "b": [1,\n  2]\n}\n') == {'b': [1, 2]}
    assert errors_in({'x': [{'error': None}, {'y': {'error': 'boom'}}], 'error': 0}) == [
        '/x[1]/y/error: boom']
    with pytest.raises(AssertionError):
        last_json('no json here')


# --- pins -------------------------------------------------------------------------------------

_PIN = re.compile(r'^\s*"?([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s";#]+)"?,?\s*(#.*)?$')


def normalise(name: str) -> str:
    """PEP 503 name: case and runs of ``-_.`` do not matter."""
    return re.sub(r'[-_.]+', '-', name).lower()


def pins(lines) -> dict:
    """``{name: version}`` of every ``name==version`` line; a package pinned twice to different
    versions is an error of its own."""
    out = {}
    for line in lines:
        m = _PIN.match(line)
        if not m:
            continue
        name, version = normalise(m.group(1)), m.group(2)
        assert out.get(name, version) == version, f'{name} pinned to {out[name]} and {version}'
        out[name] = version
    return out


def pin_files() -> dict:
    build = re.search(r'\[build-system\]\s*requires\s*=\s*\[(.*?)\]',
                      (ROOT / 'pyproject.toml').read_text(), re.S).group(1)
    return {'requirements.txt': pins((ROOT / 'requirements.txt').read_text().splitlines()),
            'requirements-bench.txt': pins(
                (ROOT / 'requirements-bench.txt').read_text().splitlines()),
            'pyproject.toml [build-system]': pins(build.splitlines())}


def test_pin_files_agree_on_every_shared_package():
    files = pin_files()
    assert len(files['requirements.txt']) > 50 and len(files['pyproject.toml [build-system]']) > 20
    seen, clashes = {}, []
    for fname, p in files.items():
        for name, version in p.items():
            if name in seen and seen[name][1] != version:
                clashes.append(f'{name}: {seen[name][0]} {seen[name][1]}, {fname} {version}')
            seen.setdefault(name, (fname, version))
    assert clashes == []


def test_bench_requirements_install_on_top_of_the_main_ones():
    lines = [ln.strip() for ln in (ROOT / 'requirements-bench.txt').read_text().splitlines()
             if ln.strip() and not ln.lstrip().startswith('#')]
    assert lines[0] == '-r requirements.txt'
    # what the bench file adds is new: nothing the main file pins is pinned again
    main = pin_files()['requirements.txt']
    assert [n for n in pins(lines) if n in main] == []


def test_pins_parser():
    assert pins(['Foo_Bar==1.2 # why', '  "ros-rclpy==9.1.2",', '-r x.txt', 'baz>=1']) == {
        'foo-bar': '1.2', 'ros-rclpy': '9.1.2'}
    with pytest.raises(AssertionError):
        pins(['a==1', 'A==2'])


def test_plant_rtf_against_a_revision_times_both_trees_side_by_side(tmp_path):
    """``--against REV`` (here HEAD, in a worktree of its own) prints a ratio per case from
    both trees' own timings, and leaves no worktree behind."""
    r = subprocess.run([sys.executable, str(BENCH_DIR / 'plant_rtf.py'), '--against', 'HEAD',
                        '--smoke'], cwd=tmp_path, capture_output=True, text=True,
                       timeout=SMOKE_TIMEOUT_S)
    assert r.returncode == 0, r.stderr[-3000:]
    out = last_json(r.stdout)
    assert out['smoke'] is True and len(out['rounds']) == 1
    assert set(out['rounds'][0]) == {'checkout', 'against'}
    assert len(out['cases']) == 4 and all(v['ratio'] > 0 for v in out['cases'].values())
    trees = subprocess.run(['git', '-C', str(ROOT), 'worktree', 'list'], capture_output=True,
                           text=True).stdout
    assert 'eha-rtf-against' not in trees
    bad = subprocess.run([sys.executable, str(BENCH_DIR / 'plant_rtf.py'), '--against',
                          'no-such-rev'], cwd=tmp_path, capture_output=True, text=True)
    assert bad.returncode != 0 and 'no-such-rev' in bad.stderr.strip().splitlines()[-1]
