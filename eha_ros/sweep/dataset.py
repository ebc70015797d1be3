"""A sweep's dataset on disk: a folder of Parquet files, one per finished batch.

``DIR/part-<first point>-<batch hash>.parquet`` holds the rows of one batch, written to a
hidden temporary file and renamed (``os.replace``, atomic on one file system) once whole:
a file present is a batch complete.  ``DIR/_spec.yaml`` is the spec the dataset belongs to.
Readers skip names starting with ``_`` or ``.``, so the folder opens as one table with
pyarrow (``pyarrow.parquet.read_table(DIR)``), pandas (``pandas.read_parquet(DIR)``), polars
(``polars.read_parquet(DIR + '/*.parquet')``) or duckdb
(``SELECT * FROM 'DIR/*.parquet'``).

Columns: ``case_id``, ``point_id``, ``status`` (``ok``, ``diverged``, ``error``), ``error``
(the message), ``procedure``, ``scenario``, ``model``, ``dt_s``, ``seed``, ``noise``, the
swept plant parameters under their plant names, the metrics, the kept signals
(``signal_<name>``, lists), then timing and placement: ``wall_s`` (the case's own runs),
``wall_point_s`` (its point's, hf reference included), ``wall_cost_s_per_s`` (wall seconds
per simulated second, scenarios), ``worker``.  Everything but ``wall_*`` and ``worker`` is a
function of the spec alone.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from .errors import SweepError

__all__ = ['SweepError', 'schema', 'write_batch', 'done_case_ids', 'read_dataset',
           'FIXED_COLUMNS', 'TIMING_COLUMNS', 'SPEC_FILE']

SPEC_FILE = '_spec.yaml'
#: The sweep's own columns ahead of a procedure's, and their types (:func:`schema`).
FIXED_COLUMNS = (('case_id', 'string'), ('point_id', 'string'), ('status', 'string'),
                 ('error', 'string'), ('procedure', 'string'), ('scenario', 'string'),
                 ('model', 'string'), ('dt_s', 'float'), ('seed', 'int'), ('noise', 'bool'))
#: Columns that depend on where and how fast a case ran (left out of determinism checks).
TIMING_COLUMNS = ('wall_s', 'wall_point_s', 'wall_cost_s_per_s', 'worker')


def schema(columns):
    """The Arrow schema of a dataset (every batch file has it): the sweep's own columns around
    ``columns``, the ``(name, type)`` a procedure declares
    (:meth:`eha_ros.procedure.Procedure.columns`; type ``float``, ``int``, ``bool``,
    ``string`` or ``floats``, a list of floats)."""
    import pyarrow as pa
    types = {'float': pa.float64(), 'int': pa.int64(), 'bool': pa.bool_(),
             'string': pa.string(), 'floats': pa.list_(pa.float64())}
    timing = [(n, 'string' if n == 'worker' else 'float') for n in TIMING_COLUMNS]
    return pa.schema([(n, types[t]) for n, t in (*FIXED_COLUMNS, *columns, *timing)])


def write_batch(folder: Path, rows: list, sch, first_index: int) -> Path:
    """Write ``rows`` as one Parquet file, atomically; returns its path."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    names = set(sch.names)
    for r in rows:
        extra = set(r) - names
        if extra:  # a metric the schema lacks would be dropped silently: refuse
            raise SweepError(f'row of case {r.get("case_id")} has columns outside the '
                             f'schema: {", ".join(sorted(extra))}')
    values = {f.name: [r.get(f.name) for r in rows] for f in sch}
    # signals (list columns): numpy arrays, one buffer per column
    columns = [_list_array(values[f.name]) if pa.types.is_list(f.type)
               else pa.array(values[f.name], type=f.type) for f in sch]
    table = pa.Table.from_arrays(columns, schema=sch)
    digest = hashlib.sha256('.'.join(r['case_id'] for r in rows).encode()).hexdigest()[:8]
    path = Path(folder) / f'part-{first_index:07d}-{digest}.parquet'
    tmp = Path(folder) / f'.{path.name}.tmp'
    with open(tmp, 'wb') as f:
        pq.write_table(table, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def _list_array(values):
    """A ``list<double>`` column from per-row arrays (``None``: a null)."""
    import numpy as np
    import pyarrow as pa
    arrays = [np.asarray(v, dtype=float).ravel() for v in values if v is not None]
    lengths = [0 if v is None else np.asarray(v).size for v in values]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    flat = np.concatenate(arrays) if arrays else np.zeros(0)
    mask = pa.array([v is None for v in values])
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(flat), mask=mask)


def parts(folder: Path) -> list:
    return sorted(Path(folder).glob('part-*.parquet'))


def done_case_ids(folder: Path) -> set:
    """Ids of the cases already in ``folder``."""
    import pyarrow.parquet as pq
    out = set()
    for f in parts(folder):
        try:
            ids = pq.read_table(f, columns=['case_id']).column('case_id').to_pylist()
        except Exception as exc:
            raise SweepError(f'{f}: not a readable batch of a sweep ({type(exc).__name__}); '
                             'move it away to resume') from None
        dup = out.intersection(ids)
        if dup:
            raise SweepError(f'{f}: case {sorted(dup)[0]} is also in another batch file')
        out.update(ids)
    return out


def read_dataset(folder, drop_timing: bool = False):
    """The whole dataset as a ``pyarrow.Table`` sorted by ``case_id`` (without the timing
    and placement columns with ``drop_timing``)."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    files = parts(Path(folder))
    if not files:
        raise SweepError(f'{folder}: no sweep results (no part-*.parquet)')
    table = pa.concat_tables([pq.read_table(f) for f in files])
    table = table.sort_by('case_id')
    if drop_timing:
        table = table.drop_columns([c for c in TIMING_COLUMNS if c in table.column_names])
    return table
