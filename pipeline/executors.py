"""Where per-frame jobs run: in this process, on a pool of local worker processes, or on a Dask cluster.

An executor only maps a picklable top-level function over picklable jobs and yields results as they
finish; every job writes its own cache entry (under the key's lock), so the result is the same
whichever executor ran it. Time stepping of one simulation never goes through an executor.
"""
from __future__ import annotations

import logging
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any, Callable, Iterable, Iterator, Protocol


class Executor(Protocol):
    name: str

    def map_unordered(self, fn: Callable[[Any], Any], jobs: Iterable[Any]) -> Iterator[Any]: ...

    def close(self) -> None: ...

    def abort(self) -> None:
        """Stop now (Ctrl-C or a failure): cancel queued jobs and stop running ones without waiting.
        A stopped job leaves at most a temporary folder that the next run sweeps."""


class InlineExecutor:
    name = "inline"

    def map_unordered(self, fn, jobs):
        for job in jobs:
            yield fn(job)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


def exit_with_parent(parent: int) -> None:
    """In a worker process: end it when ``parent``, the process that started it, is gone (killed with
    SIGKILL, or by the OOM killer, it cannot stop its workers; they idled on, 380 MB each, adopted by
    init). The parent's pid comes from the parent: a worker may start after the parent died."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _init_worker(threads: int, parent: int) -> None:
    exit_with_parent(parent)
    # each worker gets its share of the cores for numba, set before numba is imported
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    # Ctrl-C reaches the whole process group: the parent decides and stops the workers (abort), so a
    # worker never dies mid-commit on its own or prints its own traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class ProcessExecutor:
    """A pool of local worker processes (spawned, so numba's thread pools are never forked)."""

    name = "processes"

    def __init__(self, workers: int) -> None:
        self.workers = max(1, int(workers))
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=get_context("spawn"),
                                         initializer=_init_worker, initargs=(threads, os.getpid()))

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

    def abort(self) -> None:
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
        for proc in procs:
            proc.join(timeout=2)
            if proc.is_alive():
                proc.kill()


class DaskExecutor:
    """Jobs on a Dask distributed cluster (``--executor dask --scheduler tcp://host:8786``); the cache
    folder must be on a filesystem every worker sees. Needs the ``dask`` extra."""

    name = "dask"

    def __init__(self, scheduler: str | None, workers: int = 1) -> None:
        from .cluster import connect

        # without a scheduler: a LocalCluster of ``workers`` processes (as --workers says), so Ctrl-C can
        # stop a running job by ending its process (threads of this process could not be stopped)
        self._client = connect(scheduler, workers)

    def map_unordered(self, fn, jobs):
        from distributed import as_completed as dask_completed

        futures = self._client.map(fn, list(jobs), pure=False)
        self._futures = futures
        try:
            for fut in dask_completed(futures):
                yield fut.result()
        finally:
            self._client.cancel([f for f in futures if not f.done()])

    def close(self) -> None:
        from .cluster import close

        close(self._client)

    def abort(self) -> None:
        # nothing else is started; on a remote cluster a task already running finishes (Dask cannot stop
        # it) and commits a valid entry under its key's lock; a LocalCluster's workers are ended with it
        # (their unfinished entries are temporary folders, swept by the next run)
        cluster = getattr(self._client, "cluster", None)
        # the nanny's notes on the worker processes it is told to end ("exit status was already read") are
        # the expected end of an interrupted run, not news for the user
        logging.getLogger("distributed").setLevel(logging.ERROR)
        try:
            self._client.cancel(getattr(self, "_futures", []))
            self._client.close(timeout=2)
        except Exception:  # noqa: BLE001 - stopping: a slow or dead scheduler must not turn Ctrl-C into a failure
            pass
        if cluster is not None:
            try:
                cluster.close(timeout=2)
            except Exception:  # noqa: BLE001 - as above
                pass


class WorkerDaskExecutor:
    """Per-frame jobs of a shot that itself runs as a Dask task (pipeline.cluster): the frames fan out to
    the same cluster, and the shot's task secedes from its worker's thread while they run so that the
    worker can take frames (or another shot) meanwhile. Used from the task's own thread only."""

    name = "dask-worker"

    def map_unordered(self, fn, jobs):
        from distributed import as_completed as dask_completed, worker_client

        with worker_client() as client:
            futures = client.map(fn, list(jobs), pure=False)
            try:
                for fut in dask_completed(futures):
                    yield fut.result()
            finally:
                client.cancel([f for f in futures if not f.done()])

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


def make_executor(kind: str, workers: int = 1, scheduler: str | None = None) -> Executor:
    if kind == "dask":
        return DaskExecutor(scheduler, workers)
    if kind == "processes" or (kind == "auto" and workers > 1):
        return ProcessExecutor(workers)
    return InlineExecutor()
