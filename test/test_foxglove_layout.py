"""The shipped Foxglove layout (``config/foxglove/eha_rig.json``) cannot rot: every panel in its
tree has a configuration and every configuration a place in the tree; every message path it
plots or shows names a topic the graph publishes and, field by field, a field of that topic's
message type (walked through the generated classes); and it is installed with the package.
The checker itself is shown to catch a misspelt topic, field and nested field.
"""

import json
from pathlib import Path
import re
import sys

import pytest

from eha_ros import graph

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / 'config' / 'foxglove' / 'eha_rig.json'
#: What the layout must show (the live view's purpose), as topic.field paths.
REQUIRED = ('/eha/command.position_setpoint_m', '/eha/state.jack_position_m',
            '/eha/state.p12_pa', '/eha/state.p1_pa', '/eha/state.p2_pa',
            '/eha/state.spool_position_m', '/eha/state.coil_current_a',
            '/eha/health.radial_clearance_std_m', '/eha/health.level')


def tree_panels(node) -> list:
    if isinstance(node, str):
        return [node]
    return tree_panels(node['first']) + tree_panels(node['second'])


def message_paths(config) -> list:
    """Every Foxglove message path in a panel configuration (``value`` of plot and state
    paths, ``topicPath``, ``topicToRender``)."""
    out = []
    if isinstance(config, dict):
        for key, value in config.items():
            if key in ('value', 'topicPath', 'topicToRender') and isinstance(value, str):
                out.append(value)
            else:
                out += message_paths(value)
    elif isinstance(config, list):
        for value in config:
            out += message_paths(value)
    return out


def field_types(type_name: str) -> dict:
    """``{field: type}`` of a ROS type (``pkg/msg/Name`` or ``pkg/Name``)."""
    import importlib
    pkg, *_, name = type_name.split('/')
    cls = getattr(importlib.import_module(f'{pkg}.msg'), name)
    return cls.get_fields_and_field_types()


def nested_type(field_type: str):
    """The message type of a field (``sequence<pkg/Name>``, ``pkg/Name[3]``), None for a
    primitive."""
    base = re.sub(r'^sequence<(.*?)(, \d+)?>$', r'\1', field_type)
    base = re.sub(r'\[\d*\]$', '', base)
    return base if '/' in base else None


def check_path(path: str, topics: dict) -> str:
    """Why ``path`` does not name a published topic's field ('' when it does)."""
    path = re.sub(r'\{[^}]*\}', '', path)                 # filters
    path = re.sub(r'\.@\w+$', '', path)                   # modifiers (.@abs, .@derivative)
    topic = next((t for t in sorted(topics, key=len, reverse=True)
                  if path == t or path.startswith(t + '.')), None)
    if topic is None:
        return f'{path}: no graph topic'
    type_name = topics[topic]
    parts = path[len(topic):].split('.')[1:]
    for k, part in enumerate(parts):
        if type_name is None:
            return f'{path}: {parts[k - 1]!r} is a primitive field, it has no fields'
        name = re.sub(r'\[[^\]]*\]$', '', part)           # [0], [:]
        fields = field_types(type_name)
        if name not in fields:
            return f'{path}: {type_name} has no field {name!r}'
        type_name = nested_type(fields[name])
    return ''


def graph_topics() -> dict:
    return dict(graph.TOPICS)


@pytest.fixture(scope='module')
def layout():
    return json.loads(LAYOUT.read_text())


def test_every_panel_in_the_tree_has_a_configuration_and_back(layout):
    placed = tree_panels(layout['layout'])
    assert len(placed) == len(set(placed))
    assert set(placed) == set(layout['configById'])
    for key in ('globalVariables', 'userNodes', 'playbackConfig'):
        assert key in layout


def test_every_message_path_names_a_field_the_graph_publishes(layout):
    paths = message_paths(layout['configById'])
    assert len(paths) >= 15
    problems = [why for p in paths if (why := check_path(p, graph_topics()))]
    assert not problems, problems
    for p in REQUIRED:
        assert p in paths, f'the layout does not show {p}'


@pytest.mark.parametrize('bad', ['/eha/stat.jack_position_m', '/eha/state.jack_position',
                                 '/eha/health.header.stamp.secs', '/eha/events.tick',
                                 '/eha/state.p12_pa.value'])
def test_the_checker_catches_a_misspelling(bad):
    assert check_path(bad, graph_topics())


def test_the_checker_walks_nested_and_array_fields():
    topics = graph_topics()
    for good in ('/eha/health.header.stamp.sec', '/eha/health.parameter_values[0]',
                 '/diagnostics.status[:].level', '/diagnostics.status[0].values[0].key',
                 '/eha/state{status==0}.p12_pa', '/eha/state.p12_pa.@abs'):
        assert check_path(good, topics) == '', good


def test_the_layout_is_installed():
    installed = Path(sys.prefix) / 'share' / 'eha_ros' / 'config' / 'foxglove' / LAYOUT.name
    assert installed.is_file()
    assert json.loads(installed.read_text()) == json.loads(LAYOUT.read_text())
