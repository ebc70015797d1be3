"""eha_ros.realtime: SCHED_FIFO, affinity and memory lock on every thread, warnings instead of
errors when the OS refuses, and the garbage-collector tools.

Scheduling is only ever changed in child processes (never in the pytest process).  A child
loads the installed ``eha_ros/realtime.py`` by path (it is stdlib-only) from a world-readable
copy, with ``python -I -S``, so it runs the same whatever user it runs as.  No test depends on
wall-clock timing.
"""

import ctypes
import gc
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile

from hypothesis import given, strategies as st
import pytest

from eha_ros import realtime
from eha_ros.realtime import (RT_DEFAULTS, GcPauses, RealtimeSettings, apply_realtime,
                              current_realtime, settle_gc)

CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23
PR_CAPBSET_DROP = 24
NOBODY = 65534

# argv: module path, settings as JSON, threads mode.  Starts a thread before apply_realtime and
# one after, and reads back every thread's policy, priority and affinity straight from the OS.
CHILD = r'''
import importlib.util, json, os, sys, threading
spec = importlib.util.spec_from_file_location('rt_under_test', sys.argv[1])
rt = importlib.util.module_from_spec(spec)
sys.modules[spec.name] = rt
spec.loader.exec_module(rt)
settings = rt.RealtimeSettings(**json.loads(sys.argv[2]))
stop = threading.Event()
before = threading.Thread(target=stop.wait)
before.start()
try:
    warnings, raised = rt.apply_realtime(settings, sys.argv[3]), None
except BaseException as e:
    warnings, raised = None, repr(e)
after = threading.Thread(target=stop.wait)
after.start()

def sched(tid):
    return [os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority,
            sorted(os.sched_getaffinity(tid))]

status = dict(line.split(':', 1) for line in open('/proc/self/status') if ':' in line)
out = {'warnings': warnings, 'raised': raised, 'main': sched(0),
       'main_tid': threading.get_native_id(), 'before_tid': before.native_id,
       'after_tid': after.native_id,
       'threads': {tid: sched(int(tid)) for tid in os.listdir('/proc/self/task')},
       'vmlck_kb': int(status['VmLck'].split()[0]), 'cap_eff': int(status['CapEff'], 16),
       'uid': os.getuid(), 'fifo': os.SCHED_FIFO, 'other': os.SCHED_OTHER,
       'current': rt.current_realtime()}
stop.set()
before.join()
after.join()
print(json.dumps(out))
'''


@pytest.fixture(scope='module')
def module_copy():
    """A world-readable copy of the installed realtime.py (children may run as 'nobody')."""
    folder = tempfile.mkdtemp(prefix='eha-realtime-')
    os.chmod(folder, 0o755)
    path = os.path.join(folder, 'realtime.py')
    shutil.copyfile(realtime.__file__, path)
    os.chmod(path, 0o644)
    yield path
    shutil.rmtree(folder, ignore_errors=True)


def _python(code, *args, preexec_fn=None, cwd=None):
    return subprocess.run([sys.executable, '-I', '-S', '-c', code, *args],
                          capture_output=True, text=True, timeout=120, preexec_fn=preexec_fn,
                          cwd=cwd)


def run_child(module_copy, preexec_fn=None, threads='all', **settings) -> dict:
    r = _python(CHILD, module_copy, json.dumps(settings), threads, preexec_fn=preexec_fn,
                cwd=os.path.dirname(module_copy))
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def fifo_allowed() -> bool:
    """Whether a child of this process may switch to SCHED_FIFO (probe in a child)."""
    return _python('import os; os.sched_setscheduler(0, os.SCHED_FIFO, '
                   'os.sched_param(1))').returncode == 0


def _become_nobody():
    os.setgroups([])
    os.setgid(NOBODY)
    os.setuid(NOBODY)


def nobody_can_run_python() -> bool:
    """Whether the interpreter is usable by 'nobody' (not if it lives under a private /root)."""
    try:
        return _python('pass', preexec_fn=_become_nobody, cwd='/').returncode == 0
    except OSError:  # exec refused
        return False


def unprivileged_preexec():
    """What a child runs before exec so that SCHED_FIFO and mlockall are refused.

    RLIMIT_RTPRIO and RLIMIT_MEMLOCK to 0; as root, which bypasses both limits through
    CAP_SYS_NICE and CAP_IPC_LOCK, also drop those privileges: become 'nobody' where the
    interpreter allows it, else stay uid 0 but drop the two capabilities from the bounding set,
    which an exec by root then no longer grants.
    """
    if os.geteuid() != 0:
        def limits():
            resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
            resource.setrlimit(resource.RLIMIT_MEMLOCK, (0, 0))
        return limits, 'rlimits'
    as_nobody = nobody_can_run_python()

    def drop():
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
        resource.setrlimit(resource.RLIMIT_MEMLOCK, (0, 0))
        if as_nobody:
            _become_nobody()
            return
        libc = ctypes.CDLL(None, use_errno=True)
        for cap in (CAP_SYS_NICE, CAP_IPC_LOCK):
            if libc.prctl(PR_CAPBSET_DROP, cap, 0, 0, 0) != 0:
                raise OSError(ctypes.get_errno(), 'PR_CAPBSET_DROP')
    return drop, 'nobody' if as_nobody else 'capabilities'


# --- applying, in children --------------------------------------------------------------------

def test_apply_sets_fifo_on_every_thread_and_locks_memory(module_copy):
    if not fifo_allowed():
        pytest.skip('this process may not set SCHED_FIFO (the refused case covers it)')
    cpu = max(os.sched_getaffinity(0))
    out = run_child(module_copy, thread_priority=10, cpu_affinity=[cpu], lock_memory=True)
    assert out['raised'] is None
    assert out['warnings'] == []
    tids = {int(t) for t in out['threads']}
    assert {out['main_tid'], out['before_tid'], out['after_tid']} <= tids
    assert out['main'] == [out['fifo'], 10, [cpu]]
    for tid, sched in out['threads'].items():  # started before and after apply_realtime
        assert sched == [out['fifo'], 10, [cpu]], tid
    assert out['vmlck_kb'] > 0
    assert out['current']['policy'] == 'SCHED_FIFO' and out['current']['priority'] == 10
    assert out['current']['cpu_affinity'] == [cpu]
    assert out['current']['memory_locked'] and out['current']['memory_locked_kb'] > 0


def test_apply_current_thread_only(module_copy):
    if not fifo_allowed():
        pytest.skip('this process may not set SCHED_FIFO')
    out = run_child(module_copy, threads='current', thread_priority=10)
    assert out['warnings'] == []
    threads = {int(t): s for t, s in out['threads'].items()}
    assert threads[out['main_tid']][:2] == [out['fifo'], 10]
    assert threads[out['before_tid']][:2] == [out['other'], 0]
    assert threads[out['after_tid']][:2] == [out['fifo'], 10]  # inherited from its creator


def test_apply_refused_returns_warnings_and_does_not_raise(module_copy):
    preexec, how = unprivileged_preexec()
    out = run_child(module_copy, preexec_fn=preexec, thread_priority=10, lock_memory=True)
    if out['cap_eff'] >> CAP_SYS_NICE & 1 or out['cap_eff'] >> CAP_IPC_LOCK & 1:
        pytest.skip(f'the child kept CAP_SYS_NICE/CAP_IPC_LOCK ({how}): cannot be refused')
    if how == 'nobody':
        assert out['uid'] == NOBODY
    assert out['raised'] is None
    warnings = out['warnings']
    assert len(warnings) == 2, warnings
    lock, priority = warnings  # in the order applied: memory, then priority
    assert lock.startswith('lock_memory refused (')
    assert 'memlock' in lock and 'ulimit -l' in lock
    assert priority.startswith('thread_priority 10 refused (Operation not permitted')
    assert 'ulimit -r' in priority and 'limits.conf' in priority
    assert 'running at normal priority' in priority
    assert all('\n' not in w for w in warnings)
    for sched in [out['main'], *out['threads'].values()]:
        assert sched[:2] == [out['other'], 0]
    assert out['vmlck_kb'] == 0
    assert out['current']['policy'] == 'SCHED_OTHER' and not out['current']['memory_locked']


def test_settings_that_are_off_change_nothing():
    before = current_realtime()
    assert apply_realtime(RealtimeSettings()) == []
    after = current_realtime()
    assert (after['policy'], after['priority'], after['cpu_affinity']) == (
        before['policy'], before['priority'], before['cpu_affinity'])


def test_current_realtime_reads_this_thread():
    now = current_realtime(all_threads=True)
    if os.sched_getscheduler(0) == os.SCHED_OTHER:
        assert now['policy'] == 'SCHED_OTHER'
    assert now['priority'] == os.sched_getparam(0).sched_priority
    assert now['cpu_affinity'] == tuple(sorted(os.sched_getaffinity(0)))
    assert isinstance(now['memory_locked_kb'], int)
    assert now['threads'] and all(len(v) == 2 for v in now['threads'].values())


def test_apply_rejects_unknown_threads_mode():
    with pytest.raises(ValueError, match='threads'):
        apply_realtime(RealtimeSettings(), threads='main')


# --- settings ---------------------------------------------------------------------------------

def test_rt_defaults():
    assert RT_DEFAULTS == RealtimeSettings(thread_priority=40, cpu_affinity=(),
                                           lock_memory=True)
    assert RealtimeSettings() == RealtimeSettings(0, (), False)


@pytest.mark.parametrize('fields, match', [
    ({'thread_priority': 100}, 'thread_priority'),
    ({'thread_priority': -1}, 'thread_priority'),
    ({'thread_priority': 5.0}, 'thread_priority'),
    ({'thread_priority': True}, 'thread_priority'),
    ({'cpu_affinity': (-1,)}, 'non-negative'),
    ({'cpu_affinity': ('0',)}, 'non-negative'),
    ({'cpu_affinity': 3}, 'sequence'),
    ({'cpu_affinity': (10_000,)}, 'does not have'),
    ({'lock_memory': 'yes'}, 'lock_memory'),
])
def test_settings_validation(fields, match):
    with pytest.raises(ValueError, match=match) as e:
        RealtimeSettings(**fields)
    assert '\n' not in str(e.value)


def test_settings_normalise_cpus():
    cpu = min(os.sched_getaffinity(0))
    assert RealtimeSettings(cpu_affinity=[cpu, cpu]).cpu_affinity == (cpu,)


# --- garbage collector ------------------------------------------------------------------------

def test_gc_pauses_counts_a_forced_collection():
    with GcPauses() as pauses:
        gc.collect()
        stats = pauses.stats()
    assert stats['count'] >= 1
    assert stats['per_generation'][2]['count'] >= 1
    assert stats['max_ms'] >= stats['p50_ms'] >= 0
    assert stats['total_ms'] >= stats['max_ms']
    assert pauses._hook not in gc.callbacks
    gc.collect()
    assert pauses.stats()['count'] == stats['count']  # closed: counts no more


def test_gc_pauses_ring_keeps_exact_counts():
    pauses = GcPauses(capacity=2)
    try:
        for _ in range(5):
            gc.collect(0)
        stats = pauses.stats()
    finally:
        pauses.close()
    pauses.close()  # idempotent
    assert stats['count'] >= 5 and stats['per_generation'][0]['count'] >= 5
    assert stats['p99_ms'] is not None


def test_gc_pauses_empty_stats():
    pauses = GcPauses()
    pauses.close()
    stats = pauses.stats()
    assert stats['count'] == 0 and stats['p99_ms'] is None and stats['total_ms'] == 0


def test_settle_gc_freezes_the_heap():
    try:
        count = settle_gc()
        assert count == gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


# --- --rt with a harness pinned by hand ---------------------------------------------------------

@given(st.sets(st.integers(0, 63), min_size=1, max_size=8), st.integers(1, 64))
def test_rt_pinning_warning_names_a_single_cpu_of_several(cpus, total):
    """Warned exactly when the process may use one CPU of a machine that has more; the line
    names that CPU and the count."""
    from eha_ros.harness import rt_pinning_warning
    line = rt_pinning_warning(cpus, total)
    if len(cpus) == 1 and total >= 2:
        (cpu,) = cpus
        assert f'CPU {cpu} alone of {total}' in line and '\n' not in line
    else:
        assert line is None


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason='needs two CPUs to pin onto one')
def test_eha_graph_rt_pinned_to_one_cpu_warns_in_one_line(ros_env, tmp_path):
    """``taskset -c N eha-graph --rt``: the run goes on and says, in one line, that the whole
    graph shares CPU N (every node inherits the mask)."""
    cpu = min(os.sched_getaffinity(0))
    eha = os.path.join(os.path.dirname(sys.executable), 'eha-graph')
    r = subprocess.run(['taskset', '-c', str(cpu), eha, '--mode', 'realtime', '--rt',
                        '--duration', '0.2'], env=ros_env, cwd=tmp_path, text=True,
                       capture_output=True, timeout=180)
    lines = [x for x in r.stderr.splitlines() if f'pinned to CPU {cpu} alone' in x]
    assert len(lines) == 1 and 'warning' in lines[0], r.stderr
