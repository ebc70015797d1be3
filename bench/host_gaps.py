"""How often the machine itself takes a CPU away from the highest-priority thread: the time a
late tick can lose that no thread, priority or setting inside this machine explains.

A thread at ``SCHED_FIFO`` 99, pinned to one CPU, reads the monotonic clock in a tight loop
and records every gap between two reads longer than ``--gap-us`` (default 200 µs).  Nothing
in the guest preempts it but interrupts, so a gap is the CPU's interrupt handling or the
hypervisor running something else on the vCPU (host steal).  It spins in bursts of 0.4 s with
0.1 s of sleep between them (``kernel.sched_rt_runtime_us`` lets real-time threads have at
most 95 % of each second; the bursts stay under it, so RT throttling makes no gap).  Beside
the gaps, the CPU's steal from ``/proc/stat`` over the run (USER_HZ ticks: 10 ms each).

Prints one JSON object per CPU probed: gaps over 0.2 / 0.5 / 1 / 5 ms per second of spinning,
the longest gap, the steal (ms and % of the run) and the load averages before and after.
Where SCHED_FIFO is refused it says so and measures at normal priority (then the gaps include
the other processes of this machine).

    python bench/host_gaps.py [--seconds 10] [--cpus 0,1] [--load N] [--smoke]

``--load N``: N CPU-bound processes at normal priority beside it (as ``bench/graph.py
--load``); at FIFO 99 they cannot take the probe's CPU, so what changes is the host's.
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np


def _steal_jiffies() -> dict:
    out = {}
    with open('/proc/stat') as f:
        for line in f:
            if line.startswith('cpu') and line[3].isdigit():
                parts = line.split()
                out[int(parts[0][3:])] = int(parts[8])
    return out


def probe(cpu: int, seconds: float, gap_ns: int) -> dict:
    """Spin on ``cpu`` for ``seconds`` in bursts (see the module docstring)."""
    import threading
    result = {}

    def run():
        os.sched_setaffinity(0, {cpu})
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(99))
            result['priority'] = 'SCHED_FIFO 99'
        except OSError as e:
            result['priority'] = f'normal (SCHED_FIFO refused: {e.strerror})'
        gaps, spun = [], 0
        mono = time.monotonic_ns
        end = mono() + int(seconds * 1e9)
        while mono() < end:
            b0 = last = mono()
            b_end = b0 + 400_000_000
            while last < b_end:
                t = mono()
                if t - last > gap_ns:
                    gaps.append(t - last)
                last = t
            spun += last - b0
            time.sleep(0.1)
        result['gaps'], result['spun_ns'] = gaps, spun

    s0, t0 = _steal_jiffies(), time.monotonic()
    th = threading.Thread(target=run)
    th.start()
    th.join()
    s1, wall = _steal_jiffies(), time.monotonic() - t0
    g = np.array(result['gaps'], float) / 1e6
    spun_s = result['spun_ns'] * 1e-9
    tick_ms = 1000.0 / os.sysconf('SC_CLK_TCK')
    steal_ms = (s1.get(cpu, 0) - s0.get(cpu, 0)) * tick_ms
    return {'cpu': cpu, 'priority': result['priority'], 'spun_s': round(spun_s, 3),
            'gaps_per_s': {f'over_{t}_ms': round(float((g > t).sum()) / spun_s, 3)
                           for t in (0.2, 0.5, 1, 5)},
            'gaps_over_1_ms': int((g > 1).sum()),
            'longest_gap_ms': round(float(g.max()), 3) if g.size else 0.0,
            'gap_ms_per_s': round(float(g.sum()) / spun_s, 3),
            'steal_ms': steal_ms, 'steal_pct': round(100 * steal_ms / (wall * 1000), 3),
            'steal_resolution_ms': tick_ms}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--cpus', default='', help='CPUs to probe in turn (default: every one)')
    ap.add_argument('--gap-us', type=float, default=200.0)
    ap.add_argument('--load', type=int, default=0, metavar='N')
    ap.add_argument('--smoke', action='store_true', help='0.5 s on one CPU: a check, no figure')
    args = ap.parse_args()
    cpus = sorted(os.sched_getaffinity(0))
    if args.cpus:
        cpus = [int(c) for c in args.cpus.split(',')]
    if args.smoke:
        args.seconds, cpus = 0.5, cpus[-1:]
    load_before = os.getloadavg()
    hogs = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
            for _ in range(args.load)]
    try:
        results = [probe(c, args.seconds, int(args.gap_us * 1e3)) for c in cpus]
    finally:
        for p in hogs:
            p.kill()
            p.wait()
    print(json.dumps({'benchmark': 'host_gaps', 'smoke': args.smoke, 'seconds': args.seconds,
                      'load_processes': args.load, 'gap_threshold_us': args.gap_us,
                      'cpus': results,
                      'load_average_1_5_15_before': [round(x, 2) for x in load_before],
                      'load_average_1_5_15_after': [round(x, 2) for x in os.getloadavg()]}))


if __name__ == '__main__':
    main()
