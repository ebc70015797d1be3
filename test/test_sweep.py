"""Sweeps (:mod:`eha_ros.sweep`, ``eha-sweep``): spec refusals, the same dataset from every
engine, a worker killed on a real ``dask scheduler``, interrupt and resume, the report.

The shared sweep: hf and dlut on ``step_0p1`` over a 2 x 3 clearance-overlap grid (12 cases,
a few seconds on one core); its in-process dataset is the reference the other engines must
reproduce, timing and placement columns (``wall_*``, ``worker``) aside.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from hypothesis import given, settings, strategies as st

from eha_ros.sweep import SpecError, parse_spec, read_dataset, run_sweep
from eha_ros.sweep.dataset import TIMING_COLUMNS

BIN = Path(sys.executable).parent
SWEEP = str(BIN / 'eha-sweep')

SPEC = {'procedure': 'scenario', 'scenario': 'step_0p1', 'models': ['hf', 'dlut'],
        'seeds': [0], 'noise': False,
        'parameters': {'radial_clearance_m': [2.0e-6, 4.0e-6],
                       'overlap_supply_m': [0.0, 1.0e-6, 2.0e-6]}}
#: A longer one for the kill and interrupt tests: 8 points of about 2 s each (hf and the
#: reference's nn, 15 x hf's cost, on a 2 s sine), 16 cases.
SLOW = {'procedure': 'scenario', 'scenario': 'sine_0p01_2pi', 'models': ['hf', 'nn'],
        'noise': False,
        'parameters': {'radial_clearance_m': [2.0e-6, 3.0e-6],
                       'overlap_supply_m': [0.0, 1.0e-6, 2.0e-6, 3.0e-6]}}


def _env():
    env = dict(os.environ, NUMBA_NUM_THREADS='1', PYTHONUNBUFFERED='1')
    return env


def _write(path: Path, spec: dict) -> Path:
    path.write_text(yaml.safe_dump(spec))
    return path


def _table(folder):
    """The dataset without timing and placement, as a list of rows sorted by case id."""
    return read_dataset(folder, drop_timing=True).to_pylist()


@pytest.fixture(scope='module')
def reference(tmp_path_factory):
    """The shared sweep and the slow one, each run in process (no Dask)."""
    out = {}
    for name, raw in (('spec', SPEC), ('slow', SLOW)):
        folder = tmp_path_factory.mktemp('sweep') / name
        s = run_sweep(parse_spec(raw), folder, in_process=True, progress=False)
        assert s['ok'] == s['cases'] and s['ran'] == s['cases']
        out[name] = folder
    return out


# --- the spec --------------------------------------------------------------------------------

@pytest.mark.parametrize('change, words', [
    ({'bogus': 1}, "unknown key 'bogus'"),
    ({'procedure': 'wind_tunnel'}, "procedure = 'wind_tunnel'"),
    ({'scenario': 'step_9m'}, 'step_9m'),
    ({'models': ['hf', 'xgboost']}, "unknown model 'xgboost'"),
    ({'parameters': {'spool_colour': [1.0]}}, "unknown parameter 'spool_colour'"),
    ({'parameters': {'radial_clearance_m': [-1.0e-6]}}, 'radial_clearance_m'),
    ({'parameters': {'radial_clearance_m': [9.0e-6]}}, 'outside the range'),   # dlut's range
    ({'parameters': {'radial_clearance_m': ['wide']}}, "'wide' is not a number"),
    ({'seeds': [0, 1]}, 'noise: false would repeat every case'),
    ({'dt_s': 3.0e-7}, 'whole multiple'),
    ({'random': {'n': 5, 'ranges': {'overlap_supply_m': [1.0e-6, 0.0]}}}, 'lo < hi'),
])
def test_spec_refusals(change, words):
    raw = dict(SPEC, **change)
    with pytest.raises(SpecError) as e:
        parse_spec(raw)
    msg = str(e.value)
    assert words in msg and '\n' not in msg


@settings(max_examples=60, deadline=None)
@given(dt=st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(1, 1000).map(lambda n: n * 1e-9),
                    st.floats(1e-9, 2e-6)))
def test_converged_dt_is_a_whole_number_of_ns_below_the_step_or_refused(dt):
    """``converged_dt`` with the yardstick: any number is taken as it is or refused in one
    line naming the key; it is taken exactly where it is positive, below the comparison's
    1 us and a whole number of nanoseconds (so that the check at twice it is one too)."""
    raw = dict(SPEC, compare='yardstick', converged_dt=dt)
    if 0 < dt < 1e-6 and abs(round(dt * 1e9) - dt * 1e9) <= 1e-6 * dt * 1e9:
        assert parse_spec(raw).converged_dt == dt
    else:
        with pytest.raises(SpecError) as e:
            parse_spec(raw)
        assert 'converged_dt' in str(e.value) and '\n' not in str(e.value)
    with pytest.raises(SpecError, match='converged_dt needs compare: yardstick'):
        parse_spec(dict(SPEC, converged_dt=2.5e-8))


@pytest.mark.parametrize('procedure', ['scenario', 'preflight_check'])
def test_the_split_integrator_is_a_case_of_its_own_where_it_applies(procedure):
    """scenario and preflight_check take ``integrator: split`` (other ids than the explicit
    cases: another result); a step that is no whole number of its substeps is refused."""
    raw = {'procedure': procedure, 'models': ['hf'], 'seeds': [0], 'noise': True}
    if procedure == 'scenario':
        raw['scenario'] = 'step_0p1'
    split = parse_spec(dict(raw, integrator='split'))   # at the explicit scheme's own step
    explicit = parse_spec(raw)
    assert split.integrator == 'split' and explicit.integrator == 'explicit'
    assert parse_spec(dict(raw, integrator='split', dt_s=1e-5)).dt_s == 1e-5
    ids = {c.case_id for p in split.points() for c in p.cases}
    assert ids.isdisjoint(c.case_id for p in explicit.points() for c in p.cases)
    with pytest.raises(SpecError, match='whole number') as e:
        parse_spec(dict(raw, integrator='split', dt_s=2.5e-6))
    assert '\n' not in str(e.value)


def test_the_valve_test_refuses_another_integrator():
    with pytest.raises(SpecError, match='integrator: split is for procedures scenario') as e:
        parse_spec({'procedure': 'valve_test', 'models': ['hf'], 'integrator': 'split'})
    assert '\n' not in str(e.value)


def test_cli_refuses_a_bad_spec_before_anything_runs(tmp_path):
    """One line on stderr, exit 2, no output folder; the size guard the same way."""
    bad = _write(tmp_path / 'bad.yaml', dict(SPEC, parameters={'radial_clearance_m': [1.0]}))
    r = subprocess.run([SWEEP, str(bad), '--out', str(tmp_path / 'out'), '--in-process'],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 2 and r.stdout == ''
    assert r.stderr.count('\n') == 1 and 'radial_clearance_m' in r.stderr
    assert not (tmp_path / 'out').exists()
    big = _write(tmp_path / 'big.yaml', SPEC)
    r = subprocess.run([SWEEP, str(big), '--out', str(tmp_path / 'out'), '--max-cases', '11'],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 2 and '12 cases exceed --max-cases 11' in r.stderr
    assert r.stderr.count('\n') == 1 and not (tmp_path / 'out').exists()


def test_cases_and_ids():
    """Grid axes crossed, random draws reproducible, ties applied, ids hash the inputs."""
    s = parse_spec(SPEC)
    pts = s.points()
    assert len(pts) == 6 and all(len(p.cases) == 2 for p in pts)
    ids = [c.case_id for p in pts for c in p.cases]
    assert len(set(ids)) == 12
    assert [c.case_id for p in parse_spec(SPEC).points() for c in p.cases] == ids
    other = parse_spec(dict(SPEC, parameters={'radial_clearance_m': [2.0e-6, 4.0e-6],
                                              'overlap_supply_m': [0.0, 1.0e-6, 2.5e-6]}))
    common = set(ids) & {c.case_id for p in other.points() for c in p.cases}
    assert len(common) == 8   # the four points both grids hold, two models each
    r = {'procedure': 'valve_test', 'tie': {'overlap_return_m': 'overlap_supply_m'},
         'random': {'n': 4, 'seed': 3, 'ranges': {'overlap_supply_m': [0.0, 2.0e-6]}}}
    a, b = parse_spec(r).points(), parse_spec(r).points()
    assert [p.inputs for p in a] == [p.inputs for p in b]
    assert all(p.inputs['overlap_return_m'] == p.inputs['overlap_supply_m'] for p in a)
    assert all(0.0 <= p.inputs['overlap_supply_m'] <= 2.0e-6 for p in a)
    assert len({p.inputs['overlap_supply_m'] for p in a}) == 4


@pytest.mark.parametrize('raw', [
    SPEC, SLOW, {'procedure': 'valve_test'},
    {'procedure': 'preflight_check', 'noise': True, 'seeds': 3},
    {'procedure': 'scenario', 'scenario': ['step_0p1', 'ramp_0p1'], 'models': ['hf', 'dlut'],
     'noise': True, 'seeds': [0, 5], 'parameters': {'radial_clearance_m': [2e-6, 3e-6]},
     'random': {'n': 3, 'ranges': {'overlap_supply_m': [0.0, 1e-6]}},
     'cases': [{'radial_clearance_m': 5e-6, 'seed': 9}, {'overlap_supply_m': 2e-6}]},
    {'procedure': 'scenario', 'scenario': 'step_0p1', 'models': ['dlut', 'lut'],
     'compare': 'yardstick', 'large_dts': [2e-6, 5e-6]},
])
def test_the_size_guard_counts_every_case(raw):
    from eha_ros.sweep.spec import count_cases
    s = parse_spec(raw)
    assert count_cases(s) == sum(len(p.cases) for p in s.points())


def test_the_example_specs_parse():
    """The specs shipped in config/sweeps (installed beside the parameters) are valid."""
    from eha_ros.physics.params import config_dir
    from eha_ros.sweep import load_spec
    files = sorted((config_dir() / 'sweeps').glob('*.yaml'))
    assert [f.stem for f in files] == ['preflight_monte_carlo', 'valve_test_drift',
                                       'valve_test_settled_drift', 'wear_plane']
    for f in files:
        assert load_spec(f).points()


# --- engines ---------------------------------------------------------------------------------

def test_the_dataset_is_complete_and_physical(reference):
    """One row per case, surrogate errors against hf on the same case, the inputs set."""
    t = pq.read_table(reference['spec'])   # pyarrow alone reads the folder
    rows = t.to_pylist()
    assert len(rows) == 12 and len({r['case_id'] for r in rows}) == 12
    assert {r['status'] for r in rows} == {'ok'}
    for r in rows:
        assert r['radial_clearance_m'] in (2.0e-6, 4.0e-6)
        if r['model'] == 'hf':
            assert r['jack_rel_error'] is None
        else:   # dlut meets its in-loop bound on step_0p1 at every wear point
            assert 0.0 < r['jack_rel_error'] < 0.05
        assert 0.0 < r['rms_tracking_error_m'] < 1e-4   # a 0.1 mm step, tracked
        # at the end the jack stands within 10 % of the 0.1 mm command (the friction band)
        assert abs(r['final_position_m'] - 1e-4) < 1e-5


def test_localcluster_gives_the_in_process_dataset(reference, tmp_path):
    s = run_sweep(parse_spec(SPEC), tmp_path / 'lc', workers=2, progress=False)
    assert s['ok'] == 12 and s['engine'] == 'LocalCluster of 2 workers'
    assert _table(tmp_path / 'lc') == _table(reference['spec'])
    workers = set(read_dataset(tmp_path / 'lc').column('worker').to_pylist())
    assert all(w.startswith('tcp://') for w in workers)


def test_a_case_that_raises_is_a_row_not_a_failure(tmp_path):
    """A case whose run raises (here: a step the controller period is no multiple of, which
    the check refuses and a worker, given a checked spec, does not check again) is a row with
    status error and the message."""
    from eha_ros.sweep.engine import run_batch
    spec = parse_spec(dict(SPEC, dt_s=3e-7), check=False)
    rows = run_batch(spec.canonical(), spec.base, spec.points()[:2])
    assert len(rows) == 4 and {r['status'] for r in rows} == {'error'}
    assert all('whole multiple' in r['error'] for r in rows)


def _scheduler(tmp_path):
    """A real ``dask scheduler`` on an OS-chosen port and two ``dask worker`` processes
    (no nanny: a killed worker stays dead)."""
    sched_file = tmp_path / 'scheduler.json'
    env = _env()
    procs = [subprocess.Popen([str(BIN / 'dask'), 'scheduler', '--port', '0',
                               '--dashboard-address', ':0', '--scheduler-file',
                               str(sched_file)], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)]
    deadline = time.monotonic() + 60
    address = None
    while address is None:   # the scheduler writes the file in place: wait until it is whole
        assert time.monotonic() < deadline, 'the dask scheduler wrote no scheduler file'
        try:
            address = json.loads(sched_file.read_text())['address']
        except (OSError, ValueError, KeyError):
            time.sleep(0.1)
    for _ in range(2):
        procs.append(subprocess.Popen([str(BIN / 'dask'), 'worker', address, '--nthreads', '1',
                                       '--no-nanny', '--no-dashboard'], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    return address, procs


def _batch_key(point_id: str) -> str:
    """The Dask key of a batch holding just this point (``--batch-size 1``)."""
    import hashlib
    return 'eha-sweep-' + hashlib.sha256(point_id.encode()).hexdigest()[:16]


def test_a_worker_killed_mid_sweep_loses_and_repeats_nothing(reference, tmp_path):
    """SIGKILL to a worker running a batch: the scheduler runs that batch again on the other
    worker, every case is written once, and the dataset equals the in-process one.

    No race: once a batch is written the victim is frozen (SIGSTOP), so it can neither finish
    nor report its batch; the batch the scheduler then still sees it processing is the one
    the kill takes, and its rows must come from the other worker."""
    from distributed import Client
    address, procs = _scheduler(tmp_path)
    out = tmp_path / 'remote'
    try:
        client = Client(address, timeout='30s')
        client.wait_for_workers(2, timeout=60)
        pids = client.run(os.getpid)
        sweep = subprocess.Popen([SWEEP, str(_write(tmp_path / 'slow.yaml', SLOW)), '--out',
                                  str(out), '--scheduler', address, '--batch-size', '1',
                                  '--quiet'], env=_env(), stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        victim, lost = None, ()
        deadline = time.monotonic() + 180
        while not lost and time.monotonic() < deadline and sweep.poll() is None:
            if list(out.glob('part-*.parquet')):   # mid-sweep: a batch written
                for w in client.processing():
                    os.kill(pids[w], signal.SIGSTOP)
                    time.sleep(0.5)   # whatever it sent before it froze has arrived
                    lost = tuple(client.processing()[w])
                    if lost:
                        victim = w
                        break
                    os.kill(pids[w], signal.SIGCONT)   # between two batches: not this one
            time.sleep(0.05)
        assert lost, 'no worker was running a batch'
        os.kill(pids[victim], signal.SIGKILL)
        stdout, stderr = sweep.communicate(timeout=300)
        assert sweep.returncode == 0, stderr
        client.close()
    finally:
        for p in procs:
            p.kill()
            p.wait()
    rows = read_dataset(out).to_pylist()
    ids = [r['case_id'] for r in rows]
    assert len(ids) == len(set(ids)) == 16
    rerun = [r for r in rows if _batch_key(r['point_id']) in lost]
    assert rerun and all(r['worker'] != victim for r in rerun)   # ran again, elsewhere
    assert _table(out) == _table(reference['slow'])
    assert json.loads(stdout)['ok'] == 16


def test_interrupt_then_resume_gives_the_uninterrupted_dataset(reference, tmp_path):
    """Ctrl-C (SIGINT) after the first batch: exit 130, finished batches kept, the summary
    says how to resume; ``--resume`` runs only the rest; the dataset is the whole one."""
    spec = _write(tmp_path / 'slow.yaml', SLOW)
    out = tmp_path / 'cut'
    # SIGINT as a terminal leaves it (a shell starting this suite in the background ignores
    # SIGINT, and a child inherits that: Python then installs no KeyboardInterrupt handler)
    p = subprocess.Popen([SWEEP, str(spec), '--out', str(out), '--in-process',
                          '--batch-size', '2'], env=_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 180
    while not list(out.glob('part-*.parquet')) and time.monotonic() < deadline:
        time.sleep(0.02)
    # frozen, then interrupted: it takes the signal within its current case (about 2 s),
    # with three batches of two such points still to run
    p.send_signal(signal.SIGSTOP)
    p.send_signal(signal.SIGINT)
    p.send_signal(signal.SIGCONT)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 130, stderr
    kept = json.loads(stdout)
    assert kept['interrupted'] and 0 < kept['ran'] < 16
    assert f'resume with: eha-sweep {spec} --out {out} --resume' in stderr
    assert len(read_dataset(out).to_pylist()) == kept['ran']
    again = subprocess.run([SWEEP, str(spec), '--out', str(out), '--in-process', '--resume',
                            '--quiet'], capture_output=True, text=True, env=_env(), timeout=180)
    assert again.returncode == 0, again.stderr
    s = json.loads(again.stdout)
    assert s['already_done'] == kept['ran'] and s['ran'] == 16 - kept['ran']
    assert _table(out) == _table(reference['slow'])


def test_an_existing_folder_is_never_overwritten(reference, tmp_path):
    spec = _write(tmp_path / 's.yaml', SPEC)
    before = sorted(p.name for p in reference['spec'].iterdir())
    r = subprocess.run([SWEEP, str(spec), '--out', str(reference['spec']), '--in-process'],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 2 and 'not empty' in r.stderr
    other = _write(tmp_path / 'o.yaml', dict(SPEC, models=['hf']))
    r = subprocess.run([SWEEP, str(other), '--out', str(reference['spec']), '--resume'],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 2 and 'another spec' in r.stderr
    assert sorted(p.name for p in reference['spec'].iterdir()) == before


# --- reading ---------------------------------------------------------------------------------

def test_report_table_and_plots(reference, tmp_path):
    import matplotlib.image as mpimg
    r = subprocess.run([SWEEP, 'report', str(reference['spec']), '--plots', str(tmp_path)],
                       capture_output=True, text=True, env=_env(), timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith('| model | cases | ok | diverged | error |')
    assert any(line.startswith('| dlut | 6 | 6 | 0 | 0 |') for line in lines)
    heat = tmp_path / 'heatmap_jack_rel_error.png'
    spread = tmp_path / 'spread_jack_rel_error.png'
    for png in (heat, spread):
        img = mpimg.imread(png)
        assert img.shape[0] > 200 and img.shape[1] > 300
        assert np.std(img[..., :3]) > 0.05   # drawn, not blank
    bad = subprocess.run([SWEEP, 'report', str(reference['spec']), '--metric', 'colour'],
                         capture_output=True, text=True, env=_env(), timeout=120)
    assert bad.returncode == 2 and "unknown metric 'colour'" in bad.stderr


def test_timing_columns_are_named_as_such(reference):
    names = read_dataset(reference['spec']).column_names
    assert [n for n in names if n.startswith('wall') or n == 'worker'] == list(TIMING_COLUMNS)


def test_a_worker_loads_neither_ros_nor_torch_nor_training():
    """What a worker imports to run a batch of each procedure (physics, surrogates, health
    estimators): no rclpy, no torch, no eha_ros.training - a worker needs none of them."""
    code = '\n'.join([
        'import sys',
        'from eha_ros.sweep import parse_spec',
        'from eha_ros.sweep.engine import run_batch',
        'for raw in ({"procedure": "valve_test"},',
        '            {"procedure": "scenario", "scenario": "step_0p01", "models": ["dlut"]},',
        '            {"procedure": "preflight_check", "noise": True}):',
        '    s = parse_spec(raw)',
        '    rows = run_batch(s.canonical(), s.base, s.points())',
        '    assert {r["status"] for r in rows} == {"ok"}, rows',
        'bad = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "rclpy")',
        '             or m.startswith("eha_ros.training"))',
        'print(bad)'])
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=300, env=_env())
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == '[]'


def test_batches_are_sized_by_time():
    """One point until one has finished, then about 2 s of work per batch (at most 32), and
    smaller towards the end so the tail spreads over the workers; every point once."""
    from eha_ros.sweep.engine import Batcher
    b = Batcher(list(range(200)))
    first = b.next(2)
    assert first == [0]
    b.record([{'point_id': 'a', 'wall_point_s': 0.1}])     # 0.1 s a point: 20 per batch
    assert len(b.next(2)) == 20
    b.record([{'point_id': 'b', 'wall_point_s': 0.001}])   # mean 0.05 s: capped at 32
    assert len(b.next(2)) == 32
    got = first + list(range(1, 53))
    while b:
        batch = b.next(2)
        assert 1 <= len(batch) <= max(1, (len(b.pending) + len(batch)) // 4)
        got += batch
    assert got == list(range(200))
    fixed = Batcher(list(range(10)), size=4)
    assert [len(fixed.next(2)) for _ in range(3)] == [4, 4, 2]


def test_a_local_cluster_gives_its_workers_one_numba_thread_and_leaves_this_process_alone():
    """The workers run single-threaded; this process's NUMBA_NUM_THREADS is untouched (numba
    here may have started its pool: a changed value would fail its next compilation)."""
    from eha_ros.sweep.engine import _client, _close
    before = os.environ.get('NUMBA_NUM_THREADS')
    client, cluster = _client(1, None)
    try:
        seen = client.run(lambda: os.environ.get('NUMBA_NUM_THREADS'))
    finally:
        _close(client, cluster)
    assert list(seen.values()) == [before or '1']
    assert os.environ.get('NUMBA_NUM_THREADS') == before


def test_the_valve_test_keeps_its_curves_whole():
    """A valve-test case's kept P12 is every curve whole, at the schedule's points and flows
    (the test runs in holds, not in ticks: no signal interval applies), and the spec's one
    procedure declares that column and runs the point."""
    from eha_ros.physics.maintenance import valve_test_schedule
    spec = parse_spec({'procedure': 'valve_test', 'signals': ['p12_pa']})
    assert ('signal_p12_pa', 'floats') in spec.proc.columns()
    (row,) = spec.proc.run_point(spec.points()[0])
    assert row['status'] == 'ok', row['error']
    sch = valve_test_schedule('reference')
    assert row['signal_p12_pa'].shape == (sch['n_points'] * len(sch['flows_m3_s']),)
    assert np.all(np.isfinite(row['signal_p12_pa']))
    with pytest.raises(SpecError, match='keeps its P12 curves whole'):
        parse_spec({'procedure': 'valve_test', 'signals': ['p12_pa'], 'signal_dt_s': 1e-2})
