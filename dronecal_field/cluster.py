"""Dask distributed for the jobs that outgrow one process: the survey, many-run calibration.

Two calls cover both jobs::

    from dronecal_field.cluster import dask_client, map_with_progress

    with dask_client(args.scheduler, args.workers) as client:
        for index, result in map_with_progress(client, work, items, progress=True):
            store(index, result)          # in completion order, as they arrive

``dask_client(None, n)`` starts an in-process ``LocalCluster`` of ``n`` worker
processes (one thread each) and tears it down on exit;
``dask_client("tcp://host:8786")`` connects to a running scheduler and leaves
it running; ``dask_client(None, 0)`` gives ``None``: ``map_with_progress``
then runs the items in this process, one after the other (tests, tiny jobs,
debugging with pdb).

Workers are limited to one numba / BLAS thread each: the engine's numba
kernels otherwise start one thread per core in every worker, and two workers
on two cores then run four threads and go slower than one (measured in
benchmarks/bench_survey.py). Start external workers the same way:
``NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 dask worker tcp://host:8786 --nthreads 1``.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import IO, Any, TypeVar

from dronecal_field.errors import InputError

T = TypeVar("T")
R = TypeVar("R")

# One compute thread per worker process: see the module docstring.
SINGLE_THREAD_ENV: dict[str, str] = {
    "NUMBA_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


def default_workers() -> int:
    """Worker processes for a local cluster: one per core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None, *, timeout_s: float = 30.0) -> Iterator[Any]:
    """A ``distributed.Client`` for the duration of a ``with`` block (or None to run in-process).

    Parameters
    ----------
    scheduler : address of a running scheduler, e.g. ``tcp://10.0.0.5:8786``;
        None starts a local cluster (closed again on exit)
    workers : worker processes of the local cluster (default: one per core);
        0 means no Dask at all (yields None: ``map_with_progress`` runs in this
        process). Ignored with ``scheduler``, whose workers are whatever is running.
    timeout_s : how long to wait for the scheduler to answer, s

    Yields
    ------
    distributed.Client or None
    """
    if workers is not None and workers < 0:
        raise InputError(f"--workers {workers} is negative: give 0 (no Dask) or a number of worker processes")
    if scheduler is None and workers == 0:
        yield None
        return
    import logging

    from distributed import Client, LocalCluster

    if scheduler is not None:
        if "://" not in scheduler:
            raise InputError(f"--scheduler {scheduler!r} has no scheme: write it as tcp://HOST:8786")
        try:
            client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"no Dask scheduler answers at {scheduler} ({exc}): start one with `dask scheduler` or drop --scheduler") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = workers if workers is not None else default_workers()
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=logging.ERROR,
        env=dict(SINGLE_THREAD_ENV),
    )
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def worker_count(client: Any) -> int:
    """Workers a client currently reaches (1 for the in-process runner, ``client=None``)."""
    if client is None:
        return 1
    return len(client.scheduler_info().get("workers", {}))


def run_on_every_worker(client: Any, fn: Callable[[], Any]) -> None:
    """Run ``fn()`` once in every worker now connected (or here, with ``client=None``).

    Used to warm up numba-compiled kernels so the first real tasks are not
    charged the compile (or cache load) time; ``fn`` must be importable by
    the workers (a module-level function).
    """
    if client is None:
        fn()
        return
    client.run(fn)


def map_with_progress(
    client: Any,
    fn: Callable[[T], R],
    items: Iterable[T],
    *,
    total: int | None = None,
    initial: int = 0,
    desc: str = "tasks",
    unit: str = "task",
    weight: Callable[[T], int] | None = None,
    max_in_flight: int | None = None,
    progress: bool | IO[str] = False,
) -> Iterator[tuple[int, R]]:
    """Run ``fn`` on every item, on the cluster, yielding ``(index, result)`` as each finishes.

    Results come in completion order so the caller can store each as it
    arrives (what makes a long job resumable); ``index`` is the item's
    position in ``items``. At most ``max_in_flight`` tasks (default: 4 per
    worker) are submitted at once, so ``items`` may be a long lazy iterable
    and memory stays bounded. A task that raises stops the map: the
    remaining tasks are cancelled and the exception is re-raised here.

    Parameters
    ----------
    client : ``distributed.Client`` or None (run in this process, in order)
    fn : module-level function (workers import it by name), one item -> result
    items : the work
    total : work to do in bar units, for the ETA (default: the items' summed
        weight when ``items`` has a length, else unknown)
    initial : work already done before this call (a resumed job), in bar units
    desc, unit : progress bar label and unit
    weight : bar units of an item, evaluated here (e.g. ``len`` when each
        item is a batch of rows); default 1
    max_in_flight : cap on submitted, unfinished tasks
    progress : False for silence, True for a tqdm bar (rate, ETA) on stderr,
        or an open text stream to draw it on

    Yields
    ------
    (index, result) tuples, one per item
    """
    from tqdm import tqdm

    size = weight or (lambda item: 1)
    if total is None and hasattr(items, "__len__"):
        total = sum(size(item) for item in items)  # type: ignore[union-attr]
    bar_total = None if total is None else initial + total
    stream = progress if (progress is not False and progress is not True) else sys.stderr
    bar = tqdm(
        total=bar_total,
        initial=initial,
        desc=desc,
        unit=unit,
        file=stream,
        disable=progress is False,
        smoothing=0.05,
        dynamic_ncols=True,
        mininterval=0.5,
    )
    try:
        if client is None:
            for index, item in enumerate(items):
                result = fn(item)
                bar.update(size(item))
                yield index, result
            return
        yield from _map_distributed(client, fn, items, max_in_flight, bar, size)
    finally:
        bar.close()


def _map_distributed(client: Any, fn: Callable, items: Iterable, max_in_flight: int | None, bar: Any, size: Callable) -> Iterator[tuple[int, Any]]:
    from distributed import as_completed

    limit = max_in_flight or max(2, 4 * worker_count(client))
    source = iter(enumerate(items))
    index_of: dict[Any, int] = {}
    weight_of: dict[Any, int] = {}
    pending = as_completed()

    def submit_next() -> bool:
        try:
            index, item = next(source)
        except StopIteration:
            return False
        # pure=False: every call is new work; a resubmitted item must not alias a cached result
        future = client.submit(fn, item, pure=False)
        index_of[future] = index
        weight_of[future] = size(item)
        pending.add(future)
        return True

    for _ in range(limit):
        if not submit_next():
            break
    try:
        for future in pending:
            result = future.result()  # re-raises the task's exception
            index = index_of.pop(future)
            bar.update(weight_of.pop(future))
            future.release()
            submit_next()
            yield index, result
    finally:
        # stopped early (error, consumer broke off, interrupt): leave no work behind
        if index_of:
            client.cancel(list(index_of))
