"""A ticking node's timing report on ``/diagnostics`` (:class:`TickTiming`) and its start at
the graph's start (:func:`begin_timing`)."""

from __future__ import annotations

from contextlib import nullcontext
import time

import numpy as np
from rclpy.node import Node

from eha_ros.graph import RUN_ENDED, TIMING_SUFFIX, TOPIC_DIAGNOSTICS

from .common import advertise, publish_status

__all__ = ['TickTiming', 'begin_timing', 'JITTER_BIN_NS', 'JITTER_BINS']

#: Period jitter since startup is kept as a histogram of this bin width (ns) and count (the
#: last bin holds everything beyond), so a long run costs no memory.
JITTER_BIN_NS = 10_000
JITTER_BINS = 2000


class TickTiming:
    """A node's own timing, published as a ``DiagnosticStatus`` ``'<node>: timing'`` on
    ``/diagnostics`` once per ``window_s`` of wall time, like diagnostic_updater's
    ``FrequencyStatus`` (same keys for the rate) with what a 1 kHz loop also needs, and a last
    time when the node's run ends (:meth:`publish_final`, ``Run ended``).

    The node calls :meth:`tick` for every tick it runs (with the tick's lateness where it has
    a wall-clock schedule), :meth:`slip` for ticks it dropped, and :meth:`busy` with the
    duration of each callback. Values (window: since the last report; since startup):

    * ``Events in window``, ``Events since startup``, ``Duration of window (s)``,
      ``Actual frequency (Hz)``, ``Target frequency (Hz)``, ``Minimum/Maximum acceptable
      frequency (Hz)``: as ``FrequencyStatus`` (tolerance 10 %);
    * ``Period jitter p99 (ms)``, ``Period jitter max (ms)``: time between consecutive ticks
      minus the period, absolute, in the window;
    * ``Late ticks since startup`` (a tick run one period or more after it fell due),
      ``Slipped ticks since startup`` (never run: the schedule skipped them), ``On time since
      startup (%)`` (on-time ticks over run + slipped ticks);
    * ``Overruns since startup``: callbacks that took longer than one period;
    * ``Busy (core)``: the node's callback time per wall second in the window (its share of a
      core, also when several nodes share one process); ``Process CPU (core)``: the whole
      process's CPU time per wall second.

    "Since startup" counts from the graph's synchronised start (:meth:`start`, the end of the
    start-up handshake), not from the node's creation; ``JIT warm-up (s)`` and ``Discovery
    (s)`` report the time before it. In lockstep there is no wall-clock schedule: the
    realtime keys (jitter, late, slipped, on time) are left out and ``Simulated s per wall s``
    and ``Resent ticks since startup`` (the plant) are reported instead. With a garbage
    collector monitor (``gc``, :class:`eha_ros.realtime.GcPauses`): ``GC collections since
    startup`` and ``GC pause max (ms)``.

    Level (realtime): ERROR when no tick in the window, WARN when the rate is outside the
    tolerance or a tick slipped or ran late in the window, else OK. In lockstep the plant sets
    the pace and there is no wall-clock target: OK, with the rate reported.
    """

    def __init__(self, node: Node, rate_hz: float, realtime: bool, *, window_s: float = 1.0,
                 tolerance: float = 0.1):
        from diagnostic_msgs.msg import DiagnosticArray

        self.node = node
        self.name = node.get_name() + TIMING_SUFFIX
        self.target_hz = float(rate_hz)
        self.period_ns = round(1e9 / rate_hz)
        self.realtime = realtime
        self.tolerance = tolerance
        self.window_s = window_s
        self._reset(None, time.monotonic_ns())  # own schedule until start (see on_schedule)
        self.gc = None
        self.pub = advertise(node, DiagnosticArray, TOPIC_DIAGNOSTICS)
        self.timer = None
        self.lock = None  # a tick loop's lock (NodeLoop), taken to read and restart the window

    def _reset(self, due_ns: int | None, start_ns: int, startup: dict | None = None) -> None:
        """Every count zero, the run and its window from ``start_ns``, the next tick due at
        ``due_ns``."""
        self.ticks = self.late = self.slipped = self.overruns = self.resent = 0
        self._w_ticks = self._w_late = self._w_slipped = self._w_busy_ns = 0
        self._intervals = []
        self._jitter_hist = np.zeros(JITTER_BINS, np.int64)
        self._last_ns = None
        self._due_ns = due_ns
        self._w_start = self._start_ns = start_ns
        self._cpu0 = time.process_time_ns()
        self.startup = dict(startup or {})
        self.ended = False  # the final report went out (publish_final)

    def start(self, start_ns: int, startup: dict | None = None) -> None:
        """Begin at the graph's start ``start_ns`` (``time.monotonic_ns``): statistics and
        reports cover the run from there; ``startup`` (e.g. ``{'JIT warm-up (s)': ..,
        'Discovery (s)': ..}``) is reported beside them. Ticks fall due on a grid anchored at
        ``start_ns`` (:meth:`on_schedule`)."""
        from rclpy.clock import Clock as RosClock, ClockType
        self._reset(start_ns, max(start_ns, time.monotonic_ns()), startup)
        if self.timer is None:
            self.timer = self.node.create_timer(self.window_s, self.publish,
                                                clock=RosClock(clock_type=ClockType.STEADY_TIME))

    def tick(self, now_ns: int | None = None, late_ns: int | None = None) -> None:
        """One tick run at ``now_ns`` (``time.monotonic_ns``), ``late_ns`` after it fell due
        (None: no wall-clock schedule)."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        self.ticks += 1
        self._w_ticks += 1
        if self._last_ns is not None:
            self._intervals.append(now_ns - self._last_ns)
        self._last_ns = now_ns
        if late_ns is not None and late_ns >= self.period_ns:
            self.late += 1
            self._w_late += 1

    def on_schedule(self, now_ns: int | None = None) -> None:
        """:meth:`tick` for a node ticking on a timer of period ``1/rate_hz``: its ticks fall due
        on a grid anchored at the first; a call one period or more after its tick fell due
        means the timer skipped the calls in between (rcl runs a late timer once): those ticks
        slipped, and the call is the tick due last."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        if self._due_ns is None:
            self._due_ns = now_ns
        late = now_ns - self._due_ns
        if late >= self.period_ns:
            skipped = late // self.period_ns
            self.slip(skipped)
            self._due_ns += skipped * self.period_ns
            late -= skipped * self.period_ns
        self.tick(now_ns, max(0, late))
        self._due_ns += self.period_ns

    def slip(self, n: int) -> None:
        """``n`` ticks dropped (never run)."""
        self.slipped += int(n)
        self._w_slipped += int(n)

    def busy(self, start_ns: int, end_ns: int | None = None) -> None:
        """A callback ran from ``start_ns`` to ``end_ns`` (``time.monotonic_ns``)."""
        d = (time.monotonic_ns() if end_ns is None else end_ns) - start_ns
        self._w_busy_ns += d
        if d > self.period_ns:
            self.overruns += 1

    def values(self, now_ns: int | None = None) -> dict:
        """The report's values (see the class docstring), and restart the window."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        cpu = time.process_time_ns()
        window_s = max(1e-9, (now_ns - self._w_start) * 1e-9)
        run_s = max(1e-9, (now_ns - self._start_ns) * 1e-9)
        out = {
            'Events in window': self._w_ticks,
            'Events since startup': self.ticks,
            'Duration of window (s)': round(window_s, 6),
            'Actual frequency (Hz)': round(self._w_ticks / window_s, 3),
            'Target frequency (Hz)': self.target_hz,
        }
        if self.realtime:
            # numpy, not a Python loop over the window's ticks: this runs in the executor's
            # thread and holds the GIL that the tick loop's thread needs (a millisecond per
            # report with loops, the size of a late tick)
            dev_ns = np.sort(np.abs(np.asarray(self._intervals, np.int64) - self.period_ns))
            np.add.at(self._jitter_hist, np.minimum(dev_ns // JITTER_BIN_NS, JITTER_BINS - 1), 1)
            dev = dev_ns * 1e-6
            total = self.ticks + self.slipped
            out.update({
                'Minimum acceptable frequency (Hz)': self.target_hz * (1 - self.tolerance),
                'Maximum acceptable frequency (Hz)': self.target_hz * (1 + self.tolerance),
                'Period jitter p99 (ms)': round(float(dev[min(len(dev) - 1,
                                                              int(0.99 * len(dev)))]), 4)
                if len(dev) else 0.0,
                'Period jitter max (ms)': round(float(dev[-1]), 4) if len(dev) else 0.0,
                'Period jitter p99 since startup (ms)': self._jitter_p99_ms(),
                'Late ticks since startup': self.late,
                'Slipped ticks since startup': self.slipped,
                'On time since startup (%)': round(100.0 * (self.ticks - self.late) / total, 3)
                if total else 100.0,
            })
        else:
            out['Simulated s per wall s'] = round(self.ticks * self.period_ns * 1e-9 / run_s, 4)
            if self.resent:
                out['Resent ticks since startup'] = self.resent
        out.update({
            'Overruns since startup': self.overruns,
            'Wall time since startup (s)': round(run_s, 3),
            'Busy (core)': round(self._w_busy_ns * 1e-9 / window_s, 4),
            'Process CPU (core)': round((cpu - self._cpu0) * 1e-9 / window_s, 4),
        })
        if self.gc is not None:
            g = self.gc.stats()
            out.update({'GC collections since startup': g['count'],
                        'GC pause max (ms)': round(g['max_ms'] or 0.0, 4)})
        out.update(self.startup)
        self._level = self._grade(out, self._w_late, self._w_slipped)
        self._w_ticks = self._w_late = self._w_slipped = self._w_busy_ns = 0
        self._intervals = []
        self._w_start, self._cpu0 = now_ns, cpu
        return out

    def _jitter_p99_ms(self) -> float:
        cum = np.cumsum(self._jitter_hist)
        if not cum[-1]:
            return 0.0
        k = int(np.searchsorted(cum, 0.99 * cum[-1]))  # first bin holding the 99th percentile
        return round((k + 1) * JITTER_BIN_NS * 1e-6, 4)

    def _grade(self, v: dict, late: int, slipped: int):
        from diagnostic_msgs.msg import DiagnosticStatus
        if not self.realtime:
            return DiagnosticStatus.OK, 'lockstep: paced by the plant (no wall-clock target)'
        if v['Events in window'] == 0:
            return DiagnosticStatus.ERROR, 'No events recorded.'
        f = v['Actual frequency (Hz)']
        if f < v['Minimum acceptable frequency (Hz)']:
            return DiagnosticStatus.WARN, 'Frequency too low.'
        if f > v['Maximum acceptable frequency (Hz)']:
            return DiagnosticStatus.WARN, 'Frequency too high.'
        if slipped or late:
            return DiagnosticStatus.WARN, f'{late} late and {slipped} slipped ticks in window.'
        return DiagnosticStatus.OK, 'Desired frequency met.'

    def publish(self) -> None:
        """The window's report (the timer's callback); none after :meth:`publish_final`."""
        with self.lock if self.lock is not None else nullcontext():
            # the tick loop's thread counts into the same window
            if self.ended:
                return
            values = self.values()
        self._send(values)

    def publish_final(self) -> None:
        """The node's run has ended (its last tick ran): report the last window now, with
        ``Run ended`` 1, and no more reports after it.  Called where the node's tick runs,
        holding its tick loop's lock if it has one.  A run shorter than ``window_s`` of wall
        time is covered by this report alone."""
        if self.ended:
            return
        self.ended = True
        values = self.values()
        values[RUN_ENDED] = 1
        self._send(values)

    def _send(self, values: dict) -> None:
        publish_status(self.node, self.pub, self.name, *self._level, values)


def begin_timing(node: Node, timing: TickTiming, start_mono_ns: int, warm_up_s: float) -> None:
    """The graph has started: settle the garbage collector (everything alive after start-up
    moves to the permanent generation, so no later collection traverses the JIT's and the
    middleware's objects inside a tick), watch its pauses, and start ``timing`` at
    ``start_mono_ns`` with the start-up times beside it."""
    from eha_ros.realtime import GcPauses, settle_gc
    settle_gc()
    if timing.gc is None:
        timing.gc = GcPauses()
    discovery = max(0.0, (start_mono_ns - node.handshake.created_monotonic_ns) * 1e-9)
    timing.start(start_mono_ns, {'JIT warm-up (s)': round(warm_up_s, 3),
                                 'Discovery (s)': round(discovery, 3)})
