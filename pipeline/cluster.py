"""Shots and study variants as Dask tasks on worker processes (``--executor dask``).

One task per shot (a config, or one variant of a study) runs that shot's whole-run stages, the
simulation above all, in a worker process; its per-frame stages fan out from there to the same cluster
(executors.WorkerDaskExecutor). Shots sharing upstream stages compute them once: the cache's per-key lock
decides, whichever worker gets there first, and the others find the finished entry. A worker that dies
mid-task loses nothing committed: the scheduler runs the task again on another worker, whose run sweeps
the dead writer's temporary folder (pipeline.cache owner tags), so the cache never holds a partial entry.

Without a scheduler address: a LocalCluster of ``workers`` processes, one task thread each, the cores
shared out as numba threads. A task asks for the worker resources ``threads`` (the largest ``threads``
parameter of its stages, else 1) and ``memory`` (the plan's peak estimate, pipeline.estimate) when the
cluster's workers declare them (``dask worker --resources "threads=8,memory=64e9"``), so Dask places it;
a cluster whose workers declare none places tasks freely.
"""
from __future__ import annotations

import logging
import os
import re
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from .errors import PipelineError

log = logging.getLogger("pipeline")
TOPIC = "pipeline-progress"


@dataclass
class Task:
    label: str
    fn: Callable[..., Any]  # fn(args, executor=..., events=...) -> a picklable value
    args: Any
    resources: dict[str, float]


@dataclass
class Outcome:
    label: str
    value: Any = None
    error: str | None = None  # one line
    exit_code: int = 0
    seconds: float = 0.0


def connect(scheduler: str | None, workers: int = 1):
    """A client of the cluster at ``scheduler``, or of a new LocalCluster of worker processes."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise PipelineError("--executor dask needs the dask extra: pip install 'fluid-pipeline[dask]'") from None
    # the scheduler and nanny of a LocalCluster log to this process: their INFO lines are not ours
    logging.getLogger("distributed").setLevel(max(logging.WARNING, logging.getLogger("distributed").level))
    if scheduler:
        try:
            return Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise PipelineError(f"--scheduler {scheduler}: cannot connect ({e})") from None
    from .memory import available_memory

    workers = max(1, int(workers))
    threads = max(1, (os.cpu_count() or 1) // workers)
    memory = (available_memory() or 0) // workers
    resources = {"threads": threads, **({"memory": memory} if memory else {})}
    # memory_limit=0: the nanny would otherwise kill a worker whose simulation passes its share of the
    # memory; placement by the plan's memory estimate (the "memory" resource) is what keeps them apart
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, resources=resources,
                           memory_limit=0,
                           # CRITICAL: a worker's "failed to communicate with scheduler during heartbeat" traceback,
                           # when Ctrl-C closes the scheduler first, broke the interrupt's one line (a task's own
                           # failure reaches the run through its future, not through these logs)
                           dashboard_address=":0", silence_logs=logging.CRITICAL,
                           env={"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads),
                                "NUMBA_THREADING_LAYER": os.environ.get("NUMBA_THREADING_LAYER", "omp")})
    return Client(cluster)


def close(client) -> None:
    """Close the client, and the LocalCluster if it made one."""
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()


def shot_resources(config_path: str | Path, overrides: tuple[str, ...] = (),
                   cache_dir: str | Path | None = None) -> dict[str, float]:
    """What a shot asks of a worker: numba threads and its estimated peak memory (bytes). A config that
    does not load asks for nothing: its task reports the mistake in one line."""
    from .cache import Cache
    from .config import load_config
    from .estimate import plan_size
    from .graph import build_graph
    from .keys import plan
    from .registry import Registry
    from .runner import default_cache_dir

    try:
        config = load_config(config_path, Registry.from_entry_points(), overrides)
        graph = build_graph(config)
        p = plan(config, graph, Cache(Path(cache_dir) if cache_dir else default_cache_dir(config)))
        sizes = plan_size(p)
    except (PipelineError, OSError):
        return {}
    threads = max([getattr(n.params, "threads", None) or 1 for n in graph.nodes.values()] or [1])
    memory = max([e.get("memory_bytes", 0.0) for e in sizes.values()] or [0.0])
    return {"threads": float(threads), **({"memory": float(memory)} if memory else {})}


def fit_resources(client, wanted: dict[str, float], label: str = "") -> dict[str, float]:
    """Keep the resources some worker declares, at most the largest amount one offers (asking for more
    than any worker has would wait forever)."""
    offered = [w.get("resources") or {} for w in client.scheduler_info(n_workers=-1)["workers"].values()]
    out: dict[str, float] = {}
    for name, amount in wanted.items():
        have = [float(r[name]) for r in offered if name in r]
        if amount > 0 and have:
            if amount > max(have):
                log.warning("%s: asks for %s %.3g but the largest worker offers %.3g; placed there",
                            label, name, amount, max(have))
            out[name] = min(amount, max(have))
    return out


def _on_worker(fn: Callable[..., Any], args: Any, label: str, topic: str | None) -> Outcome:
    """The task: run ``fn`` with the per-frame executor of a worker and progress events to the client."""
    from distributed import get_worker

    from .executors import WorkerDaskExecutor

    emit = None
    if topic is not None:
        worker = get_worker()
        last = [0.0]

        def emit(msg: dict) -> None:
            now = time.monotonic()
            if "task" in msg and msg["done"] < msg["total"] and now - last[0] < 0.5:
                return  # at most two progress events a second per shot
            last[0] = now
            worker.log_event(topic, {"label": label, **msg})

        emit({"state": "running", "host": worker.address})
    t0 = time.perf_counter()
    try:
        value = fn(args, executor=WorkerDaskExecutor(), events=emit)
    except PipelineError as e:
        out = Outcome(label, error=" ".join(str(e).split()), exit_code=e.exit_code)
    except Exception as e:  # noqa: BLE001 - one line to the client, whatever it was
        out = Outcome(label, error=f"{type(e).__name__}: {' '.join(str(e).split())}", exit_code=1)
    else:
        out = Outcome(label, value=value)
    out.seconds = time.perf_counter() - t0
    if emit is not None:
        # a study variant's failure comes back as its result (a row of the report), not as an exception
        emit({"state": "failed" if out.error or getattr(out.value, "error", None) else "done"})
    return out


def run_tasks(client, tasks: list[Task], events: Callable[[dict], None] | None = None) -> list[Outcome]:
    """Submit every task, wait for all, and return their outcomes in order; a failed task is an outcome
    with its error line, the others complete. Ctrl-C cancels what has not started."""
    from distributed import wait

    topic = f"{TOPIC}-{uuid.uuid4().hex[:8]}" if events is not None else None
    if topic is not None:
        client.subscribe_topic(topic, lambda event: events(event[1]))
    futures = [client.submit(_on_worker, t.fn, t.args, t.label, topic, pure=False,
                             key=f"shot-{re.sub(r'[^A-Za-z0-9_.-]', '-', t.label)[:80]}-{uuid.uuid4().hex[:8]}",
                             resources=fit_resources(client, t.resources, t.label) or None)
               for t in tasks]
    try:
        wait(futures)
    except BaseException:
        client.cancel(futures)
        raise
    outcomes = []
    for t, fut in zip(tasks, futures):
        if fut.status == "finished":
            outcomes.append(fut.result())
        else:  # the task itself never returned: its workers kept dying (KilledWorker) or it was cancelled
            exc = fut.exception() if fut.status == "error" else None
            outcomes.append(Outcome(t.label, error=f"{type(exc).__name__}: {exc}" if exc else fut.status, exit_code=1))
    if topic is not None:
        client.unsubscribe_topic(topic)
    return outcomes
