"""Run a sweep's cases in batches on Dask distributed (or in this process) into its dataset.

Engines, the same dataset from each (timing and placement columns aside):

* ``in_process``: a plain loop here, batch after batch (no Dask);
* a ``LocalCluster`` of ``workers`` single-threaded worker processes, started and stopped here
  (the kernels are single-threaded numba; each worker compiles the closed-loop kernel once and
  loads the blocks it calls from numba's on-disk cache);
* an existing cluster at ``scheduler`` (``tcp://HOST:8786``: ``dask scheduler`` and ``dask
  worker``, dask-jobqueue, Kubernetes); its workers need this package installed.

The client forms the batches (points in their fixed order, sized by time: :class:`Batcher`),
keeps two per worker thread in flight, and writes each finished batch as its own Parquet
file, atomically
(:func:`.dataset.write_batch`).  A worker that dies takes its running batch with it; the
scheduler runs that batch again elsewhere, and the client writes every batch once, when its
result arrives: no case is lost or written twice.  A batch that kills its worker
``distributed.scheduler.allowed-failures`` + 1 times (3 + 1 by default) is written as rows of
status ``error``.  Ctrl-C (or any exception) cancels what is running, keeps every written
batch, and :class:`SweepInterrupted` carries the counts; ``resume`` skips the cases already
in the folder.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import signal
import sys
import time
from pathlib import Path

from .dataset import SPEC_FILE, SweepError, done_case_ids, parts, schema, write_batch
from .spec import Spec, parse_spec

__all__ = ['run_sweep', 'run_batch', 'cluster', 'warm_up', 'worker_procedure', 'SweepInterrupted',
           'Batcher', 'Progress']

_WORKER_SPECS = {}


class SweepInterrupted(KeyboardInterrupt):
    """The sweep stopped before its end; ``summary`` says what is on disk."""

    def __init__(self, summary: dict):
        super().__init__('sweep interrupted')
        self.summary = summary


def _worker_name() -> str:
    try:
        from distributed import get_worker
        return str(get_worker().address)
    except (ImportError, ValueError):
        return 'local'


def worker_procedure(raw: dict, base: dict):
    """The procedure of the spec ``raw`` over ``base`` as a worker runs it (parsed once per
    process and spec)."""
    import json
    key = json.dumps([raw, base], sort_keys=True, default=str)
    proc = _WORKER_SPECS.get(key)
    if proc is None:
        proc = parse_spec(raw, check=False, base=base).proc
        _WORKER_SPECS.clear()
        _WORKER_SPECS[key] = proc
    return proc


def run_batch(raw: dict, base: dict, points: list) -> list:
    """Rows of every case of ``points`` (the task a worker runs)."""
    proc = worker_procedure(raw, base)
    spec = proc.spec
    worker = _worker_name()
    rows = []
    for pt in points:
        for row in proc.run_point(pt):
            row.update(point_id=pt.point_id, seed=pt.seed, procedure=spec.procedure,
                       scenario=pt.scenario, noise=spec.noise, worker=worker, **pt.inputs)
            rows.append(row)
    return rows


def warm_up(raw: dict, base: dict) -> str:
    """Load every model of the spec and compile its kernels, so that timing columns leave
    JIT compilation out."""
    worker_procedure(raw, base).warm_up()
    return _worker_name()


class Batcher:
    """Points into batches sized by time: about ``target_s`` of work each, from the mean wall
    time of the points finished so far (one point per batch until one has finished), never
    more than ``max_points``, and smaller towards the end so that the last batches spread
    over every worker (the sweep's tail waits on one short batch, not a long one).  A fixed
    ``size`` overrides the sizing.  A batch is also what Ctrl-C or a dying worker costs."""

    def __init__(self, points, size: int | None = None, target_s: float = 2.0,
                 max_points: int = 32):
        self.pending = list(reversed(points))
        self.size = size
        self.target_s = target_s
        self.max_points = max_points
        self._wall = 0.0
        self._n = 0
        self.batches = 0

    def __bool__(self) -> bool:
        return bool(self.pending)

    def record(self, rows: list) -> None:
        """Learn from a finished batch's rows (``wall_point_s`` per point)."""
        per_point = {r['point_id']: r.get('wall_point_s') for r in rows}
        for w in per_point.values():
            if w is not None:
                self._wall += w
                self._n += 1

    def next(self, workers: int) -> list:
        if self.size:
            n = self.size
        elif not self._n:
            n = 1
        else:
            mean = self._wall / self._n
            n = max(1, min(self.max_points, int(self.target_s / max(mean, 1e-6))))
            n = min(n, max(1, len(self.pending) // (2 * max(workers, 1))))
        self.batches += 1
        return [self.pending.pop() for _ in range(min(n, len(self.pending)))]


class Progress:
    """Cases done, cases per second, ETA and failures, on one line (stderr)."""

    def __init__(self, total: int, stream=None, every_s: float = 0.5):
        self.total = total
        self.done = 0
        self.failed = 0
        self.t0 = time.monotonic()
        self.stream = stream if stream is not None else sys.stderr
        self.tty = hasattr(self.stream, 'isatty') and self.stream.isatty()
        self.every_s = every_s if self.tty else 10.0
        self._last = -math.inf

    def update(self, rows: list) -> None:
        self.done += len(rows)
        self.failed += sum(1 for r in rows if r['status'] != 'ok')
        now = time.monotonic()
        if now - self._last >= self.every_s or self.done >= self.total:
            self._last = now
            self.show()

    def line(self) -> str:
        el = time.monotonic() - self.t0
        rate = self.done / el if el > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else math.inf
        width = 24
        fill = int(width * self.done / self.total) if self.total else width
        eta_s = f'{eta:5.0f} s' if math.isfinite(eta) else '    ? s'
        return (f'[{"#" * fill}{"." * (width - fill)}] {self.done}/{self.total} cases, '
                f'{rate:6.2f} cases/s, ETA {eta_s}, {self.failed} failed')

    def show(self) -> None:
        end = '\r' if self.tty and self.done < self.total else '\n'
        print(self.line(), end=end, file=self.stream, flush=True)


def _prepare_folder(out: Path, spec: Spec, resume: bool) -> None:
    import yaml
    spec_path = out / SPEC_FILE
    if out.exists() and not out.is_dir():
        raise SweepError(f'--out {out} exists and is not a folder')
    if resume:
        if not spec_path.is_file():
            raise SweepError(f'--resume: {out} holds no sweep ({SPEC_FILE} missing)')
        try:
            stored = yaml.safe_load(spec_path.read_text())
        except (OSError, yaml.YAMLError):
            raise SweepError(f'--resume: {spec_path} is unreadable') from None
        if stored != {'spec': spec.canonical(), 'base': spec.base}:
            raise SweepError(f'--resume: {out} holds a sweep of another spec (or other nominal '
                             'parameters); resume with the spec it was started with')
        for tmp in out.glob('.part-*.tmp'):  # a batch cut off while being written
            tmp.unlink()
        return
    if out.exists() and any(out.iterdir()):
        raise SweepError(f'--out {out} is not empty: use --resume to continue the sweep in it, '
                         'or another folder (nothing is overwritten)')
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f'.{SPEC_FILE}.tmp'
    tmp.write_text(yaml.safe_dump({'spec': spec.canonical(), 'base': spec.base},
                                  sort_keys=False))
    os.replace(tmp, spec_path)


def _client(workers: int, scheduler: str | None):
    """``(client, cluster or None)``: connected to ``scheduler``, or to a LocalCluster of
    ``workers`` single-threaded processes started here."""
    from distributed import Client, LocalCluster
    if scheduler:
        try:
            return Client(scheduler, timeout='10s'), None
        except (OSError, TimeoutError) as exc:
            raise SweepError(f'--scheduler {scheduler}: cannot connect ({exc})') from None
    # single-threaded workers: numba and BLAS pools of one thread in each process, set in the
    # workers only (the nannies' env), never in this process: numba here may have started its
    # pool already, and a changed NUMBA_NUM_THREADS would fail its next compilation
    one = {var: os.environ.get(var, '1') for var in (
        'NUMBA_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')}
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=':0', silence_logs=40, env=one)
    return Client(cluster), cluster


def run_sweep(spec: Spec, out, workers: int | None = None, scheduler: str | None = None,
              in_process: bool = False, resume: bool = False, batch_size: int | None = None,
              progress: bool | Progress = True, warm: bool = False, client=None) -> dict:
    """Run every case of ``spec`` not yet in ``out``; returns the summary (counts, wall time,
    engine).  Raises :class:`SweepInterrupted` on Ctrl-C, with every finished batch on disk.

    ``workers``: LocalCluster size (default: the cores of this machine); ``scheduler``: an
    existing cluster instead; ``client``: a connected ``distributed.Client`` to use (left
    open); ``in_process``: no Dask.  A LocalCluster starts its workers as fresh processes
    (spawn), which import the calling script's main module again: a script that calls this
    must do so under ``if __name__ == '__main__':``, as with :mod:`multiprocessing`.
    ``warm``: compile and load every model on every worker before the cases (timing columns
    without JIT).
    """
    out = Path(out)
    _prepare_folder(out, spec, resume)
    sch = schema(spec.proc.columns())
    points = spec.points()
    n_cases = sum(len(p.cases) for p in points)
    done = done_case_ids(out) if resume else set()
    todo = [p for p in points if any(c.case_id not in done for c in p.cases)]
    n_todo = sum(1 for p in todo for c in p.cases if c.case_id not in done)
    workers = int(workers or os.cpu_count() or 1)
    if workers < 1:
        raise SweepError(f'--workers {workers} must be at least 1')
    batches = Batcher(todo, batch_size)
    if client is not None:
        engine = f'client {client.scheduler.address}'
    elif in_process:
        engine = 'in-process'
    else:
        engine = f'scheduler {scheduler}' if scheduler else f'LocalCluster of {workers} workers'
    summary = {'out': str(out), 'cases': n_cases, 'points': len(points),
               'already_done': n_cases - n_todo, 'ran': 0, 'ok': 0, 'diverged': 0, 'error': 0,
               'batches': 0, 'batch_size': batch_size or 'by time', 'engine': engine,
               'wall_s': None, 'interrupted': False}
    bar = progress if isinstance(progress, Progress) else (Progress(n_todo) if progress
                                                           else None)
    raw, base = spec.canonical(), spec.base
    t0 = time.monotonic()

    def finished(batch, rows):
        rows = [r for r in rows if r['case_id'] not in done]
        for r in rows:  # rows a worker never made (KilledWorker) lack the point's fields
            r.setdefault('procedure', spec.procedure)
            r.setdefault('noise', spec.noise)
        # a batch's file and its count go together: Ctrl-C waits until both are done (else
        # the summary of an interrupted sweep could leave out a batch already on disk)
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            write_batch(out, rows, sch, batch[0].index)
            batches.record(rows)
            for r in rows:
                summary[r['status']] = summary.get(r['status'], 0) + 1
            summary['ran'] += len(rows)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        if bar is not None:
            bar.update(rows)

    try:
        if in_process:
            if warm and batches:
                warm_up(raw, base)
            while batches:
                b = batches.next(1)
                finished(b, run_batch(raw, base, b))
        elif batches:
            with (cluster(workers, scheduler) if client is None
                  else contextlib.nullcontext(client)) as dask:
                if importlib.util.find_spec('bokeh') is not None:  # the dashboard needs it
                    print(f'eha-sweep: dashboard {dask.dashboard_link}', file=sys.stderr,
                          flush=True)
                if warm:
                    dask.run(warm_up, raw, base)
                _run_dask(dask, raw, base, batches, finished)
    except BaseException as exc:
        summary['interrupted'] = True
        if bar is not None and bar.tty:
            print(file=bar.stream)
        if isinstance(exc, KeyboardInterrupt):
            raise SweepInterrupted(summary) from None
        raise
    finally:
        summary['batches'] = batches.batches
        summary['wall_s'] = round(time.monotonic() - t0, 3)
    summary['files'] = len(parts(out))
    return summary


def _run_dask(client, raw, base, batches: Batcher, finished) -> None:
    """Keep two batches per worker thread in flight, each sized when it is submitted."""
    import hashlib

    from distributed import as_completed
    from distributed.scheduler import KilledWorker
    futures = {}

    def threads() -> int:
        return max(1, sum(client.nthreads().values()))

    def submit():
        b = batches.next(threads())
        key = 'eha-sweep-' + hashlib.sha256('.'.join(p.point_id for p in b).encode()) \
            .hexdigest()[:16]
        fut = client.submit(run_batch, raw, base, b, key=key, pure=False)
        futures[fut] = b
        return fut

    ac = as_completed([submit() for _ in range(2 * threads()) if batches])
    try:
        for fut in ac:
            b = futures.pop(fut)
            try:
                rows = fut.result()
            except KilledWorker as exc:  # the batch killed every worker it ran on
                rows = [{'case_id': c.case_id, 'point_id': p.point_id, 'model': c.model,
                         'dt_s': c.dt_s, 'seed': p.seed, 'scenario': p.scenario,
                         'status': 'error',
                         'error': f'KilledWorker: {exc}', **p.inputs}
                        for p in b for c in p.cases]
            finished(b, rows)
            while batches and len(futures) < 2 * threads():
                ac.add(submit())
    finally:
        if futures:
            client.cancel(list(futures))


@contextlib.contextmanager
def cluster(workers: int | None = None, scheduler: str | None = None):
    """``with cluster(workers) as client:`` a ``distributed.Client`` for :func:`run_sweep`'s
    ``client``: connected to ``scheduler``, or to a LocalCluster of ``workers`` (default: the
    cores of this machine) single-threaded processes started here and closed on leaving."""
    client, local = _client(int(workers or os.cpu_count() or 1), scheduler)
    try:
        yield client
    finally:
        _close(client, local)


def _close(client, cluster) -> None:
    for what in (client, cluster):
        if what is not None:
            with contextlib.suppress(Exception):  # best effort: the results are on disk
                what.close(timeout=10)
