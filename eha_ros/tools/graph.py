"""``eha-graph``: run one scenario through the node graph from the command line (no ros2 launch).

Examples::

    eha-graph --scenario sine_0p1_5pi --model hf --mode realtime --health --record run.mcap
    eha-graph --scenario step_0p1 --set servovalve_plant.radial_clearance_m=4e-6 --json
    eha-graph --params-file config/graph.yaml --one-process --duration 2
    eha-graph --list                    # the scenarios
    eha-graph --print-params            # every node's parameters and defaults, as graph.yaml

It starts the command generator, the controller, the plant (and with ``--health`` the health
monitor, with ``--record`` the recorder) on the same harness as the tests
(:func:`eha_ros.harness.run_graph`), runs the scenario to its end (or ``--duration``), stops
every node and prints a summary. Ctrl-C (SIGINT) or SIGTERM stops every node the same way,
closes the recording and prints the summary of what ran.

Parameters, lowest precedence first: the nodes' defaults, ``--params-file`` (ROS 2's
``/node: ros__parameters:`` form, e.g. the installed ``config/graph.yaml``; ``/**`` applies to
every node that declares the parameter, and one that no node declares is refused), the
options (``--scenario``, ``--model``, ``--mode``, ``--seed``, ``--rate``, ``--dt``,
``--integrator``), then
``--set node.name=value``. The harness owns the timing and start-up parameters (``mode``,
``use_sim_time``, ``handshake_nodes``, ...): from a params file, ``scenario``, ``model``,
``mode``, ``rate_hz``, ``dt_s``, ``integrator`` and ``seed`` are taken as the options'
defaults.

Events (``--event T:node.parameter=value``, repeatable; a scenario's ``events:``) are handed to
the plant or the controller before the run and take effect at the first tick whose time is at
least T, in both modes; each is published on ``/eha/events`` (and recorded) with its tick.
``--rt`` gives the ticking nodes real-time settings (SCHED_FIFO, locked memory); where the OS
refuses them each node logs one warning and runs on.

The graph starts when every node's endpoints have matched every peer (the start-up
handshake); the summary's times and each node's timing run from that synchronised start, and
discovery is reported beside them. In lockstep the summary shows simulated seconds per wall
second and re-sent ticks.

Exit status: 0 after a complete run; 1 when a node failed (exited early, the plant diverged,
the graph stalled or never completed its start-up handshake, the recorder failed) or the data
are incomplete (a message missing: the summary says which); 2 on bad input (unknown scenario,
model, node or parameter - a misspelt name is refused with the nearest declared ones -, bad
``--set`` or ``--event``, unreadable params file, existing output), one line on stderr; 130
after Ctrl-C/SIGTERM.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path
import sys
import textwrap

import yaml

from eha_ros import graph
from eha_ros.graph import TIMING_SUFFIX

__all__ = ['main', 'parser', 'read_params_file', 'node_defaults', 'defaults_yaml']

PROG = 'eha-graph'

#: Parameters the harness sets itself on every node; a params file or ``--set`` may not.
MANAGED = frozenset(('mode', 'use_sim_time', 'handshake_nodes', 'duration_s', 'output',
                     'valve_test', 'valve_test_flows_m3_s', 'valve_test_procedure',
                     'events'))

#: Params-file entries taken as the options' defaults: ``(node, parameter) -> option``.
PROMOTED = {('command_generator', 'scenario'): 'scenario', ('servovalve_plant', 'model'): 'model',
            ('servovalve_plant', 'mode'): 'mode', ('servovalve_plant', 'rate_hz'): 'rate_hz',
            ('servovalve_plant', 'dt_s'): 'dt_s', ('servovalve_plant', 'seed'): 'seed',
            ('servovalve_plant', 'integrator'): 'integrator'}

#: Parameters rclpy declares on every node that are not the graph's (read-only).
RCLPY_OWN = frozenset(('start_type_description_service',))

#: Nodes eha-graph starts (the recorder too, with ``--record``).
GRAPH_NODES = graph.NODES + ('recorder', 'foxglove_bridge')


class UsageError(ValueError):
    """Bad input: reported on one line, exit status 2."""


# --- parameters -----------------------------------------------------------------------------

def read_params_file(path) -> dict:
    """``{node: {parameter: value}}`` from a ROS 2 params file (``/node: ros__parameters:``).

    ``/**`` (every node) is applied first, then each node's own section; a leading ``/`` on
    the node name is optional. Raises :class:`UsageError` for an unreadable file, a section
    without ``ros__parameters`` or an unknown node.
    """
    try:
        data = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except OSError as exc:
        raise UsageError(f'cannot read params file {path}: {exc.strerror or exc}') from None
    except yaml.YAMLError as exc:
        raise UsageError(f'params file {path} is not YAML: {" ".join(str(exc).split())}') \
            from None
    if not isinstance(data, dict):
        raise UsageError(f'params file {path}: expected /node: ros__parameters: sections')
    common, own = {}, {}
    for key, section in data.items():
        node = str(key).strip('/')
        if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'),
                                                           dict):
            raise UsageError(f'params file {path}: section {key!r} has no ros__parameters')
        values = dict(section['ros__parameters'])
        if node == '**':
            common.update(values)
        elif node in GRAPH_NODES:
            own.setdefault(node, {}).update(values)
        else:
            raise UsageError(f'params file {path}: unknown node {key!r} (nodes: '
                             f'{", ".join(GRAPH_NODES)})')
    # a /** entry applies to the nodes that declare it; one that no node declares is refused
    from eha_ros.harness import declared_parameters
    declared = declared_parameters()
    for name in common:
        if not any(name in declared.get(node, ()) for node in GRAPH_NODES):
            raise UsageError(f'params file {path}: no node declares {name!r} (section /**)')
    out = {}
    for node in GRAPH_NODES:
        shared = {k: v for k, v in common.items() if k in declared.get(node, ())}
        if shared or node in own:
            out[node] = dict(shared, **own.get(node, {}))
    return out


def _value(text: str):
    """A ``--set`` value typed as ROS types ``-p name:=value``: integer, then floating point
    (``4e-6`` too), ``true``/``false``, a ``[...]`` list of these, else a string."""
    text = text.strip()
    for convert in (int, float):
        try:
            return convert(text)
        except ValueError:
            pass
    if text.lower() in ('true', 'false'):
        return text.lower() == 'true'
    if text.startswith('[') and text.endswith(']'):
        return [_value(v) for v in text[1:-1].split(',') if v.strip()]
    return text


def parse_set(items) -> dict:
    """``['node.name=value', ...]`` -> ``{node: {name: value}}``."""
    out: dict = {}
    for item in items or ():
        target, sep, text = item.partition('=')
        node, dot, name = target.partition('.')
        if not sep or not dot or not name:
            raise UsageError(f'--set {item!r}: expected node.parameter=value')
        if node not in GRAPH_NODES:
            raise UsageError(f'--set {item!r}: unknown node {node!r} (nodes: '
                             f'{", ".join(GRAPH_NODES)})')
        out.setdefault(node, {})[name] = _value(text)
    return out


def node_defaults(descriptions: bool = False) -> dict:
    """Every node's declared parameters and defaults: ``{node: {name: value}}`` (with
    ``descriptions``: ``{node: {name: (value, description)}}``), read from the nodes themselves
    (each is built once in a private context, with no output written)."""
    import rclpy

    from eha_ros.harness.supervisor import NODE_CLASSES
    from eha_ros.nodes.foxglove_bridge import FoxgloveBridge
    from eha_ros.nodes.recorder import declare_parameters

    def recorder(**kwargs):  # its declarations alone: a Recorder would create its file
        node = rclpy.create_node('recorder', **kwargs)
        declare_parameters(node)
        return node
    classes = dict(NODE_CLASSES, recorder=recorder, foxglove_bridge=FoxgloveBridge)
    out = {}
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=0)
    try:
        for name, cls in classes.items():
            node = cls(context=context, start_parameter_services=False)
            try:
                out[name] = {}
                for pname in sorted(set(node._parameters) - RCLPY_OWN):
                    value = node.get_parameter(pname).value
                    if isinstance(value, (list, tuple)) or hasattr(value, 'tolist'):
                        value = list(value.tolist() if hasattr(value, 'tolist') else value)
                    desc = node.describe_parameter(pname).description
                    out[name][pname] = (value, desc) if descriptions else value
            finally:
                getattr(node, 'close', lambda: None)()
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    return out


def defaults_yaml() -> str:
    """``config/graph.yaml``: every node's parameters with their defaults and descriptions."""
    lines = [
        '# Every node of the actuator graph with all its parameters and their defaults, in ROS',
        "# 2's params-file form. Generated by `eha-graph --print-params`; a test checks that it",
        '# matches what the nodes declare.',
        '#',
        '#   servovalve_plant --ros-args --params-file config/graph.yaml',
        '#   eha-graph --params-file config/graph.yaml [--set node.name=value]',
        '#',
        '# The physical parameters listed here (wear of the plant, gains of the controller) are',
        '# the values of the installed config/eha_params.yaml; a value given here wins over the',
        "# node's params_file. Units in brackets, SI.",
    ]
    for node, params in node_defaults(descriptions=True).items():
        lines += ['', f'/{node}:', '  ros__parameters:']
        for name, (value, desc) in params.items():
            lines += [f'    # {line}' for line in textwrap.wrap(' '.join(desc.split()), 93)]
            # the value as a YAML flow scalar (whose document ends in '...')
            text = yaml.safe_dump(value, default_flow_style=True, width=1 << 16)
            lines.append(f'    {name}: ' + text.strip().removesuffix('...').strip())
    return '\n'.join(lines) + '\n'


# --- the run ----------------------------------------------------------------------------------

def build_config(args):
    """The :class:`~eha_ros.harness.GraphConfig` of the command line."""
    from eha_ros.harness import GraphConfig
    from eha_ros.physics import get_scenario, ParameterError
    from eha_ros.physics.stability import EXPLICIT, INTEGRATORS

    file_params = read_params_file(args.params_file) if args.params_file else {}
    options = {'scenario': 'step_0p1', 'model': 'hf', 'mode': 'lockstep', 'rate_hz': 1000.0,
               'dt_s': 1e-6, 'seed': 0, 'integrator': EXPLICIT}
    options.update({option: file_params[node][name] for (node, name), option in PROMOTED.items()
                    if name in file_params.get(node, {})})
    options.update({o: getattr(args, o) for o in options if getattr(args, o) is not None})
    # a file's entries for what the harness owns are its defaults: left out
    node_params = {n: {k: v for k, v in values.items()
                       if k not in MANAGED and (n, k) not in PROMOTED}
                   for n, values in file_params.items()}
    for node, values in parse_set(args.set).items():
        for name, value in values.items():
            if (node, name) in PROMOTED:
                options[PROMOTED[node, name]] = value
            elif name in MANAGED:
                raise UsageError(f'{node}.{name} is set by eha-graph itself (use --mode, '
                                 '--duration, --record or a scenario)')
            else:
                node_params.setdefault(node, {})[name] = value
    for option, allowed in (('mode', graph.MODES), ('model', graph.MODELS),
                            ('integrator', INTEGRATORS)):
        if options[option] not in allowed:
            raise UsageError(f'{option} {options[option]!r} must be one of {", ".join(allowed)}')
    try:
        get_scenario(options['scenario'])
    except (ParameterError, KeyError, ValueError) as exc:
        raise UsageError(str(exc).strip('"')) from None
    if args.duration is not None and not args.duration > 0:
        raise UsageError(f'--duration must be > 0 s, got {args.duration}')
    for path in (args.record, args.trace):
        if path and Path(path).exists():
            raise UsageError(f'{path} exists: refusing to overwrite it')
        if path and not Path(path).resolve().parent.is_dir():
            raise UsageError(f'folder of {path} does not exist')
    if args.trace and args.record and Path(args.trace).resolve() == Path(args.record).resolve():
        raise UsageError('--trace and --record name the same file')
    config = GraphConfig(scenario=options['scenario'], model=options['model'],
                         mode=options['mode'], duration_s=args.duration,
                         rate_hz=float(options['rate_hz']), dt_s=float(options['dt_s']),
                         integrator=str(options['integrator']), seed=int(options['seed']),
                         health=args.health,
                         record=args.record or '', events=parse_events(args.event),
                         node_params=node_params, rt=args.rt, trace=args.trace or '',
                         foxglove=args.foxglove or '',
                         handshake_timeout_s=min(float(args.timeout), 600.0))
    # a params file's section of a node that does not run has nothing to apply to
    for wanted, node in ((args.health, 'health_monitor'), (args.record, 'recorder'),
                         (args.foxglove, 'foxglove_bridge')):
        if not wanted:
            config.node_params.pop(node, None)
    try:
        # refuses unknown nodes, parameters and event targets, then a lockstep trace
        config.with_trace_files(config.node_parameters(), Path('.'))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return config


def parse_events(items) -> list:
    """``['T:node.parameter=value', ...]`` -> ``[(T, node, {parameter: value})]``."""
    from eha_ros.physics.events import parse_event
    out = []
    for item in items or ():
        head, colon, rest = item.partition(':')
        target, eq, value = rest.partition('=')
        node, dot, name = target.partition('.')
        if not colon or not eq or not dot or not name.strip():
            raise UsageError(f'--event {item!r}: expected T:node.parameter=value')
        ev = parse_event(f'{head}:{name.strip()}={value}')
        out.append((ev.t_s, node.strip(), ev.as_dict()))
    return out


def summarize(result, processes: bool, recording_info=None) -> dict:
    """The run's summary: what ran, how far, how fast, what arrived, health, recording, events
    and node timing (from the synchronised start; discovery separately)."""
    cfg = result.config
    st = result.state
    ticks = st['tick']
    out = {
        'scenario': cfg.scenario, 'model': cfg.model, 'mode': cfg.mode,
        'layout': 'processes' if processes else 'one-process',
        'complete': not result.interrupted and result.sim_s >= cfg.resolved_duration() - 1e-9,
        'interrupted': result.interrupted,
        'simulated_s': result.sim_s, 'wall_s': result.wall_s,
        'discovery_s': result.discovery_s,
        'states': int(ticks.size),
        'ticks_missing': len(result.missing.get('state', ())),
        'current_commands': int(result.servovalve['current_command_a'].size),
        'messages': dict(result.messages),
        'data_complete': result.complete,
        'data_loss': result.loss_report(),
        'diverged': bool(st['status'].size and st['status'][-1] == graph.STATUS_DIVERGED),
        'fault': result.fault,
        'stopped': result.stopped,
        'stale_command_ticks': result.stale_ticks,
        'safe_action_ticks': int((st['safe_action'] != 0).sum()),
        'events': result.events,
    }
    pace = result.sim_s / result.wall_s if result.wall_s > 0 else None
    if cfg.mode == 'lockstep':
        out.update(simulated_s_per_wall_s=pace, resent_ticks=result.resent_ticks)
    else:
        out['real_time_factor'] = pace
    if ticks.size:
        out['final_jack_position_m'] = float(st['jack_position_m'][-1])
        out['final_command_m'] = float(result.command['position_setpoint_m'][-1]) \
            if result.command['position_setpoint_m'].size else None
    if cfg.health:
        last = result.health[-1] if result.health else None
        out['health'] = None if last is None else {
            'level': graph.LEVEL_NAMES[int(last.level)], 'message': last.message,
            'method': last.method, 'radial_clearance_m': last.radial_clearance_m,
            'radial_clearance_std_m': last.radial_clearance_std_m,
            'overlap_m': last.overlap_m, 'overlap_std_m': last.overlap_std_m,
            'estimates': len(result.health)}
    if recording_info is not None:
        out['recording'] = {'file': cfg.record, 'complete': recording_info.complete,
                            'messages': recording_info.message_counts,
                            'lost': recording_info.lost_messages()}
    timing = {name[:-len(TIMING_SUFFIX)]: d['values'] for name, d in result.diagnostics.items()
              if name.endswith(TIMING_SUFFIX)}
    if timing:
        out['timing'] = timing
    if result.trace is not None:
        out['trace'] = {'file': cfg.trace, 'nodes': result.trace}
    return out


def _print_text(s: dict) -> None:
    state = 'complete' if s['complete'] else ('interrupted' if s['interrupted'] else
                                              'incomplete')
    print(f'{PROG}: {s["scenario"]} model {s["model"]}, {s["mode"]}, {s["layout"]}: {state}')
    if s['mode'] == 'lockstep':
        rate = s['simulated_s_per_wall_s']
        pace = (f' ({rate:.2f} simulated s per wall s, {s["resent_ticks"]} ticks re-sent)'
                if rate else '')
    else:
        rtf = s['real_time_factor']
        pace = f' ({rtf:.3f} x real time)' if rtf else ''
    print(f'  simulated {s["simulated_s"]:.3f} s in {s["wall_s"]:.2f} s wall from the '
          f'synchronised start{pace}; start-up (discovery) {s["discovery_s"]:.2f} s')
    print(f'  {s["states"]} states ({s["ticks_missing"]} ticks missing), '
          f'{s["current_commands"]} current commands'
          + ('; the plant DIVERGED' if s['diverged'] else ''))
    if s['stale_command_ticks'] or s['safe_action_ticks']:
        print(f'  {s["stale_command_ticks"]} ticks ran on a stale current command, '
              f'{s["safe_action_ticks"]} on the command watchdog\'s safe action')
    if not s['data_complete']:
        print(f'  DATA INCOMPLETE: {s["data_loss"]}')
    if 'final_jack_position_m' in s:
        print(f'  jack at {s["final_jack_position_m"] * 1e3:.5f} mm, command '
              f'{(s["final_command_m"] or 0.0) * 1e3:.5f} mm')
    for ev in s['events']:
        print(f'  event ({ev["source"]}) at tick {ev["tick_index"]} on {ev["node"]}: '
              + ', '.join(f'{k}={v:g}' for k, v in ev['changes'].items()))
    if 'health' in s:
        h = s['health']
        if h is None:
            print('  health: no estimate published')
        else:
            print(f'  health [{h["level"]}] {h["message"]} (clearance '
                  f'{h["radial_clearance_m"] * 1e6:.2f} +- {h["radial_clearance_std_m"] * 1e6:.2f}'
                  f' um, overlap {h["overlap_m"] * 1e6:.2f} +- {h["overlap_std_m"] * 1e6:.2f} um,'
                  f' {h["estimates"]} estimates)')
    if 'recording' in s:
        r = s['recording']
        print(f'  recorded {sum(r["messages"].values())} messages to {r["file"]}, '
              f'{sum(r["lost"].values())} lost'
              + ('' if r['complete'] else ' (file INCOMPLETE: run eha-recover)'))
    for node, v in s.get('timing', {}).items():
        if s['mode'] == 'lockstep':
            print(f'  {node}: {v.get("Events since startup")} ticks, '
                  f'{v.get("Simulated s per wall s")} simulated s per wall s, '
                  f'{v.get("Overruns since startup")} overruns, {v.get("Busy (core)")} core')
        else:
            print(f'  {node}: {v.get("Actual frequency (Hz)")} Hz, '
                  f'{v.get("On time since startup (%)")} % on time, '
                  f'{v.get("Late ticks since startup")} late, '
                  f'{v.get("Slipped ticks since startup")} slipped, '
                  f'{v.get("Overruns since startup")} overruns, jitter p99 '
                  f'{v.get("Period jitter p99 since startup (ms)")} ms, '
                  f'{v.get("Busy (core)")} core')
    if 'trace' in s:
        from eha_ros.tickloop import describe_shares
        print(f'  timing trace written to {s["trace"]["file"]}')
        for node, t in s['trace']['nodes'].items():
            if 'missing' in t:
                print(f'  {node} trace: {t["missing"]}')
                continue
            print(f'  {node} trace: {describe_shares(t["shares"])}'
                  + ('' if t['complete'] else f' (INCOMPLETE: {t["dropped"]} ticks not '
                     'recorded)'))


def parser() -> argparse.ArgumentParser:
    """``eha-graph``'s command line."""
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog='Exit status: 0 complete, 1 a node failed, 2 bad input, '
                                        '130 interrupted.')
    ap.add_argument('--scenario', help='named scenario (see --list; default step_0p1)')
    ap.add_argument('--model', help=f'fluid block: {", ".join(graph.MODELS)} (default hf)')
    ap.add_argument('--mode', help='realtime or lockstep (default lockstep)')
    ap.add_argument('--health', action='store_true', help='start the health monitor')
    ap.add_argument('--record', metavar='FILE.mcap', help='record every graph topic to FILE')
    ap.add_argument('--foxglove', nargs='?', const='127.0.0.1:8765', metavar='[HOST:]PORT',
                    help='serve every graph topic live to Foxglove (foxglove_bridge; default '
                         '127.0.0.1:8765): Open connection, ws://localhost:8765')
    ap.add_argument('--set', action='append', metavar='NODE.NAME=VALUE',
                    help='set a node parameter (repeatable), e.g. '
                         'servovalve_plant.radial_clearance_m=4e-6')
    ap.add_argument('--params-file', metavar='YAML',
                    help='ROS 2 params file (/node: ros__parameters:), e.g. config/graph.yaml')
    layout = ap.add_mutually_exclusive_group()
    layout.add_argument('--processes', dest='processes', action='store_true', default=True,
                        help='each node its own process (default)')
    layout.add_argument('--one-process', dest='processes', action='store_false',
                        help='every node in this process on one executor')
    ap.add_argument('--duration', type=float, metavar='S',
                    help='simulated seconds (default: the scenario\'s)')
    ap.add_argument('--seed', type=int, help='seed of the torque-motor noise (default 0)')
    ap.add_argument('--rate', dest='rate_hz', type=float, metavar='HZ',
                    help='tick rate (default 1000)')
    ap.add_argument('--dt', dest='dt_s', type=float, metavar='S',
                    help='plant integration step (default 1e-6)')
    ap.add_argument('--integrator', help='plant integration scheme: explicit (the 1 us '
                    'reference, default) or split (implicit chambers: steps of 10 us and more)')
    ap.add_argument('--event', action='append', metavar='T:NODE.NAME=VALUE',
                    help='change a parameter at simulated time T s (repeatable), applied at '
                         'the first tick at or after T, e.g. '
                         '0.1:servovalve_plant.overlap_supply_m=2.7e-6')
    ap.add_argument('--rt', action='store_true',
                    help='real-time settings for the ticking nodes: SCHED_FIFO priority, '
                         'locked memory (see README: what a rig needs)')
    ap.add_argument('--trace', metavar='FILE.mcap',
                    help='realtime: write a timing trace of every tick of every node with a '
                         'tick loop to FILE (MCAP), each late episode with its cause')
    ap.add_argument('--timeout', type=float, default=60.0, metavar='S',
                    help='give up when the start-up handshake or a state takes longer than '
                         'S seconds (default 60)')
    ap.add_argument('--isolated', action='store_true',
                    help='run in a ROS domain of its own and a temporary log folder')
    ap.add_argument('--json', action='store_true', help='print the summary as one JSON object')
    ap.add_argument('--list', action='store_true', help='list the scenarios and exit')
    ap.add_argument('--print-params', action='store_true',
                    help="print every node's parameters and defaults (config/graph.yaml)")
    return ap


def main(argv=None) -> int:
    """Console script ``eha-graph``; returns the exit status."""
    args = parser().parse_args(argv)

    if args.list:
        from eha_ros.physics import load_scenarios
        for name, sc in sorted(load_scenarios().items()):
            print(f'{name:16s} {sc.waveform:6s} {sc.duration_s:5.2f} s  {sc.description}')
        return 0
    if args.print_params:
        sys.stdout.write(defaults_yaml())
        return 0
    from rclpy.exceptions import ParameterException

    from eha_ros.harness import GraphDataLoss, GraphError, run_graph
    from eha_ros.isolation import ros_environment
    from eha_ros.physics import ParameterError
    from eha_ros.recording.stop import StopRequest

    def fail(exc, status: int) -> int:
        print(f'{PROG}: error: {" ".join(str(exc).split())}', file=sys.stderr)
        return status

    def show(result, recorded: bool) -> dict:
        """Print the summary of ``result`` (with the recording's, where ``recorded``)."""
        from eha_ros.recording.reader import scan
        summary = summarize(result, args.processes, scan(config.record) if recorded else None)
        print(json.dumps(summary, default=float)) if args.json else _print_text(summary)
        return summary

    try:
        config = build_config(args)
    except (UsageError, ParameterError) as exc:
        return fail(exc, 2)

    def started(pids):
        where = ', '.join(f'{n} (pid {p})' for n, p in pids.items()) or 'this process'
        print(f'{PROG}: running {config.scenario} ({config.mode}): {where}; Ctrl-C stops',
              file=sys.stderr, flush=True)

    with ros_environment() if args.isolated else contextlib.nullcontext() as env:
        stop = StopRequest()
        try:
            result = run_graph(config, processes=args.processes, env=env, timeout_s=args.timeout,
                               stop=lambda: stop.requested, on_start=started)
        except GraphDataLoss as exc:  # the run ended, incomplete (or a node failed mid-run):
            show(exc.result, bool(config.record) and Path(config.record).exists())  # what's there
            return fail(exc, 1)  # and fail loudly
        except (ParameterError, ParameterException, ValueError) as exc:
            return fail(exc, 2)        # refused: by a node (GraphConfigError), or in this process
        except GraphError as exc:
            return fail(exc, 130 if stop.requested else 1)
        finally:
            stop.restore()
    summary = show(result, bool(config.record))
    if result.interrupted:
        return 130
    if not result.complete:  # realtime: lockstep raised above
        print(f'{PROG}: error: data incomplete: {result.loss_report()}', file=sys.stderr)
        return 1
    if summary['diverged']:
        print(f'{PROG}: error: the plant diverged at t = {result.sim_s:.6f} s', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
