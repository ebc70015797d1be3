"""Timing of the node graph (Fast DDS), each node its own process or all in one process,
without and with the real-time settings, optionally beside CPU-bound load.

Prints one JSON object:

* ``realtime_<layout>`` and ``realtime_<layout>_rt`` (``--rt both``, the default: side by side
  in one run, each case in a fresh process so that one case's SCHED_FIFO never leaks into the
  next), all counted from the graph's synchronised start (the end of the start-up handshake;
  discovery and JIT warm-up reported apart): per ticking node its own timing report from
  ``/diagnostics`` (ticks, on time, late, slipped, period jitter p99 since the start, overruns,
  GC collections and the longest pause); the states' inter-arrival jitter at the collector
  (p50/p99/max of |interval - period|) and the command->state latency (from the collector's
  receipt of a ``ServovalveCommand`` to its receipt of the next ``ActuatorState``: it includes
  the wait for the plant's next tick, uniform in 0..1 period), both on the middleware's receipt
  times; whether every message arrived; CPU per node in cores; the load averages before and
  after (``os.getloadavg``: others' work on the same cores shows there);
* ``lockstep_<layout>``: simulated seconds per wall second for hf and each shipped surrogate from
  the synchronised start, re-sent ticks, start-up time.

``--load N`` starts N CPU-bound processes (``while True: pass``) at normal priority before the
realtime runs and stops them after: what a rig PC's other work does to the graph.

    python bench/graph.py [--realtime-s 10] [--lockstep-s 1.0] [--models hf,lut,ga,nn]
                          [--layouts processes,one-process] [--rt off|on|both] [--load N]
                          [--health] [--record] [--smoke]

``--smoke``: one realtime case of 0.5 s per real-time setting (one process) and 50 ms of
lockstep per model of ``--models`` (default hf, lut; processes): a check, no figure.  A case
that fails is reported as ``{"error": ...}`` in the JSON, and the run exits 1.
"""

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from eha_ros.graph import TIMING_SUFFIX
from eha_ros.harness import GraphConfig, run_graph
from eha_ros.isolation import ros_environment
from eha_ros.artefacts import models_dir

_TICK_S = os.sysconf('SC_CLK_TCK')


def _us(x, q):
    return round(float(np.percentile(x, q)) * 1e6, 1) if len(x) else None


def _cpu_s(pid):
    """User + system CPU seconds of a process (and its reaped children), from /proc."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return None
    return sum(int(v) for v in fields[11:13]) / _TICK_S


class _CpuSampler:
    """CPU seconds of the node processes at the end of the first second and at the end."""

    def __init__(self, skip_s=1.0):
        self.pids, self.first, self.last, self.skip_s = {}, {}, {}, skip_s
        self.t_first = self.t_last = None
        self._stop = threading.Event()

    def start(self, pids):
        self.pids = dict(pids)
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        time.sleep(self.skip_s)
        self.t_first = time.monotonic()
        self.first = {n: _cpu_s(p) for n, p in self.pids.items()}
        while not self._stop.wait(0.2):
            sample = {n: _cpu_s(p) for n, p in self.pids.items()}
            if all(v is not None for v in sample.values()):
                self.last, self.t_last = sample, time.monotonic()

    def cores(self):
        self._stop.set()
        if not self.t_last or not self.t_first or self.t_last <= self.t_first:
            return {}
        dt = self.t_last - self.t_first
        return {n: round((self.last[n] - self.first[n]) / dt, 3) for n in self.pids}


def realtime(seconds, processes, health=False, record=False, rt=False, trace=True,
             node_params=None, foxglove='', on_start=None):
    """One realtime run; ``foxglove``: ``[HOST:]PORT`` of a bridge beside it
    (``bench/foxglove.py``), ``on_start(pids)`` called beside the CPU sampler's."""
    cfg = GraphConfig(scenario='sine_0p1_5pi', mode='realtime', duration_s=seconds,
                      health=health, rt=rt, node_params=dict(node_params or {}),
                      foxglove=foxglove)
    load_before = os.getloadavg()
    sampler = _CpuSampler(skip_s=0.0)
    with tempfile.TemporaryDirectory() as tmp, ros_environment() as env:
        if record:
            cfg.record = str(Path(tmp) / 'run.mcap')
        if trace:
            cfg.trace = str(Path(tmp) / 'trace.mcap')
        cpu0, t0 = time.process_time(), time.monotonic()

        def started(pids):
            sampler.start(pids)
            if on_start is not None:
                on_start(pids)
        r = run_graph(cfg, processes=processes, env=env, timeout_s=60, on_start=started)
        own_cpu = (time.process_time() - cpu0) / (time.monotonic() - t0)
        recording = None
        if record:
            from eha_ros.recording.reader import scan
            info = scan(cfg.record)
            recording = {'messages': info.message_counts, 'lost': info.lost_messages()}
    load_after = os.getloadavg()
    # everything from the graph's synchronised start (the first state is tick 0)
    st = r.state['arrival_s']
    sv = r.servovalve['arrival_s']
    period = 1.0 / cfg.rate_hz
    jitter = np.abs(np.diff(st) - period)
    idx = np.searchsorted(st, sv)
    lat = st[idx[idx < st.size]] - sv[idx < st.size]
    timing = {name[:-len(TIMING_SUFFIX)]: {k: float(v) for k, v in d['values'].items()}
              for name, d in r.diagnostics.items() if name.endswith(TIMING_SUFFIX)}
    cpu = sampler.cores()
    if processes:
        cpu['harness (collector)'] = round(own_cpu, 3)
    else:
        cpu = {n: t.get('Busy (core)') for n, t in timing.items()}
        cpu['whole process (every node, collector, executor)'] = round(own_cpu, 3)
        cpu.update({n: c for n, c in sampler.cores().items()})  # the recorder, if any

    def node(name):
        t = timing.get(name, {})
        return {'ticks': t.get('Events since startup'),
                'on_time_pct': t.get('On time since startup (%)'),
                'late': t.get('Late ticks since startup'),
                'slipped': t.get('Slipped ticks since startup'),
                'period_jitter_p99_ms': t.get('Period jitter p99 since startup (ms)'),
                'overruns': t.get('Overruns since startup'),
                'gc_collections': t.get('GC collections since startup'),
                'gc_pause_max_ms': t.get('GC pause max (ms)'),
                'discovery_s': t.get('Discovery (s)'), 'jit_warm_up_s': t.get('JIT warm-up (s)')}
    out = {'rt': rt, 'wall_s': round(float(r.wall_s), 3), 'discovery_s': round(r.discovery_s, 2),
           'states': int(st.size), 'data_complete': r.complete, 'data_loss': r.loss_report(),
           'achieved_rate_hz': round(float((st.size - 1) / (st[-1] - st[0])), 1),
           'target_rate_hz': cfg.rate_hz,
           'plant': node('servovalve_plant'), 'controller': node('controller'),
           'command_generator': node('command_generator'),
           'state_interarrival_jitter_p50_us': _us(jitter, 50),
           'state_interarrival_jitter_p99_us': _us(jitter, 99),
           'state_interarrival_jitter_max_us': round(float(jitter.max()) * 1e6, 1),
           'command_to_state_latency_p50_us': _us(lat, 50),
           'command_to_state_latency_p99_us': _us(lat, 99),
           'current_commands_per_state': round(float(sv.size / st.size), 4),
           'command_generator_messages_per_state': round(
               float(r.command['stamp_ns'].size / st.size), 3),
           'cpu_cores': cpu, 'cpu_cores_total': round(own_cpu + sum(sampler.cores().values()),
                                                      3),
           'node_timing': timing,
           'load_average_1_5_15_before': [round(x, 2) for x in load_before],
           'load_average_1_5_15_after': [round(x, 2) for x in load_after],
           'cores': os.cpu_count()}
    if recording is not None:
        out['recording'] = recording
    out['result'] = r   # for a caller in this process; not printed
    if r.trace is not None:
        out['late_causes'] = {n: t.get('shares', t) for n, t in r.trace.items()}
    return out


def lockstep(models, sim_s, processes):
    out = {}
    for model in models:
        if model != 'hf' and not (models_dir('surrogates') / f'{model}.npz').is_file():
            out[model] = {'skipped': 'no shipped artefact'}
            continue
        with ros_environment() as env:
            r = run_graph(GraphConfig(scenario='sine_0p1_5pi', model=model, duration_s=sim_s),
                          processes=processes, env=env, timeout_s=120)
        timing = {name[:-len(TIMING_SUFFIX)]: d['values'] for name, d in r.diagnostics.items()
                  if name.endswith(TIMING_SUFFIX)}
        out[model] = {'sim_s': r.sim_s, 'ticks': int(r.state['tick'].size),
                      'sim_s_per_wall_s': round(r.sim_s / r.wall_s, 3),
                      'ticks_per_wall_s': round(r.state['tick'].size / r.wall_s, 1),
                      'resent_ticks': r.resent_ticks, 'data_complete': r.complete,
                      'startup_discovery_s': round(r.discovery_s, 2),
                      'plant_resent': timing.get('servovalve_plant', {}).get(
                          'Resent ticks since startup', '0')}
    return out


class _Load:
    """``n`` CPU-bound processes at normal priority beside the graph (a rig PC also runs a
    recorder, a GUI, logging), stopped on exit."""

    def __init__(self, n):
        self.n = n
        self.procs = []

    def __enter__(self):
        self.procs = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
                      for _ in range(self.n)]
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
            p.wait()


def _node_params(items) -> dict:
    """``['node.name=value', ...]`` -> ``{node: {name: value}}`` (values as YAML scalars)."""
    import yaml
    out = {}
    for item in items or ():
        target, eq, value = item.partition('=')
        node, dot, name = target.partition('.')
        if not eq or not dot:
            sys.exit(f'graph: --set {item!r}: expected node.name=value')
        out.setdefault(node, {})[name] = yaml.safe_load(value)
    return out


def _one_case(layout, rt, args) -> dict:
    """One realtime measurement in a fresh process (real-time settings in one process apply to
    the whole process: they must not leak into the next case)."""
    cmd = [sys.executable, __file__, '--case', f'{layout}:{int(rt)}', '--realtime-s',
           str(args.realtime_s)] + (['--health'] if args.health else []) + (
        ['--record'] if args.record else []) + (['--no-trace'] if args.no_trace else []) + [
        a for s in args.set or () for a in ('--set', s)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if out.returncode != 0:
        return {'error': out.stderr.strip().splitlines()[-1] if out.stderr.strip() else
                f'exit {out.returncode}'}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--realtime-s', type=float, default=10.0, help='0: no realtime runs')
    ap.add_argument('--lockstep-s', type=float, default=1.0, help='0: no lockstep runs')
    ap.add_argument('--models', default='hf,lut,ga,nn')
    ap.add_argument('--layouts', default='processes,one-process')
    ap.add_argument('--health', action='store_true', help='realtime with the health monitor')
    ap.add_argument('--record', action='store_true', help='realtime with the recorder')
    ap.add_argument('--load', type=int, default=0, metavar='N',
                    help='N CPU-bound processes at normal priority beside the realtime runs')
    ap.add_argument('--rt', choices=('off', 'on', 'both'), default='both',
                    help='realtime runs without and/or with the real-time settings (--rt)')
    ap.add_argument('--no-trace', action='store_true',
                    help='realtime without the timing trace (no late-tick causes)')
    ap.add_argument('--set', action='append', metavar='NODE.NAME=VALUE',
                    help='a node parameter for the realtime runs (repeatable), e.g. '
                         'servovalve_plant.switch_interval_s=0.0005')
    ap.add_argument('--case', help=argparse.SUPPRESS)
    ap.add_argument('--smoke', action='store_true', help='tiny cases: a check, no figure')
    args = ap.parse_args()
    if args.smoke and not args.case:
        args.realtime_s, args.lockstep_s, args.layouts = 0.5, 0.05, 'one-process'
        if args.models == ap.get_default('models'):
            args.models = 'hf,lut'
    if args.case:  # one realtime measurement (a child of the run below)
        layout, rt = args.case.split(':')
        case = realtime(args.realtime_s, layout == 'processes', args.health, args.record,
                        rt == '1', not args.no_trace, _node_params(args.set))
        case.pop('result')
        print(json.dumps(case))
        return
    models = args.models.split(',')
    out = {'benchmark': 'graph', 'smoke': args.smoke,
           'load_processes': args.load, 'realtime_s': args.realtime_s,
           'node_params': _node_params(args.set)}
    rts = {'off': [False], 'on': [True], 'both': [False, True]}[args.rt]
    layouts = args.layouts.split(',')
    if args.realtime_s > 0:
        with _Load(args.load):
            for layout in layouts:
                for rt in rts:
                    key = 'realtime_' + layout.replace('-', '_') + ('_rt' if rt else '')
                    out[key] = _one_case(layout, rt, args)
    if args.lockstep_s > 0:
        for layout in layouts:
            out['lockstep_' + layout.replace('-', '_')] = lockstep(models, args.lockstep_s,
                                                                   layout == 'processes')
    print(json.dumps(out))
    failed = [k for k, v in out.items() if isinstance(v, dict) and 'error' in v]
    if failed:
        sys.exit(f'graph: {len(failed)} case(s) failed: {", ".join(failed)}')


if __name__ == '__main__':
    main()
