"""Launch-free harness: start the node graph, run a scenario to completion, stop every node
cleanly and return what was published.

Two ways to start the graph:

* ``processes=True`` - each node is its installed console script in its own process (as
  ``ros2 run`` would start it), with ``--ros-args -p name:=value`` parameters;
* ``processes=False`` - all nodes in this process on one executor.

Either way a collector node in this process records ``/eha/state``, ``/eha/command``,
``/eha/servovalve_command``, ``/eha/health``, ``/diagnostics`` and ``/eha/events``, and counts
what the publishers' sequence numbers say it missed.  The graph starts only when every node's
endpoints, the collector's included, have matched their peers (the start-up handshake,
:mod:`eha_ros.nodes.handshake`).  Example::

    from eha_ros.harness import GraphConfig, GraphRun, run_graph
    result = run_graph(GraphConfig(scenario='step_0p1', model='hf', mode='lockstep'))
    result.state['jack_position_m']
    with GraphRun(GraphConfig(scenario='step_0p1')) as run:  # the same in steps
        run.pids             # {node: pid} of the node processes
        result = run.wait()  # the nodes are stopped, the recording (if any) complete

Modules: :mod:`.config` (what a run is), :mod:`.result` (what it returned), :mod:`.collector`
(the harness's node), :mod:`.supervisor` (starting, watching and stopping the nodes).  In the
tests, the ``eha_graph`` fixture (``test/conftest.py``) does the same in an isolated domain.
"""

from .collector import Collector
from .config import (COLLECTOR, declared_parameters, GraphConfig, GraphConfigError, GraphError,
                     rt_pinning_warning)
from .result import GraphDataLoss, GraphFault, GraphResult, missing_ticks
from .supervisor import GraphRun, run_graph

__all__ = ['GraphConfig', 'GraphResult', 'GraphError', 'GraphConfigError', 'GraphDataLoss',
           'GraphFault', 'GraphRun', 'run_graph', 'declared_parameters', 'COLLECTOR',
           'rt_pinning_warning', 'missing_ticks', 'Collector']
