"""Sweeps: many cases of a procedure over plant parameters, models and seeds, run on Dask
distributed (or in this process), written as a Parquet dataset one row per case.

* :mod:`.spec`: the spec (YAML or a mapping), checked whole before anything runs, and its
  points and cases (ids hash the inputs);
* :mod:`.procedures`: what runs at a point (closed-loop scenario, pre-flight check, valve
  test) and the metrics of each case;
* :mod:`.engine`: batches on a LocalCluster, a remote scheduler or a plain loop; atomic
  per-batch files, resume, worker deaths, Ctrl-C;
* :mod:`.dataset`: the files and their schema; :mod:`.report`: table and plots;
* :mod:`.cli`: ``eha-sweep``.

Physics only: nothing here imports rclpy or torch.
"""

from .dataset import SweepError, read_dataset
from .engine import SweepInterrupted, run_sweep
from .spec import Spec, SpecError, load_spec, parse_spec

__all__ = ['Spec', 'SpecError', 'SweepError', 'SweepInterrupted', 'load_spec', 'parse_spec',
           'read_dataset', 'run_sweep']
