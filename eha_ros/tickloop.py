"""The timing loop of a ticking node in a thread of its own, as ``ros2_control``'s controller
manager runs its update loop, and the timing trace that explains its late ticks.  Free of ROS.

:class:`TickLoop`
    A thread that wakes at absolute deadlines on ``CLOCK_MONOTONIC`` (``clock_nanosleep`` with
    ``TIMER_ABSTIME``: wake k falls due at the anchor plus k periods, so the schedule never
    drifts by the loop's own work) and calls the node's tick function.  The sleep runs in a
    numba ``nogil`` kernel that reads the clock as soon as the kernel wakes the thread, before
    the thread takes the GIL back: the trace tells the kernel's wake-up latency from the wait for
    the interpreter.  With a priority, the loop thread alone is ``SCHED_FIFO``: the executor
    that delivers the messages, and the middleware's threads, stay where the process put them.

:class:`TickTrace`
    Preallocated columns, one row per tick: when it fell due, when its thread woke, when it ran
    (the GIL taken), when its work ended and when its message was published; and per wake the
    evidence read after the wake's work (so it delays no message): the CPU, the loop thread's
    run-queue delay and context switches, the CPU time of the process's other threads, the
    garbage collector's pauses and the CPU's host steal.

:func:`late_episodes`
    The late ticks (one period or more after they fell due, as :class:`TickTiming` counts them)
    grouped in episodes of consecutive ticks, each with its evidence and its cause (see
    :data:`CAUSES`).

Precision: ``/proc/stat`` counts host steal in USER_HZ ticks (10 ms on this machine's kernel),
so steal is known per episode only to 10 ms; an episode is attributed to steal when the CPU's
steal counter advanced over the episode's window and no measured cause (our work, the GIL, the
collector, the run queue) explains its lateness.
"""

from __future__ import annotations

import ctypes
import functools
import os
import resource
import threading
import time

import numpy as np

__all__ = ['TickLoop', 'TickTrace', 'late_episodes', 'cause_shares', 'CAUSES', 'OWN_CAUSES',
           'sleep_until', 'TRACE_COLUMNS', 'describe_shares']

_CLOCK_MONOTONIC = 1
_TIMER_ABSTIME = 1
_EINTR = 4

#: The cause of a late episode, in the order of precedence when two measure the same:
#:
#: - ``overrun``: the loop's own previous work ended after this tick fell due (our tick took
#:   longer than its period: our process);
#: - ``gc``: a garbage collection ran over the episode (our process);
#: - ``gil``: the thread woke in time but waited for the GIL, which another thread of our
#:   process held (the executor, a callback: our process);
#: - ``run_queue``: the woken thread waited on the CPU's run queue (another thread of equal or
#:   higher priority had the CPU: without ``SCHED_FIFO`` any busy process, with it another FIFO
#:   thread or a kernel thread);
#: - ``steal``: none of the above, and the hypervisor took the CPU (``/proc/stat`` steal);
#: - ``kernel``: none of the above and no steal: the kernel woke the thread late (timer
#:   interrupts, a non-preemptible section).
CAUSES = ('overrun', 'gc', 'gil', 'run_queue', 'steal', 'kernel')
#: The causes that lie in our own process.
OWN_CAUSES = ('overrun', 'gc', 'gil')

# --- absolute-deadline sleep ------------------------------------------------------------------


@functools.cache
def _build_sleep():
    """The numba kernel (built at the first call): ``clock_nanosleep(CLOCK_MONOTONIC,
    TIMER_ABSTIME)`` until the deadline (resumed after a signal), then ``clock_gettime``;
    returns the wake time [ns].  ``nogil``: the GIL is released for the sleep and taken back
    only after the clock has been read."""
    import numba
    libc = ctypes.CDLL(None, use_errno=True)
    nanosleep = libc.clock_nanosleep
    nanosleep.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p]
    nanosleep.restype = ctypes.c_int
    gettime = libc.clock_gettime
    gettime.argtypes = [ctypes.c_int, ctypes.c_void_p]
    gettime.restype = ctypes.c_int

    @numba.njit(nogil=True)
    def kernel(deadline_ns, ts):
        gettime(_CLOCK_MONOTONIC, ts.ctypes.data)
        ts[2] = ts[0] * 1000000000 + ts[1]  # when the thread went to sleep
        ts[0] = deadline_ns // 1000000000
        ts[1] = deadline_ns % 1000000000
        while nanosleep(_CLOCK_MONOTONIC, _TIMER_ABSTIME, ts.ctypes.data, 0) == _EINTR:
            pass
        gettime(_CLOCK_MONOTONIC, ts.ctypes.data)
        return ts[0] * 1000000000 + ts[1]

    ts = np.zeros(3, np.int64)
    kernel(time.monotonic_ns(), ts)  # compile now, not in the first tick
    return kernel


def sleep_until(deadline_ns: int, _ts=np.zeros(3, np.int64)) -> int:
    """Sleep until ``deadline_ns`` on the monotonic clock (``time.monotonic_ns``), the GIL
    released; returns the time [ns] the kernel woke the thread (read before the GIL is taken
    back).  Not thread-safe with its default buffer: a :class:`TickLoop` has its own."""
    return int(_build_sleep()(int(deadline_ns), _ts))


# --- evidence readers -------------------------------------------------------------------------

def _open(path):
    try:
        return os.open(path, os.O_RDONLY)
    except OSError:
        return -1


TRACE_COLUMNS = {
    # per tick
    'tick': 'the tick (sample) index k: due at the anchor plus k periods',
    'due_ns': 'when the tick fell due [ns, monotonic clock]',
    'slept_ns': 'when the loop thread went to sleep for the wake that ran it [ns]',
    'woke_ns': 'when the kernel woke the loop thread for it [ns]',
    'ran_ns': 'when the thread ran Python again (the GIL taken) [ns]',
    'work_end_ns': 'when the tick\'s work (the step) ended [ns]',
    'published_ns': 'when its message was published [ns]',
    'wake': 'index of the wake the tick ran in (a late wake runs every tick due)',
    # per wake, read after its work: cumulative counters
    'cpu': 'the CPU the thread woke on',
    'run_delay_ns': 'the loop thread\'s run-queue wait so far [ns] (schedstat)',
    'thread_cpu_ns': 'the loop thread\'s CPU time so far [ns]',
    'other_threads_cpu_ns': 'CPU time of the process\'s other threads so far [ns]',
    'voluntary_switches': 'the loop thread\'s voluntary context switches so far',
    'involuntary_switches': 'the loop thread\'s involuntary context switches so far',
    'gc_pause_ns': 'total garbage-collection pause so far [ns]',
    'steal_jiffies': 'host steal of the CPU woken on so far [USER_HZ ticks]',
    'steal_all_jiffies': 'host steal of every CPU so far [USER_HZ ticks]',
}


class TickTrace:
    """Every tick of a loop (:data:`TRACE_COLUMNS`), in columns preallocated for ``capacity``
    ticks: recording allocates nothing.  Ticks beyond the capacity are counted in ``dropped``
    and flagged by :meth:`complete`, never silently left out.

    ``gc``: an object with ``total_ns()`` (:class:`eha_ros.realtime.GcPauses`), or None."""

    def __init__(self, capacity: int, period_ns: int, gc=None):
        if capacity < 1:
            raise ValueError(f'trace capacity must be at least one tick, got {capacity}')
        self.capacity = int(capacity)
        self.period_ns = int(period_ns)
        self.cols = {c: np.full(self.capacity, -1, np.int64) for c in TRACE_COLUMNS}
        self.n = 0
        self.dropped = 0
        self.wakes = 0
        self.gc = gc
        self._schedstat = _open('/proc/thread-self/schedstat')  # reopened by the loop thread
        self._stat = _open('/proc/stat')
        try:
            self._getcpu = ctypes.CDLL(None).sched_getcpu
            self._getcpu.restype = ctypes.c_int
        except (AttributeError, OSError):
            self._getcpu = lambda: -1
        self._wake_first = 0
        self._woke = self._ran = 0
        self._slept = -1
        self.clk_tck = os.sysconf('SC_CLK_TCK')

    def bind_thread(self) -> None:
        """Read the calling thread's schedstat (call from the loop thread)."""
        if self._schedstat >= 0:
            os.close(self._schedstat)
        self._schedstat = _open('/proc/thread-self/schedstat')

    def begin_wake(self, woke_ns: int, ran_ns: int, slept_ns: int = -1) -> None:
        self._woke, self._ran, self._slept = woke_ns, ran_ns, slept_ns
        self._wake_first = self.n

    def tick(self, k: int, due_ns: int, work_end_ns: int, published_ns: int) -> None:
        """One tick of the current wake."""
        i = self.n
        if i >= self.capacity:
            self.dropped += 1
            return
        c = self.cols
        c['tick'][i] = k
        c['due_ns'][i] = due_ns
        c['slept_ns'][i] = self._slept
        c['woke_ns'][i] = self._woke
        c['ran_ns'][i] = self._ran
        c['work_end_ns'][i] = work_end_ns
        c['published_ns'][i] = published_ns
        c['wake'][i] = self.wakes
        self.n = i + 1

    def end_wake(self) -> None:
        """The wake's work is done: read its evidence into its ticks."""
        first, last = self._wake_first, self.n
        self.wakes += 1
        if last <= first:
            return
        cpu = self._getcpu()
        run_delay = -1
        if self._schedstat >= 0:
            try:
                run_delay = int(os.pread(self._schedstat, 128, 0).split()[1])
            except (OSError, ValueError, IndexError):
                pass
        thread_cpu = time.thread_time_ns()
        other = time.process_time_ns() - thread_cpu
        ru = resource.getrusage(resource.RUSAGE_THREAD)
        gc_ns = self.gc.total_ns() if self.gc is not None else -1
        steal = steal_all = -1
        if self._stat >= 0:
            try:
                text = os.pread(self._stat, 16384, 0)
                steal_all = int(text[4:text.index(b'\n')].split()[7])  # 'cpu  user nice ...'
                key = b'\ncpu%d ' % cpu
                at = text.find(key) if cpu >= 0 else -1
                if at >= 0:
                    steal = int(text[at + len(key):text.index(b'\n', at + 1)].split()[7])
            except (OSError, ValueError, IndexError):
                pass
        c = self.cols
        for name, v in (('cpu', cpu), ('run_delay_ns', run_delay), ('thread_cpu_ns', thread_cpu),
                        ('other_threads_cpu_ns', other), ('voluntary_switches', ru.ru_nvcsw),
                        ('involuntary_switches', ru.ru_nivcsw), ('gc_pause_ns', gc_ns),
                        ('steal_jiffies', steal), ('steal_all_jiffies', steal_all)):
            c[name][first:last] = v

    def complete(self) -> bool:
        return self.dropped == 0

    def arrays(self) -> dict:
        """The recorded columns (views of the first ``n`` rows)."""
        return {c: v[:self.n] for c, v in self.cols.items()}

    def save(self, path: str, node: str = '') -> None:
        """Write the trace as ``.npz`` (with ``period_ns``, ``dropped``, ``clk_tck``, ``node``)."""
        tmp = f'{path}.part'
        with open(tmp, 'wb') as f:
            np.savez(f, period_ns=self.period_ns, dropped=self.dropped, clk_tck=self.clk_tck,
                     node=node, **self.arrays())
        os.replace(tmp, path)

    def close(self) -> None:
        for fd in (self._schedstat, self._stat):
            if fd >= 0:
                os.close(fd)
        self._schedstat = self._stat = -1


# --- the loop ---------------------------------------------------------------------------------

class TickLoop:
    """Call ``tick(due_ns, woke_ns, ran_ns)`` in a thread of its own at ``due_ns = anchor_ns +
    k * period_ns`` (``time.monotonic_ns``), k = 0, 1, ...; after a call the next deadline is the
    first one after the call's ``ran_ns`` (the node runs every tick due by then, by its own
    catch-up rules): a deadline that passed during the call's work wakes the loop at once, and
    only deadlines already passed when the call began are skipped.

    ``priority``: ``SCHED_FIFO`` priority of the loop thread only (0: the scheduling of the
    thread that starts it).  What the OS refuses is one warning line in :attr:`warnings`,
    never an error.  ``lock``: held during every call (the node's callbacks take it too).
    An exception in ``tick`` stops the loop; it is kept in :attr:`error`.
    """

    def __init__(self, name: str, period_ns: int, tick, *, priority: int = 0, lock=None):
        if isinstance(period_ns, bool) or not (isinstance(period_ns, int) and period_ns > 0):
            raise ValueError(f'period_ns must be a positive whole number, got {period_ns!r}')
        self.name = name
        self.period_ns = period_ns
        self.tick = tick
        self.priority = int(priority)
        self.lock = lock if lock is not None else threading.Lock()
        self.warnings: list[str] = []
        self.error: BaseException | None = None
        self.policy = None
        self._stop = threading.Event()
        self._thread = None
        self._ts = np.zeros(3, np.int64)
        self.slept_ns = -1  # when the thread went to sleep for the current wake
        self.on_thread_start = None
        self._kernel = _build_sleep()

    def start(self, anchor_ns: int) -> None:
        if self._thread is not None:
            raise RuntimeError(f'{self.name}: the loop has started already')
        self.anchor_ns = int(anchor_ns)
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def _set_priority(self) -> None:
        if not self.priority:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
        except OSError as e:
            from eha_ros.realtime import priority_refusal
            self.warnings.append(priority_refusal(
                self.priority, e, 'the tick loop thread running at normal priority'))

    def _run(self) -> None:
        self._set_priority()
        self.policy = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
        if self.on_thread_start is not None:
            self.on_thread_start()
        kernel, ts, period, anchor = self._kernel, self._ts, self.period_ns, self.anchor_ns
        k = 0
        now = time.monotonic_ns
        try:
            while not self._stop.is_set():
                woke = int(kernel(anchor + k * period, ts))
                ran = now()
                self.slept_ns = int(ts[2])
                if self._stop.is_set():
                    break
                with self.lock:
                    self.tick(anchor + k * period, woke, ran)
                # the next deadline: the first one after ``ran`` (the node ran every tick due
                # by then); one that fell due during this wake's work is in the past, so the
                # next wake comes at once instead of a period later
                k = max(k + 1, (ran - anchor) // period + 1)
        except BaseException as e:  # reported by the node, not lost in a thread
            self.error = e

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the loop and wait for its thread (idempotent)."""
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout_s)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()


# --- analysis ---------------------------------------------------------------------------------

def late_episodes(trace: dict, period_ns: int, clk_tck: int = 100) -> list[dict]:
    """The late ticks of ``trace`` (:meth:`TickTrace.arrays` or a saved ``.npz``) in episodes:
    maximal runs of consecutive ticks each run one period or more after it fell due.

    Each episode: ``first_tick``, ``ticks`` (late ticks), ``lateness_ms`` (of its first tick),
    the evidence over its window (from the end of the wake before it to the end of its last
    wake): ``overrun_ms`` (how long after the first tick fell due the
    thread went to sleep for it: the previous wake's work, its evidence, its GIL waits),
    ``gil_wait_ms`` (woken to running, summed over its wakes), ``gc_pause_ms``,
    ``run_queue_ms`` (the loop thread's run-queue wait), ``voluntary_switches``,
    ``involuntary_switches``, ``other_threads_cpu_ms`` (our other threads ran that long),
    ``steal_ms`` (the CPU's host steal, to 1/clk_tck s; None where unreadable), ``cpu``, and
    ``cause`` (:data:`CAUSES`): the measured cause with the largest share of the lateness;
    ``steal`` or ``kernel`` for what none explains."""
    n = len(trace['tick'])
    if n == 0:
        return []
    due = np.asarray(trace['due_ns'])
    ran = np.asarray(trace['ran_ns'])
    late = (ran - due) >= period_ns
    tick = np.asarray(trace['tick'])
    wake = np.asarray(trace['wake'])
    out = []
    idx = np.flatnonzero(late)
    used = np.zeros(n, bool)
    jiffy_ms = 1000.0 / clk_tck
    for i in idx:
        if used[i]:
            continue
        j = i
        while j + 1 < n and late[j + 1] and tick[j + 1] == tick[j] + 1:
            j += 1
        used[i:j + 1] = True
        # window: from the end of the previous wake to the end of the episode's last wake
        prev = i - 1
        while prev >= 0 and wake[prev] == wake[i]:
            prev -= 1
        wakes = np.unique(wake[i:j + 1])
        first_rows = [int(np.flatnonzero(wake == w)[0]) for w in wakes]

        def delta(col, scale=1.0):
            a = np.asarray(trace[col])
            end = a[j]
            start = a[prev] if prev >= 0 else a[i]
            return None if end < 0 or start < 0 else float(end - start) * scale

        # our own previous work: the thread went to sleep after this tick fell due (the last
        # wake's ticks, its evidence and any wait for the GIL before it slept)
        slept = int(trace['slept_ns'][i]) if 'slept_ns' in trace else -1
        prev_end = slept if slept >= 0 else (
            int(trace['published_ns'][prev]) if prev >= 0 else int(due[i]))
        overrun = max(0, prev_end - int(due[i])) * 1e-6
        gil = float(sum(int(ran[r]) - int(trace['woke_ns'][r]) for r in first_rows)) * 1e-6
        gc_ms = delta('gc_pause_ns', 1e-6)
        rq = delta('run_delay_ns', 1e-6)
        # the CPU's own steal where the window began and ended on it, else every CPU's
        cpus = np.asarray(trace['cpu'])
        same_cpu = prev < 0 or cpus[prev] == cpus[j]
        steal = delta('steal_jiffies' if same_cpu else 'steal_all_jiffies', jiffy_ms)
        lateness = (int(ran[i]) - int(due[i])) * 1e-6
        ep = {'first_tick': int(tick[i]), 'ticks': int(j - i + 1),
              'lateness_ms': round(lateness, 4), 'overrun_ms': round(overrun, 4),
              'gil_wait_ms': round(gil, 4),
              'gc_pause_ms': None if gc_ms is None else round(gc_ms, 4),
              'run_queue_ms': None if rq is None else round(rq, 4),
              'voluntary_switches': delta('voluntary_switches'),
              'involuntary_switches': delta('involuntary_switches'),
              'other_threads_cpu_ms': delta('other_threads_cpu_ns', 1e-6),
              'steal_ms': steal, 'cpu': int(trace['cpu'][i])}
        ep['cause'] = _cause(ep, lateness)
        out.append(ep)
    return out


def _cause(ep: dict, lateness_ms: float) -> str:
    measured = {'overrun': ep['overrun_ms'], 'gc': ep['gc_pause_ms'] or 0.0,
                'gil': ep['gil_wait_ms'], 'run_queue': ep['run_queue_ms'] or 0.0}
    best = max(CAUSES[:4], key=lambda c: (measured[c], -CAUSES.index(c)))
    unexplained = lateness_ms - sum(measured.values())
    if measured[best] > 0 and measured[best] >= unexplained:
        return best
    return 'steal' if (ep['steal_ms'] or 0) > 0 else 'kernel'


def cause_shares(episodes: list[dict], ticks: int) -> dict:
    """Late ticks by cause: ``{'ticks', 'late', 'late_pct', 'episodes', 'by_cause': {cause:
    {'late', 'share_pct', 'episodes'}}, 'own_process_late'}`` (shares of the late ticks)."""
    late = sum(e['ticks'] for e in episodes)
    by = {}
    for c in CAUSES:
        eps = [e for e in episodes if e['cause'] == c]
        n = sum(e['ticks'] for e in eps)
        by[c] = {'late': n, 'episodes': len(eps),
                 'share_pct': round(100.0 * n / late, 2) if late else 0.0}
    return {'ticks': int(ticks), 'late': late,
            'late_pct': round(100.0 * late / ticks, 4) if ticks else 0.0,
            'episodes': len(episodes), 'by_cause': by,
            'own_process_late': sum(by[c]['late'] for c in OWN_CAUSES)}


def describe_shares(shares: dict) -> str:
    """One line: late ticks and their causes."""
    parts = [f'{c} {v["late"]}' for c, v in shares['by_cause'].items() if v['late']]
    return (f'{shares["late"]} of {shares["ticks"]} ticks late ({shares["late_pct"]:g} %) in '
            f'{shares["episodes"]} episodes' + (': ' + ', '.join(parts) if parts else ''))
