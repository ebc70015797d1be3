"""The live view's cost to the graph and what the viewer gets: realtime 1 kHz in the processes
layout, without the Foxglove bridge and with it and one client subscribed to every channel
(``test/foxglove_client/client.mjs``, Foxglove's own client libraries, every message decoded).

Prints one JSON object:

* ``rounds``: per round the two cases side by side, ``none`` (the graph alone) and ``client``
  (the graph, ``foxglove_bridge`` and one client; ``wait_for_clients=1``, so the client is
  subscribed from the graph's first tick), alternated A-B, B-A, ... so that a drift of the
  machine's load does not favour one. Each case is a fresh process (like ``bench/graph.py``),
  measured by ``bench/graph.py``'s realtime case: per ticking node its on-time share and
  period jitter p99 from its own ``/diagnostics`` timing, the command->state latency p99 at
  the harness's collector, whether the graph lost anything, CPU per node in cores (the
  bridge's among them), the load averages before and after;
* for ``client`` also what the client got: messages per topic, per second from its first
  state to its last (every channel, the decimated ones too), the drops the
  bridge told it (its last warning status), decode errors, and two latencies of the states:
  ``stamp_to_client`` (the client's receipt, system clock, minus the tick's scheduled instant:
  the graph's start time from the handshake plus the state's stamp; it includes the tick's
  own computation) and ``collector_to_client`` (the client's receipt minus the harness's
  collector's receipt of the same state, both on the system clock: what the bridge's path
  adds over a direct subscriber), p50/p99 in ms;
* ``summary``: the mean over rounds of each figure, ``client - none``, and the issue's goals
  (on-time share within 0.2 points, command->state latency p99 within 0.3 ms, 0 lost in the
  graph) as booleans.

    python bench/foxglove.py [--realtime-s 10] [--rounds 2] [--rt on|off] [--load N] [--smoke]

``--smoke``: one round of 1 s without real-time settings: a check, no figure. A case that fails
is ``{"error": ...}`` in the JSON, and the run exits 1.
"""

import argparse
import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import graph as graph_bench  # noqa: E402  (bench/graph.py: the realtime case)

ROOT = Path(__file__).resolve().parents[1]
CLIENT_DIR = ROOT / 'test' / 'foxglove_client'
TOPIC_STATE = '/eha/state'


def _ms(x, q):
    return round(float(np.percentile(x, q)) * 1e3, 3) if len(x) else None


def _client_ready() -> str:
    node = shutil.which('node')
    if node is None:
        sys.exit('foxglove: node (Node.js >= 18) is not on PATH')
    if not (CLIENT_DIR / 'node_modules' / '@foxglove' / 'ws-protocol').is_dir():
        sys.exit(f'foxglove: the client is not installed: run `make node-client` '
                 f'(npm ci in {CLIENT_DIR})')
    return node


def _client_figures(lines: list, result, wall_minus_mono_ns: int) -> dict:
    msgs = [x for x in lines if x['type'] == 'message']
    counts: dict = {}
    for m in msgs:
        counts[m['topic']] = counts.get(m['topic'], 0) + 1
    start_ns = None
    for m in msgs:
        if m['topic'] == '/eha/handshake':
            values = {v['key']: v['value'] for v in m['data']['values']}
            if 'start_time_ns' in values:
                start_ns = int(values['start_time_ns'])
    states = [m for m in msgs if m['topic'] == TOPIC_STATE]
    # the rate over the run: from the first state to the last
    span_s = ((int(states[-1]['wall_ns']) - int(states[0]['wall_ns'])) * 1e-9
              if len(states) > 1 else 0.0)
    in_run = sum(int(states[0]['wall_ns']) <= int(m['wall_ns']) <= int(states[-1]['wall_ns'])
                 for m in msgs) if states else 0
    recv = np.array([int(m['wall_ns']) for m in states], dtype=np.int64)
    stamps = np.array([int(m['logTimeNs']) for m in states], dtype=np.int64)
    stamp_lat = (recv - (start_ns + stamps)) * 1e-9 if start_ns is not None else np.array([])
    # the collector's receipt of the same states (matched by tick), on the system clock
    ticks = np.asarray(result.state['tick'], dtype=np.int64)
    arrival_ns = np.asarray(result.state['arrival_s']) * 1e9 + wall_minus_mono_ns
    order = np.argsort(ticks)
    client_ticks = np.array([int(m['data']['tick']) for m in states], dtype=np.int64)
    pos = np.searchsorted(ticks[order], client_ticks)
    ok = (pos < ticks.size) & (ticks[order][np.minimum(pos, ticks.size - 1)] == client_ticks)
    coll_lat = (recv[ok] - arrival_ns[order][pos[ok]]) * 1e-9
    told = [x for x in lines if x['type'] == 'status' and x.get('id') == 'dropped']
    return {'messages': len(msgs), 'messages_per_topic': counts,
            'messages_per_s_during_run': round(in_run / span_s, 1) if span_s else None,
            'states_received': len(states), 'states_published': int(ticks.size),
            'decode_errors': sum(x['type'] == 'decodeError' for x in lines),
            'drops_told': told[-1]['message'] if told else None,
            'stamp_to_client_p50_ms': _ms(stamp_lat, 50),
            'stamp_to_client_p99_ms': _ms(stamp_lat, 99),
            'collector_to_client_p50_ms': _ms(coll_lat, 50),
            'collector_to_client_p99_ms': _ms(coll_lat, 99)}


def case(kind: str, seconds: float, rt: bool) -> dict:
    """One realtime run (in this process): ``none`` or ``client``."""
    if kind == 'none':
        out = graph_bench.realtime(seconds, True, rt=rt, trace=False)
        out.pop('result')
        return out
    node = _client_ready()
    with tempfile.TemporaryDirectory() as tmp:
        port_file, lines_file = Path(tmp) / 'port', Path(tmp) / 'client.jsonl'
        procs = []

        def start_client():
            end = time.monotonic() + 60
            while not port_file.is_file() and time.monotonic() < end:
                time.sleep(0.02)
            if port_file.is_file():
                url = f'ws://127.0.0.1:{int(port_file.read_text())}'
                procs.append(subprocess.Popen([node, 'client.mjs', '--url', url, '--topics',
                                               'all', '--out', str(lines_file)], cwd=CLIENT_DIR,
                                              stdout=subprocess.DEVNULL))
        watcher = threading.Thread(target=start_client, daemon=True)
        watcher.start()
        params = {'foxglove_bridge': {'port_file': str(port_file), 'wait_for_clients': 1}}
        out = graph_bench.realtime(seconds, True, rt=rt, trace=False, node_params=params,
                                   foxglove='127.0.0.1:0')
        result = out.pop('result')
        wall_minus_mono_ns = time.time_ns() - time.monotonic_ns()
        watcher.join(5)
        if not procs:
            return {'error': 'the client never started (no port from the bridge)'}
        procs[0].wait(30)
        lines = []
        for text in lines_file.read_text().splitlines():
            try:
                lines.append(json.loads(text))
            except ValueError:
                pass
        out['client'] = _client_figures(lines, result, wall_minus_mono_ns)
        out['bridge'] = result.diagnostics.get('foxglove_bridge: clients')
        return out


def _one_case(kind: str, args) -> dict:
    cmd = [sys.executable, __file__, '--case', kind, '--realtime-s', str(args.realtime_s),
           '--rt', args.rt]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        err = done.stderr.strip()
        return {'error': err.splitlines()[-1] if err else f'exit {done.returncode}'}
    return json.loads(done.stdout.strip().splitlines()[-1])


def _figures(c: dict) -> dict:
    return {'plant_on_time_pct': c['plant']['on_time_pct'],
            'command_generator_on_time_pct': c['command_generator']['on_time_pct'],
            'plant_period_jitter_p99_ms': c['plant']['period_jitter_p99_ms'],
            'command_to_state_latency_p99_ms': c['command_to_state_latency_p99_us'] / 1e3,
            'graph_complete': c['data_complete'],
            'bridge_cpu_cores': c['cpu_cores'].get('foxglove_bridge')}


def summarise(rounds: list) -> dict:
    good = [r for r in rounds if 'error' not in r['none'] and 'error' not in r['client']]
    if not good:
        return {'error': 'no round completed'}
    out = {}
    for kind in ('none', 'client'):
        figs = [_figures(r[kind]) for r in good]
        out[kind] = {k: (all(f[k] for f in figs) if k == 'graph_complete' else
                         None if any(f[k] is None for f in figs) else
                         round(float(np.mean([f[k] for f in figs])), 3)) for k in figs[0]}
    d = {k: round(out['client'][k] - out['none'][k], 3)
         for k in ('plant_on_time_pct', 'command_generator_on_time_pct',
                   'plant_period_jitter_p99_ms', 'command_to_state_latency_p99_ms')}
    out['client_minus_none'] = d
    out['goals'] = {
        'on_time_within_0p2_points': abs(d['plant_on_time_pct']) <= 0.2
        and abs(d['command_generator_on_time_pct']) <= 0.2,
        'latency_p99_within_0p3_ms': abs(d['command_to_state_latency_p99_ms']) <= 0.3,
        'nothing_lost_in_the_graph': out['none']['graph_complete']
        and out['client']['graph_complete']}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--realtime-s', type=float, default=10.0)
    ap.add_argument('--rounds', type=int, default=2)
    ap.add_argument('--rt', choices=('on', 'off'), default='on',
                    help='the real-time settings (--rt) for both cases')
    ap.add_argument('--load', type=int, default=0, metavar='N',
                    help='N CPU-bound processes at normal priority beside the runs')
    ap.add_argument('--case', choices=('none', 'client'), help=argparse.SUPPRESS)
    ap.add_argument('--smoke', action='store_true', help='one round of 1 s: a check, no figure')
    args = ap.parse_args()
    if args.case:
        print(json.dumps(case(args.case, args.realtime_s, args.rt == 'on')))
        return
    _client_ready()
    if args.smoke:
        args.realtime_s, args.rounds, args.rt = 1.0, 1, 'off'
    out = {'benchmark': 'foxglove', 'smoke': args.smoke, 'realtime_s': args.realtime_s,
           'rt': args.rt, 'load_processes': args.load, 'cores': os.cpu_count(), 'rounds': []}
    with graph_bench._Load(args.load):
        for k in range(args.rounds):
            order = ('none', 'client') if k % 2 == 0 else ('client', 'none')
            out['rounds'].append({kind: _one_case(kind, args) for kind in order})
    out['summary'] = summarise(out['rounds'])
    print(json.dumps(out))
    failed = [f'round {k} {kind}' for k, r in enumerate(out['rounds']) for kind, c in r.items()
              if 'error' in c]
    if failed:
        sys.exit(f'foxglove: {len(failed)} case(s) failed: {", ".join(failed)}')


if __name__ == '__main__':
    main()
