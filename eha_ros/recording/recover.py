"""``eha-recover``: rewrite a killed or truncated recording as a complete MCAP file.

Example::

    eha-recover killed.mcap -o recovered.mcap

A recorder killed outright (SIGKILL, power loss, a full disk) leaves a file without its summary
section and footer: the MCAP library's indexed reader and rosbags refuse it. This tool reads
the file sequentially up to its last complete chunk (every message written before the last
flush; the recorder flushes at least every ``flush_interval_s``), and writes a new file with
the same channels, schemas, QoS metadata and messages, plus what the recorder would have
written at close: rosbag2's ``rosbag2`` metadata record, the ``eha_ros`` record with the
messages lost per topic, and the summary, index and footer.

Lost messages: for a topic with one publisher (the graph's 1 kHz topics) they are counted
again from the recorded sequence numbers, to the last recovered message; for a topic with
several publishers (``/diagnostics``) they are the recorder's own count at its last flush (its
``eha_ros_progress`` record). The ``run`` entry of the ``eha_ros`` record says what was
recovered: ``recovered.source``, ``recovered.problem`` (where the original ends),
``recovered.messages`` and how each topic's loss was counted.

The offline tools (``eha-replay``, ``eha-compare``, ``eha-diagnose``) treat a truncated file
one way: they read what it holds with a one-line warning on stderr naming the count of
messages recovered and suggesting ``eha-recover``
(:func:`eha_ros.recording.arrays.load_for_tool`); a damaged file (bad CRC) is refused.

Exit status: 0 after writing the output; 2 when the input is missing or not MCAP, the output
exists, or nothing of the input is readable; one line on stderr.
"""

from __future__ import annotations

import argparse
from itertools import chain
import json
from pathlib import Path
import sys
from typing import Dict, Optional

from eha_ros.recording.definitions import (NotMcapError, PROGRESS_METADATA_NAME,
                                           RecordingError, RUN_METADATA_NAME,
                                           SequenceGapCounter)
from eha_ros.recording.reader import McapReader
from eha_ros.recording.writer import McapWriter

__all__ = ['recover', 'main']

PROG = 'eha-recover'


def _progress(metadata: Dict[str, Dict[str, str]]) -> dict:
    """The recorder's last progress record (or its closing ``eha_ros`` record)."""
    for name in (RUN_METADATA_NAME, PROGRESS_METADATA_NAME):
        record = metadata.get(name)
        if record:
            return {k: json.loads(v) for k, v in record.items()}
    return {}


def recover(source, output, *, overwrite: bool = False) -> dict:
    """Rewrite ``source`` (possibly truncated) as the complete MCAP file ``output``.

    Returns
    -------
    dict
        ``messages`` (recovered, per topic), ``lost`` (per topic), ``source_complete``,
        ``problem`` (why the source ends early, or None), ``chunks`` (read).

    Raises
    ------
    NotMcapError
        If ``source`` is not an MCAP file.
    RecordingError
        If ``source`` cannot be read, or nothing of it (not even a channel) is readable.
    FileExistsError
        If ``output`` exists and ``overwrite`` is false.
    """
    if Path(output).exists() and not overwrite:
        raise FileExistsError(f'{output} exists: refusing to overwrite it')
    try:
        reader = McapReader(source, decode=False, strict=False)
        messages = iter(reader)
        first = next(messages, None)
    except OSError as exc:
        raise RecordingError(f'cannot read {source}: {exc.strerror or exc}') from None
    if first is None and not reader.channels:
        raise RecordingError(f'{source}: nothing readable ({reader.problem or "no channels"})')
    counters: Dict[str, SequenceGapCounter] = {}
    with McapWriter(output, overwrite=overwrite) as writer:
        def register(topic):
            ch = reader.channels[topic]
            writer.add_topic(topic, ch.type_name,
                             offered_qos_profiles=ch.metadata.get('offered_qos_profiles'),
                             topic_type_hash=ch.metadata.get('topic_type_hash', ''),
                             definition=ch.schema_text)
            counters[topic] = SequenceGapCounter()

        for msg in chain([first] if first else [], messages):
            if msg.topic not in counters:
                register(msg.topic)
            writer.write(msg.topic, msg.data, msg.log_time_ns, msg.publish_time_ns,
                         msg.sequence)
            counters[msg.topic].add(msg.sequence or None)
        for topic in reader.channels:
            if topic not in counters:
                register(topic)
        progress = _progress(reader.metadata)
        run = progress.get('run')
        run = dict(run) if isinstance(run, dict) else {}
        publishers = run.get('publishers', progress.get('publishers', {}))
        recorded_lost = progress.get('lost_messages', progress.get('lost', {}))
        lost, how = {}, {}
        for topic, counter in counters.items():
            if reader.complete and topic in recorded_lost:
                lost[topic], how[topic] = int(recorded_lost[topic]), 'recorder, at close'
            elif publishers.get(topic, 1) <= 1 and counter.received:
                lost[topic], how[topic] = counter.lost, 'sequence numbers of the recovered file'
            else:
                lost[topic] = int(recorded_lost.get(topic, 0))
                how[topic] = 'recorder, at its last flush'
        writer.lost_counts = lost
        run['recovered'] = {'source': str(source), 'source_complete': reader.complete,
                            'problem': reader.problem, 'chunks': reader.chunks,
                            'messages': sum(writer.message_counts.values()),
                            'loss_counted_from': how}
        writer.run_info = run
    return {'messages': dict(writer.message_counts), 'lost': lost,
            'source_complete': reader.complete, 'problem': reader.problem, 'chunks': reader.chunks}


def main(argv: Optional[list] = None) -> int:
    """Console script ``eha-recover``; returns the exit status."""
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    ap.add_argument('input', type=Path, help='the killed or truncated recording')
    ap.add_argument('-o', '--output', type=Path, required=True,
                    help='complete MCAP file to write (never overwritten)')
    ap.add_argument('--json', action='store_true', help='print the result as one JSON object')
    args = ap.parse_args(argv)
    if args.input.resolve() == args.output.resolve():
        print(f'{PROG}: error: the output must be a new file, not the input', file=sys.stderr)
        return 2
    try:
        result = recover(args.input, args.output)
    except (RecordingError, NotMcapError, FileExistsError) as exc:
        print(f'{PROG}: error: {" ".join(str(exc).split())}', file=sys.stderr)
        if not isinstance(exc, FileExistsError) and args.output.exists():
            args.output.unlink()  # nothing half-written is left behind
        return 2
    if args.json:
        print(json.dumps(dict(result, output=str(args.output))))
    else:
        total = sum(result['messages'].values())
        state = ('the input was already complete' if result['source_complete']
                 else f'the input ends early: {result["problem"]}')
        print(f'{PROG}: wrote {args.output}: {total} messages on {len(result["messages"])} '
              f'topics, {sum(result["lost"].values())} lost ({state})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
