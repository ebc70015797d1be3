"""Timing of the node graph (each node its own process, Fast DDS).

Prints one JSON object:

* ``realtime``: achieved tick rate of the plant (states per wall second), tick jitter (state
  inter-arrival time minus the period: p50/p99/max of its absolute value) and command->state
  latency (from the collector's receipt of a ``ServovalveCommand`` to its receipt of the next
  ``ActuatorState``: it includes the wait for the plant's next tick, uniform in 0..1 period),
  the first second (discovery, JIT load) left out; the controller's achieved rate (current
  commands per wall second) and the command generator's messages per plant state;
* ``lockstep``: simulated seconds per wall second for hf and each shipped surrogate, between the
  first and the last state (start-up reported separately).

    python bench/graph.py [--realtime-s 10] [--lockstep-s 1.0] [--models hf,lut,ga,nn]
"""

import argparse
import json

import numpy as np

from eha_ros.harness import GraphConfig, run_graph
from eha_ros.surrogates.base import models_dir
from eha_ros.isolation import ros_environment


def _us(x, q):
    return round(float(np.percentile(x, q)) * 1e6, 1) if len(x) else None


def realtime(seconds):
    cfg = GraphConfig(scenario='sine_0p1_5pi', mode='realtime', duration_s=seconds)
    with ros_environment() as env:
        r = run_graph(cfg, processes=True, env=env, timeout_s=60)
    st = r.state['arrival_s']
    sv = r.servovalve['arrival_s']
    period = 1.0 / cfg.rate_hz
    skip = st[0] + 1.0
    st_ss = st[st > skip]
    jitter = np.abs(np.diff(st_ss) - period)
    sv_ss = sv[sv > skip]
    idx = np.searchsorted(st, sv_ss)
    lat = st[idx[idx < st.size]] - sv_ss[idx < st.size]
    return {'wall_s': round(float(st[-1] - st[0]), 3), 'states': int(st.size),
            'achieved_rate_hz': round(float((st_ss.size - 1) / (st_ss[-1] - st_ss[0])), 1),
            'target_rate_hz': cfg.rate_hz,
            'tick_jitter_p50_us': _us(jitter, 50), 'tick_jitter_p99_us': _us(jitter, 99),
            'tick_jitter_max_us': round(float(jitter.max()) * 1e6, 1),
            'command_to_state_latency_p50_us': _us(lat, 50),
            'command_to_state_latency_p99_us': _us(lat, 99),
            'controller_rate_hz': round(float((sv_ss.size - 1) / (sv_ss[-1] - sv_ss[0])), 1),
            'command_generator_messages_per_state': round(
                float(r.command['stamp_ns'].size / st.size), 3)}


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
    ap.add_argument('--lockstep-s', type=float, default=1.0)
    ap.add_argument('--models', default='hf,lut,ga,nn')
    args = ap.parse_args()
    models = args.models.split(',')
    print(json.dumps({'benchmark': 'graph', 'realtime': realtime(args.realtime_s),
                      'lockstep_processes': lockstep(models, args.lockstep_s, True),
                      'lockstep_one_process': lockstep(models, args.lockstep_s, False)}))


if __name__ == '__main__':
    main()
