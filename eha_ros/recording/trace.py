"""A realtime run's timing trace as an MCAP file that any MCAP tool opens (Foxglove,
``mcap cat``, the ``mcap`` Python reader): JSON messages, one channel per ticking node.

* ``/eha/timing_trace/<node>``: one message per tick (:data:`eha_ros.tickloop.TRACE_COLUMNS`;
  times in ns on the monotonic clock, log time the tick's due time on the wall clock);
* ``/eha/timing_episodes/<node>``: one message per late episode, its evidence and its cause
  (:func:`eha_ros.tickloop.late_episodes`);
* metadata ``eha_timing_trace``: per node, its period, the ticks, the ticks the trace had no
  room for (``dropped``: the trace is then flagged incomplete), and the late ticks by cause.

    from eha_ros.recording.trace import read_trace
    trace = read_trace('run_trace.mcap')   # {node: {'ticks': {column: array}, 'episodes', ...}}
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from eha_ros.tickloop import cause_shares, late_episodes, TRACE_COLUMNS

__all__ = ['write_trace', 'read_trace', 'load_node_trace', 'summarise', 'TRACE_TOPIC',
           'EPISODES_TOPIC']

TRACE_TOPIC = '/eha/timing_trace/'
EPISODES_TOPIC = '/eha/timing_episodes/'
_METADATA = 'eha_timing_trace'


def load_node_trace(path) -> dict:
    """A node's saved trace (:meth:`eha_ros.tickloop.TickTrace.save`): ``{'node',
    'period_ns', 'dropped', 'clk_tck', 'ticks': {column: array}}``."""
    with np.load(path) as d:
        return {'node': str(d['node']), 'period_ns': int(d['period_ns']),
                'dropped': int(d['dropped']), 'clk_tck': int(d['clk_tck']),
                'ticks': {c: np.asarray(d[c]) for c in TRACE_COLUMNS}}


def summarise(trace: dict) -> dict:
    """``trace`` (:func:`load_node_trace`) with its ``episodes`` and ``shares``
    (:func:`eha_ros.tickloop.cause_shares`), and ``complete`` (no tick dropped)."""
    episodes = late_episodes(trace['ticks'], trace['period_ns'], trace['clk_tck'])
    n = len(trace['ticks']['tick'])
    return dict(trace, episodes=episodes, shares=cause_shares(episodes, n),
                complete=trace['dropped'] == 0)


def _schema(title: str, properties: dict) -> bytes:
    return json.dumps({'type': 'object', 'title': title, 'properties': {
        k: {'type': v, 'description': k}
        for k, v in properties.items()}}).encode()


def write_trace(path, traces: dict, wall_offset_ns: int) -> None:
    """Write ``traces`` (``{node: summarise(...)}``) to the MCAP ``path`` (written whole to a
    temporary file, then renamed: never a partial file).  ``wall_offset_ns``: wall clock minus
    monotonic clock, for the log times."""
    from mcap.writer import Writer
    path = Path(path)
    tmp = path.with_name(path.name + '.part')
    with open(tmp, 'wb') as f:
        w = Writer(f)
        w.start(profile='', library='eha_ros')
        tick_schema = w.register_schema(
            name='eha_ros/TickTrace', encoding='jsonschema',
            data=_schema('TickTrace', {c: 'integer' for c in TRACE_COLUMNS}))
        ep_schema = w.register_schema(
            name='eha_ros/LateEpisode', encoding='jsonschema',
            data=_schema('LateEpisode', {'first_tick': 'integer', 'ticks': 'integer',
                                         'lateness_ms': 'number', 'cause': 'string'}))
        meta = {}
        for node, tr in traces.items():
            ch = w.register_channel(topic=TRACE_TOPIC + node, message_encoding='json',
                                    schema_id=tick_schema)
            cols = tr['ticks']
            rows = np.column_stack([cols[c] for c in TRACE_COLUMNS]).tolist() \
                if len(cols['tick']) else []
            for seq, row in enumerate(rows):
                t = int(row[1]) + wall_offset_ns
                w.add_message(channel_id=ch, log_time=t, publish_time=t, sequence=seq,
                              data=json.dumps(dict(zip(TRACE_COLUMNS, row))).encode())
            ch = w.register_channel(topic=EPISODES_TOPIC + node, message_encoding='json',
                                    schema_id=ep_schema)
            due = dict(zip(cols['tick'].tolist(), cols['due_ns'].tolist()))
            for seq, ep in enumerate(tr['episodes']):
                t = int(due.get(ep['first_tick'], 0)) + wall_offset_ns
                w.add_message(channel_id=ch, log_time=t, publish_time=t, sequence=seq,
                              data=json.dumps(ep).encode())
            meta[node] = json.dumps({'period_ns': tr['period_ns'], 'dropped': tr['dropped'],
                                     'clk_tck': tr['clk_tck'], 'shares': tr['shares']})
        w.add_metadata(_METADATA, meta)
        w.finish()
    os.replace(tmp, path)


def read_trace(path) -> dict:
    """``{node: {'period_ns', 'dropped', 'clk_tck', 'shares', 'ticks': {column: array},
    'episodes': [dict]}}`` from a trace written by :func:`write_trace`.

    Raises
    ------
    ValueError
        Naming the file, when it is not an MCAP timing trace.
    """
    from mcap.reader import make_reader
    out: dict = {}
    rows: dict = {}
    try:
        with open(path, 'rb') as f:
            reader = make_reader(f)
            for record in reader.iter_metadata():
                if record.name == _METADATA:
                    for node, text in record.metadata.items():
                        out[node] = dict(json.loads(text), episodes=[])
            f.seek(0)
            for _, channel, message in make_reader(f).iter_messages():
                if channel.topic.startswith(TRACE_TOPIC):
                    rows.setdefault(channel.topic[len(TRACE_TOPIC):], []).append(
                        json.loads(message.data))
                elif channel.topic.startswith(EPISODES_TOPIC):
                    node = channel.topic[len(EPISODES_TOPIC):]
                    out.setdefault(node, {'episodes': []})['episodes'].append(
                        json.loads(message.data))
    except Exception as exc:  # the mcap reader raises several types for a bad file
        raise ValueError(f'{path}: not a readable timing trace ({exc})') from None
    if not out:
        raise ValueError(f'{path}: no {_METADATA} metadata: not a timing trace')
    for node, tr in out.items():
        r = rows.get(node, [])
        tr['ticks'] = {c: np.array([x[c] for x in r], np.int64) for c in TRACE_COLUMNS}
    return out
