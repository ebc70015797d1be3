"""Timing of the node graph (Fast DDS), each node its own process or all in one process.

Prints one JSON object:

* ``realtime_processes`` / ``realtime_one_process``: the plant's achieved tick rate, tick jitter
  (state inter-arrival time at the collector minus the period: p50/p99/max of its absolute
  value) and command->state latency (from the collector's receipt of a ``ServovalveCommand``
  to its receipt of the next ``ActuatorState``: it includes the wait for the plant's next
  tick, uniform in 0..1 period), the first second (discovery, JIT load) left out; the
  controller's achieved rate; each node's own timing report from ``/diagnostics`` (ticks on
  time, late, slipped, overruns); CPU per node in cores (processes: from ``/proc/<pid>/stat``
  over the run after its first second; one process: each node's callback time per wall
  second, and the whole process's CPU); the machine's load averages before and after
  (``os.getloadavg``: others' work on the same cores shows there);
* ``lockstep``: simulated seconds per wall second for hf and each shipped surrogate, between the
  first and the last state (start-up reported separately).

    python bench/graph.py [--realtime-s 10] [--lockstep-s 1.0] [--models hf,lut,ga,nn]
                          [--layouts processes,one-process] [--health] [--record]
"""

import argparse
import json
import os
from pathlib import Path
import tempfile
import threading
import time

import numpy as np

from eha_ros.graph import TIMING_SUFFIX
from eha_ros.harness import GraphConfig, run_graph
from eha_ros.isolation import ros_environment
from eha_ros.surrogates.base import models_dir

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


def realtime(seconds, processes, health=False, record=False):
    cfg = GraphConfig(scenario='sine_0p1_5pi', mode='realtime', duration_s=seconds,
                      health=health)
    load_before = os.getloadavg()
    sampler = _CpuSampler()
    with tempfile.TemporaryDirectory() as tmp, ros_environment() as env:
        if record:
            cfg.record = str(Path(tmp) / 'run.mcap')
        cpu0, t0 = time.process_time(), time.monotonic()
        r = run_graph(cfg, processes=processes, env=env, timeout_s=60, on_start=sampler.start)
        own_cpu = (time.process_time() - cpu0) / (time.monotonic() - t0)
        recording = None
        if record:
            from eha_ros.recording.reader import scan
            info = scan(cfg.record)
            recording = {'messages': info.message_counts, 'lost': info.lost_messages()}
    load_after = os.getloadavg()
    st = r.state['arrival_s']
    sv = r.servovalve['arrival_s']
    period = 1.0 / cfg.rate_hz
    skip = st[0] + 1.0
    st_ss = st[st > skip]
    jitter = np.abs(np.diff(st_ss) - period)
    sv_ss = sv[sv > skip]
    idx = np.searchsorted(st, sv_ss)
    lat = st[idx[idx < st.size]] - sv_ss[idx < st.size]
    timing = {name[:-len(TIMING_SUFFIX)]: {k: float(v) for k, v in d['values'].items()}
              for name, d in r.diagnostics.items() if name.endswith(TIMING_SUFFIX)}
    plant = timing.get('servovalve_plant', {})
    cpu = sampler.cores()
    if processes:
        cpu['harness (collector)'] = round(own_cpu, 3)
    else:
        cpu = {n: t.get('Busy (core)') for n, t in timing.items()}
        cpu['whole process (every node, collector, executor)'] = round(own_cpu, 3)
        cpu.update({n: c for n, c in sampler.cores().items()})  # the recorder, if any
    out = {'wall_s': round(float(st[-1] - st[0]), 3), 'states': int(st.size),
           'achieved_rate_hz': round(float((st_ss.size - 1) / (st_ss[-1] - st_ss[0])), 1),
           'target_rate_hz': cfg.rate_hz,
           'plant_ticks_on_time_pct': plant.get('On time since startup (%)'),
           'plant_ticks': plant.get('Events since startup'),
           'plant_late_ticks': plant.get('Late ticks since startup'),
           'plant_slipped_ticks': plant.get('Slipped ticks since startup'),
           'tick_jitter_p50_us': _us(jitter, 50), 'tick_jitter_p99_us': _us(jitter, 99),
           'tick_jitter_max_us': round(float(jitter.max()) * 1e6, 1),
           'command_to_state_latency_p50_us': _us(lat, 50),
           'command_to_state_latency_p99_us': _us(lat, 99),
           'controller_rate_hz': round(float((sv_ss.size - 1) / (sv_ss[-1] - sv_ss[0])), 1),
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
    return out


def lockstep(models, sim_s, processes):
    out = {}
    for model in models:
        if model != 'hf' and not (models_dir() / f'{model}.npz').is_file():
            out[model] = {'skipped': 'no shipped artefact'}
            continue
        with ros_environment() as env:
            r = run_graph(GraphConfig(scenario='sine_0p1_5pi', model=model, duration_s=sim_s),
                          processes=processes, env=env, timeout_s=120)
        a = r.state['arrival_s']
        steady = a[-1] - a[0]
        out[model] = {'sim_s': r.sim_s, 'ticks': int(a.size),
                      'sim_s_per_wall_s': round(r.sim_s / steady, 3),
                      'ticks_per_wall_s': round(a.size / steady, 1),
                      'startup_wall_s': round(float(r.wall_s - steady), 2)}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--realtime-s', type=float, default=10.0)
    ap.add_argument('--lockstep-s', type=float, default=1.0, help='0: no lockstep runs')
    ap.add_argument('--models', default='hf,lut,ga,nn')
    ap.add_argument('--layouts', default='processes,one-process')
    ap.add_argument('--health', action='store_true', help='realtime with the health monitor')
    ap.add_argument('--record', action='store_true', help='realtime with the recorder')
    args = ap.parse_args()
    models = args.models.split(',')
    out = {'benchmark': 'graph'}
    for layout in args.layouts.split(','):
        key = layout.replace('-', '_')
        out[f'realtime_{key}'] = realtime(args.realtime_s, layout == 'processes', args.health,
                                          args.record)
        if args.lockstep_s > 0:
            out[f'lockstep_{key}'] = lockstep(models, args.lockstep_s, layout == 'processes')
    print(json.dumps(out))


if __name__ == '__main__':
    main()
