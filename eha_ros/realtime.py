"""Real-time settings for a 1 kHz node process, as ``ros2_control_node`` has them, plus the
Python-specific jitter source: the cyclic garbage collector.

Stdlib only (no rclpy import), so it can be used and tested without ROS.

Settings (:class:`RealtimeSettings`, applied by :func:`apply_realtime`)
----------------------------------------------------------------------
``thread_priority``
    ``SCHED_FIFO`` priority 1-99 (0: leave the normal ``SCHED_OTHER`` scheduling).  A FIFO
    thread runs until it blocks or a higher-priority FIFO thread wakes; it preempts every normal
    thread at once instead of waiting for its CFS/EEVDF slice.
``cpu_affinity``
    CPUs the threads may run on (empty: no pinning, the kernel's choice).
``lock_memory``
    ``mlockall(MCL_CURRENT | MCL_FUTURE)``: every page mapped now is faulted in and locked, and
    every later mapping is populated when it is made, so the tick never waits for a page fault
    (nor for swap).  The price: resident memory grows to the mapped size (thread stacks are
    faulted in whole): a process that has imported rclpy, numba and numpy and compiled the
    plant goes from about 210 MB resident to 535 MB (700 MB locked, ``VmLck``).  With a
    finite ``RLIMIT_MEMLOCK`` and no ``CAP_IPC_LOCK`` an allocation that would exceed the limit
    fails.

:func:`apply_realtime` sets every thread of the process (``/proc/self/task``): in lockstep a
tick waits for messages that the middleware's receive threads deliver, so it is only as timely
as the slowest link of that chain.  In realtime the ticking nodes run their tick in a thread
of their own (:mod:`eha_ros.tickloop`), as ``ros2_control_node`` runs its control loop, and
only that thread gets ``thread_priority`` and ``cpu_affinity``; the process's other threads
get ``executor_priority`` (``--rt``: the listeners' 30, because a normal-priority thread that
holds the GIL can be preempted by any busy process while the loop waits for it).  Threads
started later inherit the scheduling, affinity and (process-wide) memory lock of the thread
that creates them.

What the OS may refuse, and what to change (each refusal is one warning line, never an error):

- ``SCHED_FIFO`` needs ``RLIMIT_RTPRIO`` >= the priority (``ulimit -r``; ``rtprio`` in
  ``/etc/security/limits.conf``) or ``CAP_SYS_NICE`` (in docker: ``--cap-add=sys_nice
  --ulimit rtprio=99``).  With RT group scheduling (cgroup v1 ``cpu.rt_runtime_us``) the
  cgroup must also have RT time (docker ``--cpu-rt-runtime``).
- ``mlockall`` needs ``RLIMIT_MEMLOCK`` above the process size (``ulimit -l unlimited``;
  ``memlock`` in ``limits.conf``) or ``CAP_IPC_LOCK`` (docker ``--ulimit memlock=-1`` or
  ``--cap-add=ipc_lock``).
- CPUs outside the cgroup's cpuset are dropped by the kernel (docker ``--cpuset-cpus``;
  ``taskset``).

RT throttling: ``kernel.sched_rt_runtime_us`` (default 950000 of ``sched_rt_period_us``
1000000) caps all RT threads of a CPU at 95 % of each second, so a runaway FIFO thread still
leaves 50 ms/s to normal tasks (a shell, ``kill``) instead of hanging the machine; with -1 there
is no such cap.  A 1 kHz tick that only needs part of each millisecond never meets the cap.

Garbage collector
-----------------
CPython frees most objects by reference counting; the cyclic collector runs when allocations
minus deallocations of container objects pass the gen-0 threshold (700), so a tick that frees
what it allocates never triggers it (``bench/gc_pauses.py``: no collection at all in 10 s of
1 kHz plant ticks, nor in an rclpy executor publishing at 1 kHz).  Collections come with net
growth (objects kept: histories, in-memory recording; reference cycles), and a full (gen-2)
one, due once the survivors pass a quarter of the long-lived heap, traverses every tracked
object alive: after importing rclpy, numba and numpy and compiling the plant some 190 000,
127-143 ms per full collection on this project's 2-CPU machine, i.e. over a hundred missed
1 kHz ticks.  :func:`settle_gc` collects once and then freezes what is alive (``gc.freeze``:
moved to a permanent generation that collections skip), so later collections only traverse
what the process allocated since (the same bench, every message kept: 29 ms after 60 s instead
of 127 and 143 ms).  :class:`GcPauses` times every collection through ``gc.callbacks``.
"""

from __future__ import annotations

from contextlib import suppress
import ctypes
import errno
import gc
import itertools
import math
import os
import resource
import time
from dataclasses import dataclass

__all__ = ['RealtimeSettings', 'RT_DEFAULTS', 'RT_LISTENER_DEFAULTS', 'apply_realtime',
           'current_realtime', 'normal_scheduling', 'settle_gc', 'GcPauses']

_MAX_FIFO_PRIORITY = 99
_CAP_IPC_LOCK = 14


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclass(frozen=True)
class RealtimeSettings:
    """Real-time settings of a node process (see the module docstring).

    ``thread_priority``: ``SCHED_FIFO`` priority 1-99, 0 for normal scheduling.
    ``cpu_affinity``: CPUs to pin every thread to, empty for no pinning (normalised to a sorted
    tuple without duplicates).  ``lock_memory``: ``mlockall(MCL_CURRENT | MCL_FUTURE)``.
    """

    thread_priority: int = 0
    cpu_affinity: tuple[int, ...] = ()
    lock_memory: bool = False

    def __post_init__(self):
        p = self.thread_priority
        if not _is_int(p) or not 0 <= p <= _MAX_FIFO_PRIORITY:
            raise ValueError(f'thread_priority must be an integer in 0..{_MAX_FIFO_PRIORITY} '
                             f'(0: normal scheduling), got {p!r}')
        try:
            cpus = tuple(self.cpu_affinity)
        except TypeError:
            raise ValueError(f'cpu_affinity must be a sequence of CPU numbers, got '
                             f'{self.cpu_affinity!r}') from None
        bad = [c for c in cpus if not _is_int(c) or c < 0]
        if bad:
            raise ValueError(f'cpu_affinity must hold non-negative integers, got {bad[0]!r}')
        machine = set(range(os.cpu_count() or 1))
        with suppress(AttributeError, OSError):
            machine |= os.sched_getaffinity(0)
        missing = sorted(set(cpus) - machine)
        if missing:
            raise ValueError(f'cpu_affinity names CPUs {missing} that this machine does not '
                             f'have (it has {_ranges(machine)})')
        object.__setattr__(self, 'cpu_affinity', tuple(sorted(set(cpus))))
        if not isinstance(self.lock_memory, bool):
            raise ValueError(f'lock_memory must be True or False, got {self.lock_memory!r}')


#: What a rig's ``--rt`` flag sets.
#:
#: - ``thread_priority=40``: ``ros2_control_node`` runs its control thread at ``SCHED_FIFO`` 50,
#:   which is also where a PREEMPT_RT kernel puts its threaded interrupt handlers (network
#:   card, timers of other devices).  A simulation node at 40 stays below them, so the
#:   interrupts that deliver the DDS packets a lockstep tick waits for are served first, and
#:   below a real ``ros2_control_node`` sharing the machine; it is still above every normal
#:   process (compilers, browsers, the recorder's disk writes).
#: - ``cpu_affinity=()``: no pinning.  The default rig has two CPUs and several node processes
#:   whose threads all get FIFO 40; pinned to one CPU, a node's DDS receive thread and its tick
#:   thread, at equal FIFO priority, could not preempt each other; pinning needs a per-machine
#:   plan (an isolated CPU per node) that a default cannot make.
#: - ``lock_memory=True``: as ``ros2_control_node``'s default: no page fault (first touch of a
#:   new heap page, a code page evicted under memory pressure) inside a tick.  It costs about
#:   320 MB more resident memory per node process that imports numba (see above).
RT_DEFAULTS = RealtimeSettings(thread_priority=40, cpu_affinity=(), lock_memory=True)

#: What ``--rt`` gives the graph's listeners (the harness's collector, the recorder, the health
#: monitor): SCHED_FIFO below the ticking nodes, so the loop always preempts them, but above
#: every normal process, so other work on the machine cannot starve them into losing messages
#: (a listener's history holds one second at 1 kHz).
RT_LISTENER_DEFAULTS = RealtimeSettings(thread_priority=30, cpu_affinity=(), lock_memory=True)


def normal_scheduling(cpus=None) -> None:
    """Every thread of the process back to normal scheduling (``SCHED_OTHER``) on ``cpus``
    (default: left as they are), memory unlocked: undoes :func:`apply_realtime` where the
    process outlives its real-time part."""
    for tid in _thread_ids():
        with suppress(OSError):
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            if cpus:
                os.sched_setaffinity(tid, cpus)
    _libc().munlockall()


# --- applying ---------------------------------------------------------------------------------

def _libc():
    return ctypes.CDLL(None, use_errno=True)


def _ranges(cpus) -> str:
    """``{0, 1, 2, 5}`` -> ``'0-2,5'``."""
    out = []
    for _, run in itertools.groupby(enumerate(sorted(cpus)), lambda ic: ic[1] - ic[0]):
        run = [c for _, c in run]
        out.append(f'{run[0]}-{run[-1]}' if len(run) > 1 else str(run[0]))
    return ','.join(out)


def _status_field(name: str) -> str | None:
    with suppress(OSError), open('/proc/self/status') as f:
        for line in f:
            if line.startswith(name + ':'):
                return line.split(':', 1)[1].strip()
    return None


def _limit_text(limit: int, unit: int = 1, suffix: str = '') -> str:
    return 'unlimited' if limit == resource.RLIM_INFINITY else f'{limit // unit}{suffix}'


def _thread_ids() -> list[int]:
    try:
        return sorted(int(t) for t in os.listdir('/proc/self/task'))
    except OSError:  # no procfs: the calling thread only
        return [0]


def _own_tid() -> int:
    try:
        return int(os.readlink('/proc/thread-self').rsplit('/', 1)[1])
    except (OSError, ValueError, IndexError):
        return 0


def _for_threads(fn, threads: str) -> tuple[int, int, OSError | None]:
    """Call ``fn(tid)`` for the calling thread and then (``threads='all'``) every thread of the
    process, again for threads that appeared meanwhile.  Returns (applied, refused, first
    refusal); threads that exited meanwhile are skipped."""
    ok = refused = 0
    first = None
    done = set()
    pending = [0]
    for _ in range(5):
        for tid in pending:
            try:
                fn(tid)
                ok += 1
            except ProcessLookupError:  # the thread exited
                pass
            except OSError as e:
                refused += 1
                first = first or e
            done.add(tid)
        done.add(_own_tid())
        if threads != 'all':
            break
        pending = [t for t in _thread_ids() if t not in done]
        if not pending:
            break
    return ok, refused, first


def _reason(e: OSError) -> str:
    return e.strerror or os.strerror(e.errno or 0)


def _lock_memory() -> str | None:
    # MCL_CURRENT, MCL_FUTURE of this architecture
    other = os.uname().machine.startswith(('ppc', 'powerpc', 'sparc', 'alpha'))
    current, future = (0x2000, 0x4000) if other else (1, 2)
    libc = _libc()
    soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    if libc.mlockall(current | future) == 0:
        eff = _status_field('CapEff')  # the effective capabilities
        if soft != resource.RLIM_INFINITY and not (eff and int(eff, 16) >> _CAP_IPC_LOCK & 1):
            return (f'lock_memory applied, but RLIMIT_MEMLOCK is {_limit_text(soft, 1024)} KiB '
                    f'and new memory is locked as it is mapped: an allocation beyond that '
                    f'fails; set `ulimit -l unlimited` or a `memlock unlimited` line in '
                    f'/etc/security/limits.conf, or in docker --ulimit memlock=-1')
        return None
    err = ctypes.get_errno()
    libc.munlockall()  # a partial lock (ENOMEM while faulting in) is undone
    size = _status_field('VmSize') or '?'
    return (f'lock_memory refused ({os.strerror(err)}; RLIMIT_MEMLOCK '
            f'{_limit_text(soft, 1024, " KiB")}, process size {size}): allow it with '
            f'`ulimit -l unlimited` or a `memlock unlimited` line in /etc/security/limits.conf, '
            f'or in docker --ulimit memlock=-1 or --cap-add=ipc_lock; running with memory '
            f'unlocked')


def _set_affinity(cpus: tuple[int, ...], threads: str) -> str | None:
    # numba sizes its thread pool by the CPUs the process may use, read again at every
    # compilation when NUMBA_NUM_THREADS is unset: pinning (or unpinning) after its pool has
    # started would make a later compilation fail ("Cannot set NUMBA_NUM_THREADS to a different
    # value once the threads have been launched").  Keep the count it has now.
    os.environ.setdefault('NUMBA_NUM_THREADS', str(len(os.sched_getaffinity(0))))
    ok, refused, e = _for_threads(lambda tid: os.sched_setaffinity(tid, cpus), threads)
    want = ','.join(map(str, cpus))
    if e is not None:
        where = 'left as it was' if not ok else f'set on {ok} of {ok + refused} threads'
        if e.errno == errno.EINVAL:
            return (f'cpu_affinity {want} refused ({_reason(e)}): none of these CPUs is in '
                    f'this process\'s cpuset; pick CPUs of the cpuset or give them to it '
                    f'(docker --cpuset-cpus, systemd AllowedCPUs=, taskset -c); {where}')
        return (f'cpu_affinity {want} refused ({_reason(e)}): run as a user allowed to change '
                f'affinity (CAP_SYS_NICE for other users\' threads) or start the process with '
                f'`taskset -c {want}`; {where}')
    got = os.sched_getaffinity(0)
    if got != set(cpus):
        return (f'cpu_affinity {want} applied as {_ranges(got)}: CPUs '
                f'{_ranges(set(cpus) - got)} are outside this process\'s cpuset; give them to it '
                f'(docker --cpuset-cpus, systemd AllowedCPUs=) or pick CPUs of the cpuset')
    return None


def priority_refusal(priority: int, e: OSError, where: str) -> str:
    """One warning line: ``SCHED_FIFO`` ``priority`` refused with ``e``, what to change, and
    ``where`` (what runs at normal priority instead)."""
    soft = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
    if e.errno == errno.EPERM and (soft == resource.RLIM_INFINITY or soft >= priority):
        # The limit allows it: RT group scheduling without RT time for this cgroup.
        return (f'thread_priority {priority} refused ({_reason(e)}) although RLIMIT_RTPRIO is '
                f'{_limit_text(soft)}: the cgroup has no real-time time (RT group scheduling); '
                f'give it some (cpu.rt_runtime_us, docker --cpu-rt-runtime=950000); {where}')
    return (f'thread_priority {priority} refused ({_reason(e)}; RLIMIT_RTPRIO '
            f'{_limit_text(soft)}): allow SCHED_FIFO with `ulimit -r 99` or an `rtprio 99` line '
            f'in /etc/security/limits.conf, or in docker --cap-add=sys_nice --ulimit rtprio=99; '
            f'{where}')


def _set_priority(priority: int, threads: str) -> str | None:
    param = os.sched_param(priority)
    ok, refused, e = _for_threads(
        lambda tid: os.sched_setscheduler(tid, os.SCHED_FIFO, param), threads)
    if e is None:
        return None
    where = 'running at normal priority' if not ok else \
        f'set on {ok} of {ok + refused} threads, the others at normal priority'
    return priority_refusal(priority, e, where)


def apply_realtime(settings: RealtimeSettings, threads: str = 'all') -> list[str]:
    """Apply ``settings`` to the process: memory lock, then CPU affinity, then ``SCHED_FIFO``
    priority (last, so the thread does the slow parts at normal priority).

    ``threads='all'``: affinity and priority for every thread of the process (the calling one
    first), so middleware threads started before get them too; ``'current'``: the calling
    thread only.  Threads created afterwards inherit from their creator.  Settings that are off
    (priority 0, no CPUs, no lock) are left as they are.

    Never raises for what the OS refuses: returns one warning line per refused setting (what,
    the OS error, what to change), ``[]`` when everything was applied.
    """
    if threads not in ('all', 'current'):
        raise ValueError(f"threads must be 'all' or 'current', got {threads!r}")
    warnings = [settings.lock_memory and _lock_memory(),
                settings.cpu_affinity and _set_affinity(settings.cpu_affinity, threads),
                settings.thread_priority and _set_priority(settings.thread_priority, threads)]
    return [w for w in warnings if w]


_POLICIES = {getattr(os, n): n for n in ('SCHED_OTHER', 'SCHED_FIFO', 'SCHED_RR', 'SCHED_BATCH',
                                         'SCHED_IDLE', 'SCHED_DEADLINE') if hasattr(os, n)}


def _policy_name(policy: int) -> str:
    return _POLICIES.get(policy & 0xff, str(policy))  # without SCHED_RESET_ON_FORK


def current_realtime(all_threads: bool = False) -> dict:
    """What is in effect: ``policy`` (name) and ``priority`` of the calling thread, its
    ``cpu_affinity`` (sorted tuple), ``memory_locked_kb`` (``VmLck``) and ``memory_locked``,
    ``rt_runtime_us`` (``kernel.sched_rt_runtime_us``, None if unreadable); with
    ``all_threads``, ``threads``: ``{tid: (policy, priority)}`` for every thread."""
    locked = _status_field('VmLck')
    locked_kb = int(locked.split()[0]) if locked else 0
    try:
        with open('/proc/sys/kernel/sched_rt_runtime_us') as f:
            rt_runtime = int(f.read())
    except (OSError, ValueError):
        rt_runtime = None
    out = {'policy': _policy_name(os.sched_getscheduler(0)),
           'priority': os.sched_getparam(0).sched_priority,
           'cpu_affinity': tuple(sorted(os.sched_getaffinity(0))),
           'memory_locked_kb': locked_kb, 'memory_locked': locked_kb > 0,
           'rt_runtime_us': rt_runtime}
    if all_threads:
        threads = {}
        for tid in _thread_ids():
            with suppress(ProcessLookupError):  # the thread exited
                threads[tid] = (_policy_name(os.sched_getscheduler(tid)),
                                os.sched_getparam(tid).sched_priority)
        out['threads'] = threads
    return out


# --- garbage collector ------------------------------------------------------------------------

def settle_gc() -> int:
    """Collect, then freeze everything alive (``gc.freeze``): call once after start-up (imports,
    JIT compilation, node construction), before the loop.  Later collections skip the frozen
    objects, so a full collection costs what the loop allocated, not the whole heap.  Frozen
    objects are never collected: a cycle among them that becomes garbage later stays
    allocated (fine for start-up state that lives as long as the process).  Returns
    ``gc.get_freeze_count()``."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def _nearest_rank(sorted_values, q: float):
    """The ``q``-quantile (0..1) of sorted values, nearest-rank; None when empty."""
    if not sorted_values:
        return None
    k = max(0, min(len(sorted_values) - 1, math.ceil(q * len(sorted_values)) - 1))
    return sorted_values[k]


class GcPauses:
    """Times every garbage collection while installed (from construction to :meth:`close`;
    also a context manager).

    The ``gc.callbacks`` hook stores the pause in a preallocated ring of the last ``capacity``
    pauses (for the percentiles) and updates per-generation count, total and maximum (exact
    over all pauses); it allocates nothing but the int it stores.  :meth:`stats` sorts the
    ring (4096 entries by default: well under a millisecond).
    """

    def __init__(self, capacity: int = 4096):
        if capacity < 1:
            raise ValueError(f'capacity must be positive, got {capacity}')
        self.capacity = int(capacity)
        self._ring = [0] * self.capacity
        self._n = 0
        self._t0 = 0
        self._count = [0, 0, 0]
        self._total_ns = [0, 0, 0]
        self._max_ns = [0, 0, 0]
        self._collected = 0
        self._hook = self._callback
        gc.callbacks.append(self._hook)

    def _callback(self, phase, info, _now=time.perf_counter_ns):
        if phase == 'start':
            self._t0 = _now()
            return
        d = _now() - self._t0
        g = info['generation']
        self._ring[self._n % self.capacity] = d
        self._n += 1
        self._count[g] += 1
        self._total_ns[g] += d
        if d > self._max_ns[g]:
            self._max_ns[g] = d
        self._collected += info['collected']

    def total_ns(self) -> int:
        """Every pause so far, summed [ns]."""
        return sum(self._total_ns)

    def close(self) -> None:
        """Remove the hook (idempotent)."""
        with suppress(ValueError):
            gc.callbacks.remove(self._hook)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def stats(self) -> dict:
        """``count``, ``total_ms``, ``max_ms``, ``p50_ms`` and ``p99_ms`` (over the last
        ``capacity`` pauses; None before any), ``collected`` (objects freed) and
        ``per_generation``: ``{0: {'count', 'total_ms', 'max_ms'}, 1: ..., 2: ...}``."""
        kept = sorted(self._ring[:min(self._n, self.capacity)])

        def ms(ns):
            return None if ns is None else ns / 1e6

        return {'count': self._n, 'total_ms': ms(sum(self._total_ns)),
                'max_ms': ms(max(self._max_ns)), 'p50_ms': ms(_nearest_rank(kept, 0.50)),
                'p99_ms': ms(_nearest_rank(kept, 0.99)), 'collected': self._collected,
                'per_generation': {g: {'count': self._count[g],
                                       'total_ms': ms(self._total_ns[g]),
                                       'max_ms': ms(self._max_ns[g])} for g in range(3)}}
