"""The timing loop in a thread of its own (:mod:`eha_ros.tickloop`) and the timing trace that
explains late ticks: the loop's schedule, its thread's scheduling, the episodes and their
causes (property tests on drawn traces), the trace file, and ``--trace`` through the graph.
No test passes or fails on how late the machine is: they check the schedule's arithmetic,
the bookkeeping and what the trace holds."""

import json
import os
import subprocess
import sys
import threading
import time

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest

from eha_ros.tickloop import (CAUSES, OWN_CAUSES, TRACE_COLUMNS, TickLoop, TickTrace,
                              cause_shares, describe_shares, late_episodes, sleep_until)

MS = 1_000_000


def _run_loop(period_ns, n, work_ns=lambda k: 0, **kw):
    """Run a TickLoop for ``n`` wakes; returns [(due, woke, ran, returned)]."""
    calls, done = [], threading.Event()

    def tick(due, woke, ran):
        k = len(calls)
        end = time.monotonic_ns() + work_ns(k)
        while time.monotonic_ns() < end:
            pass
        calls.append((due, woke, ran, time.monotonic_ns()))
        if len(calls) >= n:
            done.set()

    loop = TickLoop('test tick', period_ns, tick, **kw)
    loop.start(time.monotonic_ns() + 5 * MS)
    assert done.wait(30), 'the loop did not run its wakes'
    loop.stop()
    assert not loop.running and loop.error is None
    return loop, calls


def test_sleep_until_never_wakes_before_its_deadline():
    """``clock_nanosleep`` with TIMER_ABSTIME: the wake time read before the GIL is taken back
    is never before the deadline, and a deadline in the past returns at once."""
    for _ in range(50):
        deadline = time.monotonic_ns() + 200_000
        assert sleep_until(deadline) >= deadline
    past = time.monotonic_ns() - 10 * MS
    assert sleep_until(past) >= past


def test_loop_wakes_on_an_absolute_grid_and_skips_what_a_slow_tick_overran():
    """Wake k falls due at the anchor plus k periods (no drift from the loop's own work); the
    next deadline is the first one after the wake began running, so one that passed during a
    slow wake's work wakes the loop at once (it is not skipped); the thread never runs a wake
    before its deadline."""
    period = 2 * MS
    slow = {10, 25}  # these wakes take 3.5 periods
    loop, calls = _run_loop(period, 40, work_ns=lambda k: 7 * MS if k in slow else 0)
    anchor = calls[0][0]
    for (due, woke, ran, returned), nxt in zip(calls, calls[1:] + [None]):
        assert (due - anchor) % period == 0
        assert woke >= due and ran >= woke and returned >= ran
        if nxt is not None:
            assert nxt[0] == max(due + period, anchor + ((ran - anchor) // period + 1) * period)
    for k in slow:  # the deadlines its work overran come at once, one by one
        assert calls[k + 1][0] < calls[k][3] and calls[k + 1][1] >= calls[k][3]


def test_fifo_priority_is_the_loop_threads_alone():
    """``priority`` makes the loop thread SCHED_FIFO and leaves the thread that started it as
    it was (the executor and the middleware stay at normal priority)."""
    before = os.sched_getscheduler(0)
    loop, _ = _run_loop(MS, 5, priority=7)
    if loop.warnings:  # refused by this machine: one line saying what to change
        assert len(loop.warnings) == 1 and 'thread_priority 7 refused' in loop.warnings[0]
        assert loop.policy[0] == before
    else:
        assert loop.policy == (os.SCHED_FIFO, 7)
    assert os.sched_getscheduler(0) == before


def test_refused_priority_is_one_warning_and_the_loop_runs(monkeypatch):
    """Where the OS refuses SCHED_FIFO the loop runs at normal priority with one warning that
    names the limit to change."""
    def refuse(*a):
        raise PermissionError(1, 'Operation not permitted')
    monkeypatch.setattr(os, 'sched_setscheduler', refuse)
    loop, calls = _run_loop(MS, 3, priority=40)
    assert len(calls) >= 3 and len(loop.warnings) == 1
    assert 'thread_priority 40 refused' in loop.warnings[0]
    assert 'normal priority' in loop.warnings[0]


def test_an_exception_in_a_tick_stops_the_loop_and_is_kept():
    def tick(due, woke, ran):
        raise RuntimeError('boom')
    loop = TickLoop('failing tick', MS, tick)
    loop.start(time.monotonic_ns())
    for _ in range(200):
        if not loop.running:
            break
        time.sleep(0.01)
    assert not loop.running and isinstance(loop.error, RuntimeError)


@pytest.mark.parametrize('period', [0, -1, 1.5, True])
def test_loop_refuses_a_period_that_is_not_a_positive_whole_number(period):
    with pytest.raises(ValueError, match='period_ns'):
        TickLoop('x', period, lambda *a: None)


# --- the trace ----------------------------------------------------------------------------------

def test_trace_records_every_tick_and_flags_what_had_no_room(tmp_path):
    """Every tick recorded with its wake's evidence; ticks beyond the capacity are counted,
    never silently left out; the saved file reads back whole."""
    from eha_ros.realtime import GcPauses
    from eha_ros.recording.trace import load_node_trace
    with GcPauses() as gc:
        tr = TickTrace(5, MS, gc=gc)
        tr.bind_thread()
        t = time.monotonic_ns()
        for w in range(4):  # wakes of 1, 2, 1, 3 ticks: 7 ticks, room for 5
            tr.begin_wake(t, t + 10)
            for _ in range((1, 2, 1, 3)[w]):
                tr.tick(tr.n + tr.dropped, t, t + 20, t + 30)
            tr.end_wake()
    assert tr.n == 5 and tr.dropped == 2 and not tr.complete()
    a = tr.arrays()
    assert list(a['wake']) == [0, 1, 1, 2, 3] and list(a['tick']) == list(range(5))
    for col in ('run_delay_ns', 'thread_cpu_ns', 'other_threads_cpu_ns', 'voluntary_switches',
                'gc_pause_ns', 'steal_all_jiffies', 'cpu'):
        assert (a[col] >= 0).all(), col  # read on this Linux machine
    assert np.all(np.diff(a['thread_cpu_ns']) >= 0)
    tr.save(str(tmp_path / 'p.npz'), 'servovalve_plant')
    back = load_node_trace(tmp_path / 'p.npz')
    assert back['dropped'] == 2 and back['node'] == 'servovalve_plant'
    assert all(np.array_equal(back['ticks'][c], a[c]) for c in TRACE_COLUMNS)
    with pytest.raises(ValueError, match='capacity'):
        TickTrace(0, MS)


def _trace(late_ms, period=MS, **evidence):
    """A one-tick-per-wake trace whose tick k runs ``late_ms[k]`` after it fell due; evidence
    columns (cumulative) from ``evidence`` (name -> per-tick increments), zero otherwise."""
    n = len(late_ms)
    due = np.arange(n, dtype=np.int64) * period
    ran = due + (np.asarray(late_ms) * 1e6).astype(np.int64)
    t = {c: np.zeros(n, np.int64) for c in TRACE_COLUMNS}
    t.update(tick=np.arange(n), due_ns=due, slept_ns=due - period // 2, woke_ns=ran.copy(),
             ran_ns=ran, work_end_ns=ran + 1000,
             published_ns=ran + 2000, wake=np.arange(n), cpu=np.zeros(n, np.int64))
    for name, inc in evidence.items():
        t[name] = np.cumsum(np.asarray(inc, np.int64))
    return t


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 6.0, allow_nan=False), min_size=1, max_size=120))
def test_episodes_partition_the_late_ticks(late_ms):
    """Every tick run one period or more after it fell due is in exactly one episode; an
    episode is a maximal run of consecutive late ticks; every one has a cause; the shares add
    up."""
    t = _trace(late_ms)
    late = (t['ran_ns'] - t['due_ns']) >= MS
    eps = late_episodes(t, MS)
    covered = np.zeros(len(late_ms), bool)
    for e in eps:
        span = slice(e['first_tick'], e['first_tick'] + e['ticks'])
        assert late[span].all() and not covered[span].any()
        covered[span] = True
        assert e['first_tick'] == 0 or not late[e['first_tick'] - 1]
        end = e['first_tick'] + e['ticks']
        assert end == len(late_ms) or not late[end]
        assert e['cause'] in CAUSES
    assert np.array_equal(covered, late)
    shares = cause_shares(eps, len(late_ms))
    assert shares['late'] == int(late.sum())
    assert sum(v['late'] for v in shares['by_cause'].values()) == shares['late']
    assert shares['own_process_late'] == sum(shares['by_cause'][c]['late'] for c in OWN_CAUSES)
    assert describe_shares(shares).startswith(f'{shares["late"]} of {len(late_ms)} ticks late')


def test_cause_is_the_measured_one_that_explains_the_lateness():
    """Closed cases: the GIL wait, our own previous work, the collector, the run queue, the
    CPU's steal counter; and 'kernel' where nothing inside the guest explains it."""
    base = [0.1, 0.1, 2.5, 0.1]
    # the thread woke on time and waited 2.4 ms for the GIL
    t = _trace(base)
    t['woke_ns'][2] = t['due_ns'][2] + 100_000
    assert [e['cause'] for e in late_episodes(t, MS)] == ['gil']
    # the thread went to sleep 2.4 ms after this tick fell due (its previous wake's work)
    t = _trace(base)
    t['slept_ns'][2] = t['due_ns'][2] + 2_400_000
    assert [e['cause'] for e in late_episodes(t, MS)] == ['overrun']
    # without the sleep time (-1), the previous wake's publication stands in for it
    t['slept_ns'][:] = -1
    t['published_ns'][1] = t['due_ns'][2] + 2_400_000
    assert [e['cause'] for e in late_episodes(t, MS)] == ['overrun']
    # a 2.3 ms collection over the episode
    t = _trace(base, gc_pause_ns=[0, 0, 2_300_000, 0])
    assert [e['cause'] for e in late_episodes(t, MS)] == ['gc']
    # 2.2 ms on the run queue
    t = _trace(base, run_delay_ns=[0, 0, 2_200_000, 0])
    assert [e['cause'] for e in late_episodes(t, MS)] == ['run_queue']
    # nothing measured, but the CPU's steal counter advanced
    t = _trace(base, steal_jiffies=[0, 0, 1, 0])
    ep, = late_episodes(t, MS, clk_tck=100)
    assert ep['cause'] == 'steal' and ep['steal_ms'] == 10.0
    # nothing at all
    assert [e['cause'] for e in late_episodes(_trace(base), MS)] == ['kernel']


def test_trace_file_round_trips_and_a_bad_file_is_refused(tmp_path):
    from eha_ros.recording.trace import read_trace, summarise, write_trace
    t = _trace([0.1, 1.5, 2.0, 0.1, 0.2])
    tr = summarise({'node': 'p', 'period_ns': MS, 'dropped': 0, 'clk_tck': 100, 'ticks': t})
    path = tmp_path / 'trace.mcap'
    write_trace(path, {'servovalve_plant': tr}, wall_offset_ns=10 ** 18)
    back = read_trace(path)['servovalve_plant']
    assert all(np.array_equal(back['ticks'][c], t[c]) for c in TRACE_COLUMNS)
    assert back['episodes'] == json.loads(json.dumps(tr['episodes']))
    assert back['shares'] == json.loads(json.dumps(tr['shares']))
    assert not (tmp_path / 'trace.mcap.part').exists()
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(b'not an mcap file')
    with pytest.raises(ValueError, match='bad.mcap'):
        read_trace(bad)


# --- through the graph ----------------------------------------------------------------------

@pytest.mark.parametrize('processes', [True, False])
def test_graph_trace_holds_every_tick_of_every_loop(eha_graph, tmp_path, processes):
    """A realtime run with ``trace``: the MCAP holds one record per tick of the plant (as many
    as states published) and of the command generator, on the loop's grid, with the late
    episodes and their causes; ``GraphResult.trace`` has the shares."""
    from eha_ros.recording.trace import read_trace
    path = tmp_path / 'trace.mcap'
    r = eha_graph(processes=processes, mode='realtime', scenario='step_0p1', duration_s=0.5,
                  trace=str(path))
    assert set(r.trace) == {'servovalve_plant', 'command_generator'}
    back = read_trace(path)
    plant = back['servovalve_plant']['ticks']
    assert len(plant['tick']) == r.state['tick'].size == r.trace['servovalve_plant']['ticks']
    assert list(plant['tick']) == list(range(len(plant['tick'])))
    for node, t in back.items():
        ticks = t['ticks']
        assert r.trace[node]['complete'] and r.trace[node]['dropped'] == 0
        d = np.diff(ticks['due_ns'])
        assert (d >= MS).all() and (d % MS == 0).all(), node  # one record per tick, on the grid
        assert (ticks['ran_ns'] >= ticks['due_ns']).all()     # no tick runs before it is due
        assert (ticks['published_ns'] >= ticks['work_end_ns']).all()
        late = int(((ticks['ran_ns'] - ticks['due_ns']) >= MS).sum())
        assert t['shares']['late'] == late == r.trace[node]['shares']['late']


def test_trace_refusals(ros_env, tmp_path):
    """A lockstep trace, an existing trace file, and a trace for a node without a tick loop
    are refused with one line, before anything runs."""
    from eha_ros.harness import GraphConfig, GraphConfigError, GraphError, run_graph
    with pytest.raises(GraphConfigError, match='lockstep'):
        run_graph(GraphConfig(mode='lockstep', trace=str(tmp_path / 't.mcap')), env=ros_env)
    existing = tmp_path / 'there.mcap'
    existing.write_bytes(b'keep me')
    with pytest.raises(GraphError, match='exists'):
        run_graph(GraphConfig(mode='realtime', trace=str(existing)), env=ros_env)
    assert existing.read_bytes() == b'keep me'
    bin_dir = os.path.dirname(sys.executable)
    for node, extra in (('servovalve_plant', ['-p', 'mode:=lockstep']),
                        ('controller', [])):  # a state-clocked controller has no loop
        out = subprocess.run([os.path.join(bin_dir, node), '--ros-args', '-p',
                              f'trace_file:={tmp_path / "x.npz"}'] + extra,
                             env=ros_env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 2, out.stderr
        assert 'trace_file needs a tick loop' in out.stderr.strip().splitlines()[-1]
    p = subprocess.run([os.path.join(bin_dir, 'eha-graph'), '--mode', 'lockstep', '--trace',
                        str(tmp_path / 'l.mcap')], env=ros_env, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and 'lockstep' in p.stderr


def test_realtime_plant_runs_fifo_on_its_tick_thread_alone(ros_env):
    """A realtime plant with ``thread_priority`` 10: mid-run, its process has one thread named
    ``eha_tick`` (its loop) at SCHED_FIFO 10 and every other thread (executor, middleware) at
    ``executor_priority``: normal scheduling by default, SCHED_FIFO 5 when set."""
    from eha_ros.harness import GraphConfig, run_graph
    from eha_ros.nodes.common import LOOP_THREAD_NAME
    for executor_priority in (0, 5):
        pids, seen = {}, {}

        def look():
            pid = pids.get('servovalve_plant')
            if pid is None:
                return False
            try:
                for tid in os.listdir(f'/proc/{pid}/task'):
                    with open(f'/proc/{pid}/task/{tid}/comm') as f:
                        name = f.read().strip()
                    seen[int(tid)] = (name, os.sched_getscheduler(int(tid)),
                                      os.sched_getparam(int(tid)).sched_priority)
            except (FileNotFoundError, ProcessLookupError):
                pass
            return False

        cfg = GraphConfig(mode='realtime', scenario='step_0p1', duration_s=1.0, node_params={
            'servovalve_plant': {'thread_priority': 10,
                                 'executor_priority': executor_priority}})
        run_graph(cfg, env=ros_env, on_start=pids.update, stop=look, timeout_s=120)
        loops = [v for v in seen.values() if v[0] == LOOP_THREAD_NAME]
        assert loops == [(LOOP_THREAD_NAME, os.SCHED_FIFO, 10)]
        others = {v[1:] for v in seen.values() if v[0] != LOOP_THREAD_NAME}
        assert others == ({(os.SCHED_OTHER, 0)} if executor_priority == 0
                          else {(os.SCHED_FIFO, 5)}), others
