"""Where per-frame jobs run: in this process, on a pool of local worker processes, or on a Dask cluster.

An executor only maps a picklable top-level function over picklable jobs and yields results as they
finish; every job writes its own cache entry (under the key's lock), so the result is the same
whichever executor ran it. Time stepping of one simulation never goes through an executor.
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any, Callable, Iterable, Iterator, Protocol


class Executor(Protocol):
    name: str

    def map_unordered(self, fn: Callable[[Any], Any], jobs: Iterable[Any]) -> Iterator[Any]: ...

    def close(self) -> None: ...


class InlineExecutor:
    name = "inline"

    def map_unordered(self, fn, jobs):
        for job in jobs:
            yield fn(job)

    def close(self) -> None:
        pass


def _init_worker(threads: int) -> None:
    # each worker gets its share of the cores for numba, set before numba is imported
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))


class ProcessExecutor:
    """A pool of local worker processes (spawned, so numba's thread pools are never forked)."""

    name = "processes"

    def __init__(self, workers: int) -> None:
        self.workers = max(1, int(workers))
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=get_context("spawn"),
                                         initializer=_init_worker, initargs=(threads,))

    def map_unordered(self, fn, jobs):
        futures = [self._pool.submit(fn, job) for job in jobs]
        try:
            for fut in as_completed(futures):
                yield fut.result()
        finally:
            for fut in futures:
                fut.cancel()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor:
    """Jobs on a Dask distributed cluster (``--executor dask --scheduler tcp://host:8786``); the cache
    folder must be on a filesystem every worker sees. Needs the ``dask`` extra."""

    name = "dask"

    def __init__(self, scheduler: str | None) -> None:
        try:
            from distributed import Client
        except ImportError:
            from .errors import PipelineError

            raise PipelineError("--executor dask needs the dask extra: pip install 'fluid-pipeline[dask]'") from None
        self._client = Client(scheduler) if scheduler else Client(processes=False)

    def map_unordered(self, fn, jobs):
        from distributed import as_completed as dask_completed

        futures = self._client.map(fn, list(jobs), pure=False)
        for fut in dask_completed(futures):
            yield fut.result()

    def close(self) -> None:
        self._client.close()


def make_executor(kind: str, workers: int = 1, scheduler: str | None = None) -> Executor:
    if kind == "dask":
        return DaskExecutor(scheduler)
    if kind == "processes" or (kind == "auto" and workers > 1):
        return ProcessExecutor(workers)
    return InlineExecutor()
