"""Shared fixtures.

The tests run against the installed ``eha_ros`` (``make test`` installs it into ``.venv`` and runs
``.venv/bin/pytest`` with ``--import-mode=importlib``): only the installed package carries the
generated ``eha_ros.msg``.
"""

import os

import pytest

from eha_ros.harness import GraphConfig, run_graph
from eha_ros.isolation import ros_environment

# Type and range checks on message field assignment. The generated message modules read this
# when first imported, so it is set before any test imports them.
os.environ.setdefault('ROS_PYTHON_CHECK_FIELDS', '1')


@pytest.fixture
def ros_env(monkeypatch):
    """Environment for ROS 2 nodes with its own ``ROS_DOMAIN_ID`` and temporary ``ROS_LOG_DIR``.

    Yields the environment as a dict (for subprocesses) and also applies it to ``os.environ``
    for nodes created in the test process; ``os.environ`` is restored afterwards.
    """
    with ros_environment() as env:
        for key in set(os.environ) - set(env):
            monkeypatch.delenv(key)
        for key, value in env.items():
            if os.environ.get(key) != value:
                monkeypatch.setenv(key, value)
        yield env


@pytest.fixture
def eha_graph(ros_env):
    """``eha_graph(processes=True, **GraphConfig fields) -> GraphResult``: the node graph
    (:func:`eha_ros.harness.run_graph`) in this test's own ROS domain."""
    def run(processes: bool = True, timeout_s: float = 120.0, **fields):
        return run_graph(GraphConfig(**fields), processes=processes, env=ros_env,
                         timeout_s=timeout_s, log_dir=ros_env.get('ROS_LOG_DIR'))
    return run
