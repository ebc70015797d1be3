"""Garbage-collector pauses in a 1 kHz node-like loop: default GC, settled (collect + freeze
after warm-up), disabled.

Prints one JSON object.  Each condition runs in its own fresh process, one after the other
(same starting heap, no competition for CPUs): it imports what the plant node imports (rclpy,
numba, numpy, eha_ros.physics), builds ``Plant(default_params())`` and compiles it with
``advance(0.0, 1000)``, runs ``--warmup`` seconds of ticks, applies the condition, then runs
``--seconds`` of ticks paced at ``--rate`` Hz on absolute deadlines.  A tick allocates what the
plant node's tick allocates: ``plant.advance(0.0, 1000)`` (1 ms at dt = 1 us),
``plant.snapshot()`` (a dict of 15 floats) and one ``ActuatorState`` message filled from it;
``--keep N`` also retains the last N messages (a history buffer), ``--keep -1`` every message
(a recorder buffering the run in memory).

The cyclic collector runs when allocations minus deallocations of tracked objects pass 700
(``gc.get_threshold()``), so a tick that frees everything it allocated never triggers it, however
much it allocates: the default ``--keep 0`` shows the steady state of a node; ``--keep -1`` the
net growth (about four tracked objects per tick) that makes collections happen, and, once the
survivors pass a quarter of the long-lived heap, full ones.

Per condition: the GC pauses (:class:`eha_ros.realtime.GcPauses`: count, total, p50, p99, max,
per generation), the tick duration (work only, sleep excluded) p50/p99/max and the ticks over
the period, the wake-up lateness against the deadline, and the tracked heap size.
``os.getloadavg()`` before and after the whole run.

    python bench/gc_pauses.py [--seconds 10] [--rate 1000] [--warmup 1] [--keep 0|N|-1] [--rt]
        [--conditions default,settled,disabled] [--smoke]

``--smoke``: every condition for 0.3 s after 0.1 s of warm-up (a check that the bench runs, no
figure).

``--rt`` applies :data:`eha_ros.realtime.RT_DEFAULTS` (SCHED_FIFO 40 on every thread, memory
locked) in each child before the loop.
"""

import argparse
import collections
import json
import math
import os
import platform
import subprocess
import sys
import time

CONDITIONS = ('default', 'settled', 'disabled')


def _quantiles_us(ns_values) -> dict:
    v = sorted(ns_values)
    if not v:
        return {}

    def q(p):
        return round(v[max(0, min(len(v) - 1, math.ceil(len(v) * p / 100) - 1))] / 1e3, 1)

    return {'p50_us': q(50), 'p99_us': q(99), 'p999_us': q(99.9), 'max_us': round(v[-1] / 1e3, 1),
            'mean_us': round(sum(v) / len(v) / 1e3, 1)}


def child(args) -> dict:
    os.environ.setdefault('NUMBA_NUM_THREADS', '1')
    t0 = time.perf_counter()
    import gc

    import numba  # noqa: F401
    import numpy  # noqa: F401
    import rclpy  # noqa: F401

    from eha_ros.physics import Plant, default_params
    from eha_ros.physics.plant import PositionController  # noqa: F401
    from eha_ros.realtime import RT_DEFAULTS, GcPauses, apply_realtime, current_realtime, \
        settle_gc
    try:
        from eha_ros.msg import ActuatorState
        message = 'eha_ros.msg.ActuatorState'
    except ImportError:  # no generated messages: a stand-in with the same fields
        class ActuatorState:
            __slots__ = ('jack_position_m', 'jack_position_measured_m', 'jack_velocity_m_s',
                         'spool_position_m', 'flapper_position_m', 'p1_pa', 'p2_pa', 'p12_pa',
                         'load_flow_m3_s', 'coil_current_a', 'torque_motor_force_n',
                         'sim_time_s', 'tick', 'model')
        message = 'stand-in class'
    t_import = time.perf_counter() - t0
    plant = Plant(default_params())
    t1 = time.perf_counter()
    plant.advance(0.0, 1000)
    t_jit = time.perf_counter() - t1
    keep = collections.deque(maxlen=args.keep if args.keep > 0 else None) if args.keep else None

    def tick():
        plant.advance(0.0, 1000)
        s = plant.snapshot()
        msg = ActuatorState()
        msg.jack_position_m = s['jack_position_m']
        msg.jack_position_measured_m = s['jack_position_measured_m']
        msg.jack_velocity_m_s = s['jack_velocity_m_s']
        msg.spool_position_m = s['spool_position_m']
        msg.flapper_position_m = s['flapper_position_m']
        msg.p1_pa = s['p1_pa']
        msg.p2_pa = s['p2_pa']
        msg.p12_pa = s['p12_pa']
        msg.load_flow_m3_s = s['load_flow_m3_s']
        msg.coil_current_a = s['coil_current_a']
        msg.torque_motor_force_n = s['torque_motor_force_n']
        msg.sim_time_s = s['time_s']
        msg.tick = plant.steps
        msg.model = 'hf'
        if keep is not None:
            keep.append(msg)

    period = round(1e9 / args.rate)

    def loop(n):
        dur = [0] * n
        late = [0] * n
        now = time.perf_counter_ns
        sleep = time.sleep
        due = now()
        for i in range(n):
            due += period
            t = now()
            if due > t:
                sleep((due - t) / 1e9)
            start = now()
            late[i] = start - due
            tick()
            dur[i] = now() - start
            if start - due > period:  # more than a period behind: start afresh, no burst
                due = start
        return dur, late

    loop(round(args.warmup * args.rate))
    out = {'message': message, 'import_s': round(t_import, 2), 'jit_s': round(t_jit, 2)}
    if args.rt:
        out['rt_warnings'] = apply_realtime(RT_DEFAULTS)
        rt = current_realtime()
        out['rt'] = {k: rt[k] for k in ('policy', 'priority', 'memory_locked_kb')}
    out['tracked_objects'] = len(gc.get_objects())
    if args.condition == 'settled':
        out['frozen_objects'] = settle_gc()
    elif args.condition == 'disabled':
        gc.disable()
    pauses = GcPauses()
    n = round(args.seconds * args.rate)
    dur, late = loop(n)
    pauses.close()
    stats = pauses.stats()
    for k, v in list(stats.items()):
        if k.endswith('_ms') and v is not None:
            stats[k] = round(v, 4)
    for g in stats['per_generation'].values():
        g['total_ms'] = round(g['total_ms'], 3)
        g['max_ms'] = round(g['max_ms'], 4)
    out.update(ticks=n, gc=stats, tick=_quantiles_us(dur),
               over_period=sum(d > period for d in dur), late=_quantiles_us(late),
               gc_count_after=gc.get_count())
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--rate', type=float, default=1000.0)
    ap.add_argument('--warmup', type=float, default=1.0)
    ap.add_argument('--keep', type=int, default=0)
    ap.add_argument('--rt', action='store_true')
    ap.add_argument('--conditions', default=','.join(CONDITIONS))
    ap.add_argument('--condition', help=argparse.SUPPRESS)  # child
    ap.add_argument('--smoke', action='store_true',
                    help='every condition for 0.3 s: a check, no figure')
    args = ap.parse_args()
    if args.smoke:
        args.seconds, args.warmup = 0.3, 0.1
    if args.condition:
        print(json.dumps(child(args)))
        return
    conditions = [c for c in args.conditions.split(',') if c]
    unknown = set(conditions) - set(CONDITIONS)
    if unknown:
        ap.error(f'unknown conditions {sorted(unknown)}; known: {", ".join(CONDITIONS)}')
    out = {'benchmark': 'gc_pauses', 'smoke': args.smoke, 'python': platform.python_version(),
           'cpus': os.cpu_count(), 'seconds': args.seconds, 'rate_hz': args.rate,
           'warmup_s': args.warmup, 'keep': args.keep, 'rt': args.rt,
           'loadavg_before': [round(x, 2) for x in os.getloadavg()], 'conditions': {}}
    for cond in conditions:
        cmd = [sys.executable, os.path.abspath(__file__), '--condition', cond,
               '--seconds', str(args.seconds), '--rate', str(args.rate), '--warmup',
               str(args.warmup), '--keep', str(args.keep)] + (['--rt'] if args.rt else [])
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode:
            sys.exit(f'{cond}: child failed ({r.returncode}):\n{r.stderr}')
        out['conditions'][cond] = json.loads(r.stdout.strip().splitlines()[-1])
    out['loadavg_after'] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out, indent=1))


if __name__ == '__main__':
    main()
