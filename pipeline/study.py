"""Studies: what accuracy costs in time. A study runs variants of a base config (``--set`` style
overrides, swept as a product or zipped), reads each variant's stage times and the metrics its stages
recorded (a JSON file in an artifact, e.g. the simulate stage's ``meta.json`` ``stats``), and writes a
table (CSV, JSON, Markdown) and accuracy-against-time plots.

```yaml
study_version: 1
name: dam_break_resolution
base: ../dam_break.yaml
mode: product                      # or zip
sweep:
  fluid.spacing: [0.04, 0.03, 0.02]
  simulate.use: [sph, mps]
time: simulate                     # whose wall time is the cost axis
metrics:
  - {name: density_error, file: particles/meta.json, key: stats.summary.density_error_mean}
  - name: surge_front_error          # computed by a function from the variant's output folder
    function: stages.simulate.validation:surge_front_error
    args: {reference: martin_moyce_1952.csv, column_width: 0.25, back_wall: 0.0}
```
Variants run through the normal cache, so re-running a study only computes new variants.

The cost column (``<time>_seconds``) is the ``time`` stage's own wall time without one-off JIT
compilation and without waiting for locks: a stage that declares ``warm_up_run`` (the numba solvers) is
first run once per process on a 2-frame copy of the variant in a throw-away cache (its upstream stages
recomputed there: a cached 2-frame entry would become the real run's resume source), untimed, so every
variant finds its kernels compiled; a stage's own ``Context.warm_up`` is left out as well.
``<time>_cpu_seconds`` beside it is the CPU time of the process that ran the stage (all its threads),
which variants running at the same time on shared cores inflate much less than wall time (but numba
threads spinning at barriers on an oversubscribed machine do count). A cached variant keeps the times of
the run that computed it. A stage that keeps its own account of its work over a resumed or extended shot
(simulate: ``meta.json`` ``stats.wall_seconds``) is charged that instead, fresh or resumed
(``_whole_shot_cost``).

``--executor dask`` runs each variant as a task on Dask worker processes (pipeline.cluster); variants
sharing upstream stages compute them once (the cache's per-key lock).
"""
from __future__ import annotations

import csv
import hashlib
import importlib
import io
import itertools
import json
import os
import re
import shutil
import tempfile
import uuid
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextvars import ContextVar
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .config import OUTPUT_NAMES
from .cache import owner_tag
from .errors import ConfigError, StageFailed
from .executors import exit_with_parent
from .publish import (RECORD, TMP_PREFIX, OutputRefused, changed_file, check_out_dir, publish_file, read_record,
                      read_record_stats, sweep_out_dir)
from .stage import STAGE_KINDS


class Metric(BaseModel):
    """A number read from a variant's outputs: a JSON value (``file`` + ``key``), or computed by a
    validation function (``function: "module:name"``, called as ``fn(out_dir, study_dir=..., **args)``,
    e.g. a surge front compared with an experiment)."""
    model_config = ConfigDict(extra="forbid")
    name: str = Field(pattern=r"^[A-Za-z0-9_]+$")
    file: str | None = Field(None, description="output/relative path of a JSON file, e.g. particles/meta.json")
    key: str | None = Field(None, description="dotted path inside that JSON, e.g. stats.density_error")
    function: str | None = Field(None, pattern=r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$",
                                 description="module:function computing the metric from the variant's output folder")
    args: dict[str, Any] = Field(default_factory=dict, description="keyword arguments of `function`")
    label: str | None = None
    lower_is_better: bool = True

    @model_validator(mode="after")
    def _one_source(self) -> "Metric":
        from_file = self.file is not None or self.key is not None
        if (self.function is not None) == from_file or (from_file and (self.file is None or self.key is None)):
            raise ValueError("a metric needs either file and key, or function")
        return self


class StudyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    study_version: Literal[1]
    # a plain folder name, as scene.name: no '.', '..' or hidden name (the report goes to out/<name>/)
    name: str = Field(pattern=r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$")
    base: str = Field(description="the scene config the variants start from, relative to this file")
    mode: Literal["product", "zip"] = "product"
    sweep: dict[str, list[Any]] = Field(min_length=1, description="override path -> values")
    set: list[str] = Field(default_factory=list, description="overrides applied to every variant")
    outputs: list[str] = Field(default_factory=lambda: ["particles"], description="outputs each variant needs")
    time: str = Field("simulate", description="stage whose wall time is the cost axis")
    metrics: list[Metric] = Field(min_length=1)

    @model_validator(mode="after")
    def _check(self) -> "StudyConfig":
        if self.mode == "zip" and len({len(v) for v in self.sweep.values()}) > 1:
            raise ValueError("mode zip needs every sweep list to have the same length")
        if any(not v for v in self.sweep.values()):
            raise ValueError("every sweep entry needs at least one value")
        if self.time not in STAGE_KINDS:
            raise ValueError(f"time: expected a stage kind ({', '.join(STAGE_KINDS)})")
        for o in self.outputs:
            if o not in OUTPUT_NAMES:
                raise ValueError(f"outputs: unknown output {o!r}")
        return self


@dataclass
class VariantResult:
    overrides: dict[str, Any]
    seconds: float | None  # the time stage's cost: wall seconds without warm-up (see above); None: it failed
    metrics: dict[str, float | None]
    out: str
    cpu_seconds: float | None = 0.0
    error: str | None = None  # one line: the variant failed (a blow-up, a bad value); no cost or metrics
    user_error: bool = False


def load_study(path: Path) -> StudyConfig:
    from .config import _first_error, _parse_yaml

    if not path.is_file():
        raise ConfigError(f"{path}: study file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the study: {e}") from None
    data, lines = _parse_yaml(text, str(path))  # the same safe YAML as configs, with each key's line
    if "config_version" in data and "study_version" not in data:
        raise ConfigError(f"{path}: a scene config (config_version), not a study: run it with `pipeline run {path}`")
    try:
        return StudyConfig.model_validate(data)
    except ValidationError as e:
        raise _first_error(e, (), lines, StudyConfig) from None


def variants(study: StudyConfig) -> list[dict[str, Any]]:
    keys = list(study.sweep)
    rows = itertools.product(*study.sweep.values()) if study.mode == "product" else zip(*study.sweep.values())
    return [dict(zip(keys, row)) for row in rows]


def _metric_function(spec: str, study_path: Path | None = None):
    module, _, name = spec.partition(":")
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"{study_path or 'study'}: metrics: function {spec!r} not found ({e})") from None
    if not callable(fn):
        raise ConfigError(f"{study_path or 'study'}: metrics: {spec!r} is not a function")
    return fn


def _lookup(data: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        if isinstance(data, dict) and part in data:
            data = data[part]
        else:
            return None
    return data


_PLAIN = re.compile(r"^[A-Za-z0-9_.+-]{1,40}$")  # a value written into a folder name as it is
_NAME_MAX = 120  # a folder name's length at most (filesystems allow 255 bytes)


def _short_hash(value: Any) -> str:
    return hashlib.sha1(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:8]


def _value_name(value: Any) -> str:
    """A swept value in a folder name: a number or a plain word as written (spacing-0.05, use-sph); anything
    else (a list of emitters, a path, spaces, quotes) a readable prefix and a hash of the whole value
    (str() of an emitter list made a name too long to create, with brackets and quotes in it)."""
    text = _text(value)
    if (isinstance(value, (int, float)) or _PLAIN.match(text)) and text not in (".", ".."):
        return text
    prefix = re.sub(r"[^A-Za-z0-9.+-]+", "-", text).strip("-.")[:24].rstrip("-.")
    return f"{prefix}-{_short_hash(value)}" if prefix else _short_hash(value)


def variant_name(overrides: dict[str, Any]) -> str:
    """The variant's folder under variants/: short, filesystem-safe and deterministic; the full values are in
    the report (study.json)."""
    name = "_".join(f"{k.split('.')[-1]}-{_value_name(v)}" for k, v in overrides.items())
    if len(name) > _NAME_MAX:  # many swept keys: cut, and told apart by a hash of every value
        name = f"{name[:_NAME_MAX - 9]}-{_short_hash(overrides)}"
    return name


def _sets(study: StudyConfig, overrides: dict[str, Any]) -> tuple[str, ...]:
    return tuple(study.set) + tuple(f"{k}={json.dumps(v)}" for k, v in overrides.items()) \
        + (f"outputs={json.dumps(study.outputs)}",)


_warmed: set[str] = set()  # in this process: time stages (implementation and parameters) already warmed up


def _warm_up(study: StudyConfig, base: str, sets: tuple[str, ...], cache_dir: str) -> None:
    """Run the variant's ``time`` stage once in this process on 2 frames in a throw-away cache, if the
    stage declares ``warm_up_run``, the variant is not cached, and this implementation with these
    parameters has not run in this process yet."""
    from . import runner
    from .cache import Cache
    from .config import load_config
    from .errors import PipelineError
    from .graph import build_graph
    from .keys import plan
    from .registry import Registry

    try:
        config = load_config(base, Registry.from_entry_points(), sets)
        graph = build_graph(config)
        node = graph.nodes.get(study.time)
        if node is None or not node.cls.warm_up_run:
            return
        cache = Cache(Path(cache_dir))
        if cache.lookup(study.time, plan(config, graph, cache).keys[study.time]) is not None:
            return
    except (PipelineError, OSError):
        return  # the variant's own run reports the mistake
    key = node.label + json.dumps(node.params.model_dump(mode="json"), sort_keys=True)
    if key in _warmed:
        return
    with tempfile.TemporaryDirectory(prefix="pipeline-warm-up.") as tmp:
        try:
            runner.run(base, overrides=sets + ("scene.frames.count=2",), cache_dir=Path(tmp) / "cache",
                       out_dir=Path(tmp) / "out", until=study.time)
        except PipelineError:
            return
    _warmed.add(key)


def _run_variant(args: tuple, executor=None, events=None) -> VariantResult:
    study_dict, base, overrides, cache_dir, out_root, study_dir = args
    from . import runner

    study = StudyConfig.model_validate(study_dict)
    out = Path(out_root) / "variants" / variant_name(overrides)
    if events:
        events({"stage": "warm-up"})
    _warm_up(study, base, _sets(study, overrides), cache_dir)
    name = variant_name(overrides)
    try:
        report = runner.run(base, overrides=_sets(study, overrides), cache_dir=cache_dir, out_dir=out,
                            executor=executor, events=events)
    except StageFailed as e:
        # one variant's failure is a result of the study (a time step past the stable one blows up): the
        # others still run, the row says why, and the study exits non-zero at the end
        return failed_variant(study, overrides, str(out), " ".join(str(e).split()), e.exit_code == 2)
    except ConfigError as e:
        raise ConfigError(f"variant {name}: {e}") from None
    stage = next((s for s in report.stages if s.kind == study.time), None)
    seconds, cpu = _whole_shot_cost(stage, cache_dir) if stage else (0.0, 0.0)
    return VariantResult(overrides=overrides, seconds=seconds, metrics={m.name: None for m in study.metrics},
                         out=str(out), cpu_seconds=cpu)


def _whole_shot_cost(stage, cache_dir: str) -> tuple[float, float | None]:
    """The time stage's cost for the whole shot, and its CPU seconds. A resumed run (the simulate stage continues
    from its checkpoints after a kill, or from a shorter shot's entry when the shot is extended) reports only
    this process's part in cost_seconds: an extended shot cost half a fresh one's, a killed one a tenth. A stage
    that keeps its own account of its work loop's wall time over every part, JIT warm-up left out as in
    cost_seconds (simulate: meta.json ``stats.wall_seconds``), is charged that, resumed or not, so resumed and
    fresh variants are measured alike; its CPU seconds are the run's CPU-to-wall ratio times that wall time."""
    from .cache import Cache

    try:
        hit = Cache(Path(cache_dir)).lookup(stage.kind, stage.key)
        wall = json.loads((hit.path / "meta.json").read_text())["stats"]["wall_seconds"] if hit else None
    except (OSError, ValueError, KeyError, TypeError):
        wall = None
    if not isinstance(wall, (int, float)) or isinstance(wall, bool):
        return stage.cost_seconds, stage.cpu_seconds
    return float(wall), (stage.cpu_seconds * wall / stage.cost_seconds if stage.cost_seconds > 0 else None)


# the running study's variants (overrides, output folder) while its metrics are measured: a metric that reads
# another variant (stages.simulate.validation.finest_variant) finds it here by the sweep's keys and values, not
# by parsing folder names (a key with '_' in it matched nothing, and the variant was compared with itself) or
# by what lies in variants/ (a folder an earlier config of the study left)
_variants: ContextVar[tuple[tuple[dict[str, Any], Path], ...] | None] = ContextVar("study_variants", default=None)


def study_variants() -> tuple[tuple[dict[str, Any], Path], ...] | None:
    """While a study measures its metrics: each of its current variants' overrides and output folder; else None."""
    return _variants.get()


def _measure(study: StudyConfig, result: VariantResult, study_dir: Path) -> VariantResult:
    """The variant's metrics, once every variant has run: a metric may read another variant's outputs (the
    distance to the finest run), which variants running side by side had not written yet, or had written
    for the study's former config (a user's sweep: wrong distances, exit 0, with --workers 2)."""
    if result.error:
        return result
    out, name = Path(result.out), variant_name(result.overrides)
    metrics: dict[str, float | None] = dict(result.metrics)
    error, mistyped = None, False  # mistyped: the row's error is a file or key the study names wrongly
    for m in study.metrics:
        if m.function is not None:
            try:
                value = _metric_function(m.function)(out, study_dir=study_dir, **m.args)
            except Exception as e:  # noqa: BLE001 - a user's metric: one line naming it, in the variant's row
                # the first failure is the row's error; the metrics that do not depend on it are still given
                error = error or f"metric {m.name} ({m.function}): {type(e).__name__}: {' '.join(str(e).split())}"
                continue
        else:
            value, missing = _file_metric(study, m, out, name)
            if missing:  # the row says it; the other metrics and rows are still reported
                if error is None:
                    error, mistyped = missing, True
                continue
        metrics[m.name] = float(value) if isinstance(value, (int, float)) else None
    return replace(result, metrics=metrics, error=error, user_error=result.user_error or mistyped)


def _file_metric(study: StudyConfig, m, out: Path, name: str) -> tuple[Any, str | None]:
    """A file metric's value in a variant's outputs, and why it cannot be read (None when it can)."""
    f = out / m.file
    if not f.is_file():
        return None, f"metric {m.name}: variant {name} has no {m.file} (its outputs: {', '.join(study.outputs)})"
    value = _lookup(json.loads(f.read_text()), m.key)
    return value, (f"metric {m.name}: {m.file} of variant {name} has no key {m.key}" if value is None else None)


def failed_variant(study: StudyConfig, overrides: dict[str, Any], out: str, error: str,
                   user_error: bool) -> VariantResult:
    return VariantResult(overrides=overrides, seconds=None, metrics={m.name: None for m in study.metrics}, out=out,
                         cpu_seconds=None, error=error, user_error=user_error)


def run_study(path: str | Path, *, cache_dir: Path | None = None, out_dir: Path | None = None,
              workers: int = 1, executor: str = "auto", scheduler: str | None = None,
              events: Callable[[dict], None] | None = None) -> tuple[list[VariantResult], Path]:
    """Run the study's variants: one after another in this process, on ``workers`` local processes, or
    with ``executor="dask"`` as tasks on a Dask cluster (``scheduler`` address, else a LocalCluster of
    ``workers`` processes). ``events`` receives progress events (pipeline.live) inline and on Dask."""
    path = Path(path).resolve()
    study = load_study(path)
    base = (path.parent / study.base).resolve()
    if not base.is_file():
        raise ConfigError(f"{path}: base: config not found: {base}")
    out_root = Path(out_dir) if out_dir else path.parent / "out" / study.name
    # the report's files replace only what an earlier study published there: checked before any variant runs
    report = report_files(study)
    check_out_dir(out_root, report, files=report)
    cache = Path(cache_dir) if cache_dir else base.parent / ".pipeline"
    for m in study.metrics:
        if m.function is not None:
            _metric_function(m.function, path)  # a typo is a config error before anything runs
    _check_variants(study, path, base)
    _drop_old_variants(out_root / "variants", {variant_name(v) for v in variants(study)})
    jobs = [(study.model_dump(), str(base), v, str(cache), str(out_root), str(path.parent)) for v in variants(study)]
    results: list[VariantResult] = []
    if executor == "dask":
        results = _run_on_dask(study, jobs, base, cache, scheduler, workers, events)
    elif workers > 1 and executor != "inline":
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=exit_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            futs = [pool.submit(_run_variant, j) for j in jobs]
            results = [f.result() for f in as_completed(futs)]
        order = {json.dumps(j[2], sort_keys=True): i for i, j in enumerate(jobs)}
        results.sort(key=lambda r: order[json.dumps(r.overrides, sort_keys=True)])
    else:
        for j in jobs:
            label = variant_name(j[2])
            results.append(_run_variant(j, events=(lambda e, label=label: events({"label": label, **e}))
                                        if events else None))
            if events:
                events({"label": label, "state": "failed" if results[-1].error else "done"})
            if not results[-1].error and sum(not r.error for r in results) == 1:
                # a metric's file or key misspelt shows on the first variant: said before the others run (it
                # was found after every variant of an hours-long study had run)
                for m in study.metrics:
                    missing = m.function is None and _file_metric(study, m, Path(results[-1].out), label)[1]
                    if missing:
                        raise ConfigError(f"{path}: {missing}; the other variants were not run")
    token = _variants.set(tuple((r.overrides, Path(r.out)) for r in results))
    try:
        results = [_measure(study, r, path.parent) for r in results]
    finally:
        _variants.reset(token)
    write_report(study, results, out_root)
    failed = [r for r in results if r.error]
    if failed:
        more = f" (and {len(failed) - 1} more; every row in {out_root / 'study.md'})" if len(failed) > 1 else \
            f" (the other variants are in {out_root / 'study.md'})"
        raise StageFailed(f"study {study.name}: {len(failed)} of {len(results)} variant(s) failed: variant "
                          f"{variant_name(failed[0].overrides)}: {failed[0].error}{more}",
                          user_error=all(r.user_error for r in failed))
    return results, out_root


def _check_variants(study: StudyConfig, path: Path, base: Path) -> None:
    """Every variant's config loads and runs the ``time`` stage, before any runs (a bad swept value was found
    only after the variants before it had run and been published)."""
    from .config import load_config
    from .estimate import check_stages
    from .graph import build_graph
    from .registry import Registry

    registry = Registry.from_entry_points()
    names: dict[str, dict] = {}
    for v in variants(study):
        if variant_name(v) in names:  # (1 and True, or a value given twice): one folder for two variants
            raise ConfigError(f"{path}: sweep: variants {names[variant_name(v)]} and {v} would share the folder "
                              f"{variant_name(v)}: give each value once")
        names[variant_name(v)] = v
        try:
            config = load_config(base, registry, _sets(study, v))
            graph = build_graph(config)
            check_stages(config, graph)
        except ConfigError as e:
            raise ConfigError(f"{path}: variant {variant_name(v)}: {e}") from None
        if study.time not in graph.nodes:
            raise ConfigError(f"{path}: time: {study.time} is not a stage the outputs {study.outputs} run "
                              f"(they run {', '.join(graph.order())}): its cost would read 0 s")


def _drop_old_variants(folder: Path, current: set[str]) -> list[str]:
    """Remove the variant folders an earlier run of the study published that the sweep no longer makes (a metric
    read one made with other settings): only a folder whose record says the pipeline published everything in
    it, unchanged since (publish.drop_stale's rule); anything else in variants/ is left alone."""
    if not folder.is_dir():
        return []
    sweep_out_dir(folder)  # a killed removal's leftovers
    dropped = []
    for d in sorted(folder.iterdir()):
        if d.name in current or d.name.startswith(".") or d.is_symlink() or not d.is_dir():
            continue
        sweep_out_dir(d)
        try:
            record, stats = read_record(d), read_record_stats(d)
        except OutputRefused:
            continue
        published = {RECORD} | {f"{n}/{f}" if (d / n).is_dir() else n for n, files in record.items() for f in files}
        held = {f.relative_to(d).as_posix() for f in d.rglob("*") if f.is_symlink() or not f.is_dir()}
        if not record or not held <= published or any(changed_file(d, n, stats) for n in record):
            continue
        trash = folder / f"{TMP_PREFIX}old-{d.name}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
        os.replace(d, trash)
        shutil.rmtree(trash, ignore_errors=True)
        dropped.append(d.name)
    return dropped


def _run_on_dask(study: StudyConfig, jobs: list[tuple], base: Path, cache: Path, scheduler: str | None,
                 workers: int, events) -> list[VariantResult]:
    from . import cluster

    client = cluster.connect(scheduler, workers)
    try:
        tasks = [cluster.Task(variant_name(j[2]), _run_variant, j, cluster.shot_resources(base, _sets(study, j[2]), cache))
                 for j in jobs]
        outcomes = cluster.run_tasks(client, tasks, events)
    finally:
        cluster.close(client)
    # a task that failed outside the variant's own run (a worker lost): its row, like a failed run's
    return [failed_variant(study, j[2], str(Path(j[4]) / "variants" / o.label), o.error, o.exit_code == 2)
            if o.error else o.value for j, o in zip(jobs, outcomes)]


def report_files(study: StudyConfig) -> list[str]:
    """The files a study publishes beside its variants/ folder."""
    return ["study.csv", "study.json", "study.md"] + [f"{m.name}_vs_time.png" for m in study.metrics]


def write_report(study: StudyConfig, results: list[VariantResult], out_root: Path) -> None:
    """The table (csv, json, md) and one plot per metric, each published as a run publishes its outputs
    (publish.publish_file: atomically, and never over a file the pipeline did not write)."""
    keys = list(study.sweep)
    header = keys + [f"{study.time}_seconds", f"{study.time}_cpu_seconds"] + [m.name for m in study.metrics] \
        + ["variant-error"]  # a name no metric can take (metric names have no '-')
    rows = [[r.overrides[k] for k in keys] + [_rounded(r.seconds), _rounded(r.cpu_seconds)]
            + [r.metrics[m.name] for m in study.metrics] + [r.error or ""] for r in results]
    table = io.StringIO(newline="")
    w = csv.writer(table)
    w.writerow(header)
    w.writerows([[_text(v) for v in row[:len(keys)]] + row[len(keys):] for row in rows])
    publish_file(out_root, "study.csv", table.getvalue())
    publish_file(out_root, "study.json", json.dumps({"study": study.model_dump(), "results": [r.__dict__ for r in results]},
                                                    indent=1))
    md = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    n = len(keys)  # the swept values as written (0.04 and 0.0400001 were both 0.04); costs and metrics to 4 figures
    md += ["| " + " | ".join(_cell(v, i < n) for i, v in enumerate(row)) + " |" for row in rows]
    publish_file(out_root, "study.md", f"# Study {study.name}\n\n" + "\n".join(md) + "\n")
    _plot(study, results, out_root)


def _text(value: Any) -> str:
    """A swept value as text (lists and mappings as JSON)."""
    return str(value) if isinstance(value, (int, float, str, bool)) or value is None else \
        json.dumps(value, sort_keys=True)


def _cell(value: Any, swept: bool) -> str:
    if value is None:
        return ""
    text = _text(value) if swept or not isinstance(value, float) else f"{value:.4g}"
    return text.replace("|", "\\|")


def _rounded(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds, 3)


def _plot(study: StudyConfig, results: list[VariantResult], out_root: Path) -> None:
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib.pyplot as plt

    keys = list(study.sweep)
    series_key = keys[-1] if len(keys) > 1 else None  # one line per value of the last swept key
    for m in study.metrics:
        fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
        groups: dict[Any, list[VariantResult]] = {}
        for r in results:
            # by the value's short name, as its folder's: a list value (emitters, a box corner) is no dict key
            groups.setdefault(_value_name(r.overrides[series_key]) if series_key else m.name, []).append(r)
        for label, rs in groups.items():
            pts = [(r.seconds, r.metrics[m.name], r) for r in rs if r.metrics[m.name] is not None]
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=str(label))
            for s, v, r in pts:
                tag = ", ".join(f"{k.split('.')[-1]}={_value_name(r.overrides[k])}" for k in keys if k != series_key)
                ax.annotate(tag, (s, v), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xlabel(f"{study.time} wall time without JIT warm-up (s)")
        ax.set_ylabel(m.label or m.name)
        ax.set_title(f"{study.name}: accuracy against time")
        ax.grid(True, alpha=0.3)
        if series_key:
            ax.legend(title=series_key.split(".")[-1])
        fig.tight_layout()
        png = io.BytesIO()
        fig.savefig(png, format="png")
        plt.close(fig)
        publish_file(out_root, f"{m.name}_vs_time.png", png.getvalue())
