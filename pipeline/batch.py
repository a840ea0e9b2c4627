"""A batch of shots (``pipeline run A.yaml B.yaml ...``): every shot runs, in this process one after
another (per-frame jobs on the chosen executor) or as tasks on a Dask cluster (pipeline.cluster); a
shot that fails is reported in one line and the others complete. Shots share the cache: upstream stages
they have in common are computed once."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from .cluster import Outcome
from .errors import ConfigError, PipelineError


def run_shot(args: dict[str, Any], executor=None, events=None) -> dict[str, Any]:
    """One shot (top level so Dask can send it to a worker); returns how many stages ran and were cached."""
    from . import runner

    args = dict(args)
    report = runner.run(args.pop("config"), executor=executor, events=events, **args)
    ran = sum(1 for s in report.stages if s.status != "cached")
    return {"ran": ran, "cached": len(report.stages) - ran, "out": report.out, "seconds": report.seconds}


def check_shots(configs: list[Path], overrides: tuple[str, ...] = ()) -> None:
    """Before any shot runs: every config loads and its stages take its scene (a malformed one is exit 2 now,
    not after the others' hours), and no two shots publish into the same folder (out/<scene.name>/ beside the config), where
    the later would silently replace the earlier."""
    from .config import load_config
    from .estimate import check_stages
    from .graph import build_graph
    from .registry import Registry
    from .runner import default_out_dir

    registry = Registry.from_entry_points()
    seen: dict[Path, Path] = {}
    for c in configs:
        config = load_config(c, registry, overrides)
        check_stages(config, build_graph(config))
        out = default_out_dir(config).resolve()
        if out in seen:
            raise ConfigError(f"{c}: would publish into {out}, as {seen[out]} does (the same scene.name in the same "
                              "folder); give each shot its own scene.name")
        seen[out] = Path(c)


def run_batch(configs: list[Path], options: dict[str, Any], *, executor: str = "auto", workers: int = 1,
              scheduler: str | None = None, events: Callable[[dict], None] | None = None) -> list[Outcome]:
    """Run every config with the same ``options`` (runner.run keywords); one Outcome per shot, in order.
    Raises ConfigError before running any if ``check_shots`` finds a problem."""
    check_shots(configs, tuple(options.get("overrides", ())))
    labels = [str(c) for c in configs]
    jobs = [{**options, "config": str(c)} for c in configs]
    if executor == "dask":
        from . import cluster

        client = cluster.connect(scheduler, workers)
        try:
            tasks = [cluster.Task(label, run_shot, job, cluster.shot_resources(job["config"], options.get("overrides", ()),
                                                                               options.get("cache_dir")))
                     for label, job in zip(labels, jobs)]
            return cluster.run_tasks(client, tasks, events)
        finally:
            cluster.close(client)
    from .executors import make_executor

    ex = make_executor(executor, workers)
    outcomes = []
    try:
        for label, job in zip(labels, jobs):
            emit = (lambda e, label=label: events({"label": label, **e})) if events else None
            t0 = time.perf_counter()
            try:
                out = Outcome(label, value=run_shot(job, executor=ex, events=emit))
            except PipelineError as e:
                out = Outcome(label, error=" ".join(str(e).split()), exit_code=e.exit_code)
            except Exception as e:  # noqa: BLE001 - one shot's failure is one line; the others go on
                out = Outcome(label, error=f"{type(e).__name__}: {' '.join(str(e).split())}", exit_code=1)
            out.seconds = time.perf_counter() - t0
            if emit:
                emit({"state": "failed" if out.error else "done"})
            outcomes.append(out)
    except BaseException:
        ex.abort()
        raise
    ex.close()
    return outcomes
