"""Run a config's plan (pipeline.keys) against the cache: hits, misses, per-frame jobs, publishing,
run.json. Whole-run stages run in dependency order in this process; per-frame jobs go to the executor.
Status and clean are in pipeline.status.
"""
from __future__ import annotations

import faulthandler
import json
import logging
import multiprocessing
import os
import shutil
import sys
import threading
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, NoReturn

from .cache import Cache, env_seconds, hash_key, owner_tag, unwritable
from .config import OUTPUT_NAMES, Config, load_config
from .errors import CacheMissError, CodeChanged, ConfigError, FrameError, PipelineError, StageFailed
from .estimate import check_size, check_stages
from .executors import Executor, make_executor
from .graph import Graph, Node, build_graph
from .keys import (Plan, changed_since_loaded, check_inputs_unchanged, context, frame_key, plan, record_resume,
                   resume_source)
from .publish import check_out_dir, drop_stale, publish, read_record_keys, write_run_json
from .registry import Registry
from .reads import FRAMES, SceneReads
from .stage import Artifact, Context, Progress, Stage, StageError

log = logging.getLogger("pipeline")


# -- reports ---------------------------------------------------------------------------------------
@dataclass
class StageReport:
    kind: str
    implementation: str
    version: str
    key: str
    status: str  # "cached", "ran", "forced"; per-frame: also frames counts
    seconds: float = 0.0
    frames_total: int = 0
    frames_ran: int = 0
    # the stage's own wall and process CPU seconds without its warm-up (Context.warm_up: one-off JIT
    # compilation) and without waiting for locks (per-frame stages: the sum over their frames); what a study
    # charges a variant
    cost_seconds: float = 0.0
    cpu_seconds: float = 0.0


@dataclass
class RunReport:
    config: str
    scene: str
    cache: str
    out: str
    seconds: float = 0.0
    stages: list[StageReport] = field(default_factory=list)
    outputs: dict[str, str] = field(default_factory=dict)
    # what the outputs were made with beyond the config file (the stages are the run's selection): the --set
    # overrides, the frame selection (None: every frame), and when it finished (UTC)
    overrides: list[str] = field(default_factory=list)
    frames: list[int] | None = None
    finished: str = ""
    settings: dict[str, Any] = field(default_factory=dict)  # the config as this run read it (--set applied)

    def stage(self, kind: str) -> StageReport:
        return next(s for s in self.stages if s.kind == kind)

    def artifact(self, name: str) -> Artifact:
        """The cache entry of artifact ``name`` ("particles", "raw_surface", "surface", "sdf", "walls", ...) that
        this run made or found: ``.path`` for a whole-run artifact, ``.frame(i)`` for a per-frame one; read it
        with ``stages.common.formats`` and do not write into it (it is shared by every run of its key).
        Only in the process that ran (not in run.json)."""
        made = getattr(self, "_artifacts", {})
        if name not in made:
            raise KeyError(f"this run has no artifact {name!r} (it has: {', '.join(sorted(made)) or 'none'})")
        return made[name]

    def ran(self) -> list[str]:
        return [s.kind for s in self.stages if s.status != "cached"]


# -- per-frame job (top level so process pools can pickle it) -----------------------------------
@dataclass
class FrameJob:
    cache_root: str
    kind: str
    stage_cls: type[Stage]
    params: Any
    scene: SceneReads  # only what the stage declares
    config_dir: str
    frames: tuple[int, ...]
    inputs: dict[str, Artifact]
    stage_key: str
    frame: int
    force: bool
    lock_timeout: float | None = None
    fault_log: str | None = None  # the run's log: faulthandler writes native crashes of workers there
    files: dict[str, str] = field(default_factory=dict)  # the input files the key was made from


_worker_fault_log: tuple[str, Any] | None = None  # (path, open file) in a worker process


def _enable_faulthandler(path: str | None) -> None:
    """In a worker process, send faulthandler's output to the current run's log (in this process, as
    with the inline executor, execute() has done it already)."""
    global _worker_fault_log
    if path is None or (_worker_fault_log is None and faulthandler.is_enabled()):
        return
    if _worker_fault_log is not None and _worker_fault_log[0] == path:
        return
    try:
        fh = open(path, "a")
    except OSError:
        return  # no log (disk full): the work goes on
    faulthandler.enable(fh)
    if _worker_fault_log is not None:
        _worker_fault_log[1].close()
    _worker_fault_log = (path, fh)


def run_frame_job(job: FrameJob) -> tuple[int, str, float, float, bool]:
    """Compute one frame's entry unless it is cached; returns (frame, entry path, seconds, CPU seconds, ran):
    the frame's own work (the run that made a cached frame), without waiting for its lock.
    Any failure comes back as FrameError naming the frame (with the worker's traceback)."""
    try:
        return _frame_job(job)
    except KeyboardInterrupt:
        raise
    except SystemExit as exc:  # the stage's own sys.exit(): a failed frame, not the end of this worker
        raise FrameError(job.frame, f"the stage called sys.exit({exc.code!r})", "".join(traceback.format_exception(exc)),
                         False) from None
    except BaseException as exc:  # noqa: BLE001 - re-raised with the frame, picklable
        user = isinstance(exc, StageError) or (isinstance(exc, PipelineError) and exc.exit_code == 2)
        plain = user or isinstance(exc, PipelineError)  # our own one-line errors need no type name
        raise FrameError(job.frame, brief(exc) if not plain else str(exc),
                         "".join(traceback.format_exception(exc)), user) from None


def _check_wrote(out_dir: Path, stage_cls: type[Stage]) -> None:
    """A stage that returned without writing anything would be committed as an empty entry and served as
    done, the fault surfacing later as a missing input of the next stage."""
    if not any(f.is_file() for f in out_dir.rglob("*")):  # empty folders are no output either
        raise StageFailed(f"wrote nothing into its output folder (ctx.out_dir), where its outputs "
                          f"({', '.join(stage_cls.outputs)}) belong", user_error=False)


def _frame_job(job: FrameJob) -> tuple[int, str, float, float, bool]:
    _enable_faulthandler(job.fault_log)
    cache = Cache(Path(job.cache_root), lock_timeout=job.lock_timeout)
    key = frame_key(job.stage_key, job.frame)
    with cache.lock(key, f"stage {job.stage_cls.qualname()} frame {job.frame}"):
        hit = None if job.force else cache.lookup(job.kind, key)
        if hit is not None:
            return (job.frame, str(hit.path), float(hit.manifest.get("seconds", 0.0)),
                    float(hit.manifest.get("cpu_seconds", 0.0)), False)
        tmp = cache.new_tmp(key)
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            ctx = Context(out_dir=tmp, scene=job.scene, config_dir=Path(job.config_dir),
                          frames=job.frames if FRAMES in job.stage_cls.reads else None,
                          log=logging.getLogger(f"stage.{job.stage_cls.qualname()}"))
            job.stage_cls().run_frame(ctx, job.inputs, job.params, job.frame)
            _check_wrote(tmp, job.stage_cls)
            check_inputs_unchanged(job.config_dir, job.files)
            seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
            entry = cache.commit(job.kind, key, tmp, {"stage_key": job.stage_key, "frame": job.frame,
                                                      "stage": job.stage_cls.qualname(), "seconds": seconds,
                                                      "cpu_seconds": cpu})
        except BaseException:
            cache.discard(tmp)
            raise
    return job.frame, str(entry.path), seconds, cpu, True


# -- running ---------------------------------------------------------------------------------------
Events = Callable[[dict], None]


# a run whose stderr is no terminal (a farm's log file) says a long stage's progress in a line this often (s;
# env PIPELINE_LOG_EVERY)
LOG_EVERY = 30.0


class _Progress:
    """Rich progress bars for long stages when ``enabled`` is True; with "log" (stderr is no terminal: a
    render farm's log, which had nothing from a 2-minute simulation until its end) a logged line every LOG_EVERY
    seconds (env PIPELINE_LOG_EVERY) of a stage that runs that long; silent when quiet. With ``events`` (a live view of several shots,
    pipeline.live), every advance is also sent there as ``{"task": description, "done": n, "total": total}``."""

    def __init__(self, enabled: bool | str, events: Events | None = None) -> None:
        self._bar = None
        self._events = events
        self._lines = enabled == "log"
        self._every = env_seconds("PIPELINE_LOG_EVERY", LOG_EVERY)
        if enabled is True:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress as RichProgress, TextColumn, TimeElapsedColumn

            self._bar = RichProgress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), transient=False)

    def __enter__(self) -> "_Progress":
        if self._bar is not None:
            self._bar.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._bar is not None:
            self._bar.stop()

    def make(self, description: str, total: float) -> Progress:
        if self._bar is None and self._events is None and not self._lines:
            return Progress()
        task = None if self._bar is None else self._bar.add_task(description, total=total)
        done = [0.0]
        start = time.monotonic()
        said = [start]  # when the last line was logged

        def update(amount: float) -> None:
            done[0] += amount
            if task is not None:
                self._bar.advance(task, amount)
            if self._events is not None:
                self._events({"task": description, "done": done[0], "total": total})
            now = time.monotonic()
            finished = done[0] >= total
            if self._lines and (now - said[0] >= self._every or (finished and said[0] > start)):
                said[0] = now
                spent = now - start
                left = f", about {spent * (total - done[0]) / done[0]:.0f} s left" if 0 < done[0] < total else ""
                log.info("%s: %g of %g (%.0f %%) in %.0f s%s", description, done[0], total,
                         100.0 * min(done[0] / total, 1.0) if total else 100.0, spent, left)

        return Progress(update)


# what a failed write says, wherever a library buries it (USD's ErrorException repeats "File too large" 36 times
# in 8.7 KB of C++ context)
_IO_CAUSES = ("No space left on device", "File too large", "Disk quota exceeded", "Read-only file system",
              "Permission denied")


def brief(exc: BaseException, limit: int = 300) -> str:
    """``Type: message`` for a one-line report: a full disk or a file-size limit named as such, other
    messages cut to their first line and ``limit`` characters (the whole text goes to the saved log)."""
    text = str(exc)
    cause = next((c for c in _IO_CAUSES if c in text), None)
    if cause is not None and not isinstance(exc, OSError):
        return f"{type(exc).__name__}: a write failed: {cause}"
    first = text.strip().splitlines()[0] if text.strip() else ""
    if len(first) > limit:
        first = first[:limit].rstrip() + " ..."
    elif first != text.strip():
        first += " ..."
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def write_log(cache: Cache, name: str, text: str) -> str:
    """Save a traceback under the cache's logs/; returns where, or why it could not be saved."""
    log_file = cache.root / "logs" / f"{name}.log"
    try:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        log_file.write_text(text)
    except OSError as e:
        try:
            log_file.unlink(missing_ok=True)
        except OSError:
            pass
        return f"no log saved: {e.strerror or e}"
    return f"traceback in {log_file}"


def interrupt_in(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C (or SIGTERM) behind ``exc``, if one is in its chain: one arriving inside numba's dispatcher (its
    unpickler) comes out as "SystemError: ... returned a result with an exception set", and the run was said as a
    failed stage (exit 1) instead of interrupted (130)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _raise_failed(node: Node, key: str, config: Config, exc: BaseException, cache: Cache, hook: str) -> NoReturn:
    """A stage hook's exception as the run says it: an interrupt (a library's wrapping of one too) as itself, the
    hook's own sys.exit() and anything else as a failed stage, its traceback saved."""
    interrupt = interrupt_in(exc)
    if interrupt is not None:
        raise interrupt from None
    if isinstance(exc, SystemExit):
        exc = StageFailed(f"{hook} called sys.exit({exc.code!r})", user_error=False).with_traceback(exc.__traceback__)
    raise _fail(node, key, config, exc, cache) from exc


def _fail(node: Node, key: str, config: Config, exc: BaseException, cache: Cache) -> StageFailed:
    if isinstance(exc, FrameError):
        where = f"stage {node.label} frame {exc.frame}"
        if exc.user_error:
            return StageFailed(f"{where}: {exc.cause}", user_error=True)
        saved = write_log(cache, f"{node.kind}-{key[:12]}-frame{exc.frame}", exc.traceback)
        return StageFailed(f"{where} failed (key {key[:12]}, config {config.path.name}): {exc.cause} ({saved})",
                           user_error=False)
    if isinstance(exc, (StageError, PipelineError)):
        # stages name themselves in their messages ("simulate.sph: ..."): do not say it twice
        text = str(exc).removeprefix(f"{node.label}: ")
        user = isinstance(exc, StageError) or exc.exit_code == 2
        if not user:  # a failed run (a simulation's blow-up, exit 1): its traceback is saved as for any failure
            text += f" ({write_log(cache, f'{node.kind}-{key[:12]}', ''.join(traceback.format_exception(exc)))})"
        return StageFailed(f"stage {node.label}: {text}", user_error=user)
    if type(exc).__name__ == "BrokenProcessPool":
        exc_text = ("a worker process died (killed, out of memory or a native crash; faulthandler output in the run log; "
                    "a script calling pipeline.run with workers needs the if __name__ == \"__main__\": guard)")
    else:
        exc_text = brief(exc)
    saved = write_log(cache, f"{node.kind}-{key[:12]}", "".join(traceback.format_exception(exc)))
    return StageFailed(f"stage {node.label} failed (key {key[:12]}, config {config.path.name}): "
                       f"{exc_text} ({saved})", user_error=False)


def _outside(what: str, exc: BaseException, cache: Cache) -> StageFailed:
    """An error outside a stage's own work (publishing, saving state): exit 1, one line, a log."""
    saved = write_log(cache, f"{what.split()[0]}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}",
                      "".join(traceback.format_exception(exc)))
    return StageFailed(f"{what}: {type(exc).__name__}: {exc} ({saved})", user_error=False)


def execute(p: Plan, *, out_dir: Path, force: frozenset[str] = frozenset(), executor: Executor | None = None,
            progress: bool | str = False, events: Events | None = None, allow_large: bool = False) -> RunReport:
    """Run the plan. Inline, stages go one by one in dependency order; with a pool executor, independent
    branches (e.g. render frames and export) are driven concurrently by threads of this process while
    their per-frame jobs run in the pool's worker processes. faulthandler writes native crashes (VTK,
    numba) of this process (unless the host enabled faulthandler itself) and of the workers into the run's
    log under the cache's logs/. ``allow_large``:
    stages' own memory checks (Context.check_memory) let anything pass."""
    cache = p.cache
    try:
        cache.root.mkdir(parents=True, exist_ok=True)
        cache.sweep_tmp()
        (cache.root / "logs").mkdir(exist_ok=True)
        fault_log = cache.root / "logs" / f"run-{time.strftime('%Y%m%d-%H%M%S')}-{owner_tag()}.log"
        fault_fh = open(fault_log, "w")
    except OSError as exc:
        raise _outside(f"cache {cache.root}", exc, cache) from exc
    # a host that enabled faulthandler itself (an application embedding the library, pytest,
    # PYTHONFAULTHANDLER) keeps it: its file cannot be asked for, so it could not be given back
    ours = not faulthandler.is_enabled()
    if ours:
        faulthandler.enable(fault_fh)
    try:
        return _execute(p, out_dir, force, executor, progress, str(fault_log), events, allow_large)
    finally:
        if ours:
            faulthandler.disable()
        fault_fh.close()
        try:
            if fault_log.stat().st_size == 0:
                fault_log.unlink()
        except OSError:
            pass


def _execute(p: Plan, out_dir: Path, force: frozenset[str], executor: Executor | None, progress: bool | str,
             fault_log: str, events: Events | None = None, allow_large: bool = False) -> RunReport:
    config, graph, cache = p.config, p.graph, p.cache
    t_start = time.perf_counter()
    count = config.scene.scene.frames.count
    report = RunReport(config=str(config.path), scene=config.name, cache=str(cache.root), out=str(out_dir),
                       overrides=list(config.overrides), frames=None if p.frames == tuple(range(count)) else list(p.frames),
                       settings=json.loads(json.dumps(config.raw, default=str)))
    artifacts: dict[str, Artifact] = {}
    reports: dict[str, StageReport] = {}
    state = cache.read_state(config.path)
    executor = executor or make_executor("inline")
    guard = threading.Lock()

    def run_node(kind: str, bars: _Progress) -> tuple[StageReport, dict[str, Artifact]]:
        node = graph.nodes[kind]
        key = p.keys[kind]
        runnable = kind in graph.runnable
        forced = kind in force or "all" in force
        with guard:
            inputs = {name: artifacts[name] for name, _ in node.inputs}
        if events is not None:
            events({"stage": kind})
        t0 = time.perf_counter()
        try:
            if node.per_frame:
                sr, frames = _run_per_frame(p, node, key, inputs, runnable, forced, executor, bars, fault_log)
                made = {out: Artifact(name=out, key=key, frames=frames) for out in node.cls.outputs}
            else:
                sr, path = _run_whole(p, node, key, inputs, runnable, forced, bars, allow_large)
                made = {out: Artifact(name=out, key=key, path=path) for out in node.cls.outputs}
        except PipelineError:
            raise
        except Exception as exc:  # noqa: BLE001 - the engine's own work for this stage (lock, cache folders)
            raise _fail(node, key, config, exc, cache) from exc
        if sr.status != "cached":
            sr.seconds = time.perf_counter() - t0
        return sr, made

    def finish(kind: str, result: tuple[StageReport, dict[str, Artifact]]) -> None:
        sr, made = result
        with guard:
            artifacts.update(made)
            reports[kind] = sr
            state[kind] = {"key": sr.key, "components": p.components[kind], "seconds": sr.seconds,
                           "status": sr.status, "time": time.time()}
            if graph.nodes[kind].per_frame:  # `clean` removes the frames this run made, not the config's only
                state[kind]["frames"] = list(p.frames)
            try:
                cache.write_state(config.path, state)
            except OSError as exc:
                raise _outside(f"stage {graph.nodes[kind].label}: saving the cache state", exc, cache) from exc
        log.debug("%-16s %-16s %s  %s", kind, sr.implementation, sr.key[:12], sr.status)

    order = graph.order()
    with _Progress(progress, events) as bars:
        # on a Dask worker the stages stay in the task's thread: only it may secede while frames run
        if executor.name in ("inline", "dask-worker") or len(order) < 2:
            for kind in order:
                finish(kind, run_node(kind, bars))
        else:
            _run_branches(graph, order, lambda k: run_node(k, bars), finish)
    report.stages = [reports[k] for k in order]
    report._artifacts = dict(artifacts)  # RunReport.artifact; not a field: run.json holds no cache paths
    try:
        # two runs publishing into one folder (the same config run twice) take turns
        with cache.lock(hash_key({"publish": str(out_dir)}), f"publish into {out_dir}"):
            report.outputs = publish(graph, artifacts, out_dir, p.frames, _made_from(p, graph, graph.outputs),
                                     shot_of(p.config))
            earlier = {n: k for n, k in read_record_keys(out_dir).items() if n not in report.outputs}
            stale = drop_stale(out_dir, _current_keys(p, earlier)) if earlier else []
            if stale:
                log.info("removed %s from %s: made with other settings than the config's now",
                         ", ".join(f"{n}/" for n in stale), out_dir)
            report.seconds = time.perf_counter() - t_start
            report.finished = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            write_run_json(report, out_dir)
    except OSError as exc:
        raise _outside(f"publish into {out_dir}", exc, cache) from exc
    return report


def shot_of(config: Config) -> dict[str, str]:
    """What the output folder's record names as the shot it holds (the config's file name only: a copied project
    must publish the same bytes)."""
    return {"scene": config.scene.scene.name, "config": Path(config.path).name}


def _made_from(p: Plan, graph: Graph, names) -> dict[str, dict]:
    """What each output of plan ``p`` is made from, for the publish record: its producer's key and the
    run's frame selection (None: all frames)."""
    every = p.frames == tuple(range(p.config.scene.scene.frames.count))
    return {n: {"key": p.keys[graph.producer(n)], "frames": None if every else list(p.frames)}
            for n in names if graph.producer(n) in p.keys}


def _current_keys(p: Plan, earlier: dict[str, dict]) -> dict[str, str | None]:
    """The key the config as it is now gives the producer of each output an earlier run published, for
    that run's frames (a --frames run does not make a whole-shot movie stale); None where it cannot be
    worked out (such an output is kept)."""
    from dataclasses import replace

    current: dict[str, str | None] = dict.fromkeys(earlier)
    selections = {tuple(k["frames"]) if k.get("frames") is not None else None for k in earlier.values()}
    for frames in selections:
        names = tuple(n for n, k in earlier.items() if n in OUTPUT_NAMES
                      and (tuple(k["frames"]) if k.get("frames") is not None else None) == frames)
        try:
            config = replace(p.config, outputs=names)
            graph = build_graph(config)
            keys = plan(config, graph, p.cache, frames).keys
        except PipelineError:
            continue
        current.update({n: keys[graph.producer(n)] for n in names if graph.producer(n) in keys})
    return current


def _run_branches(graph: Graph, order: list[str], run_node: Callable, finish: Callable) -> None:
    """Start every stage as soon as its producers are done; the first failure is raised after the
    stages already running have finished (their entries stay valid)."""
    done: set[str] = set()
    remaining = list(order)
    error: BaseException | None = None
    threads = ThreadPoolExecutor(max_workers=len(order))
    try:
        running: dict[Any, str] = {}
        while remaining or running:
            if error is None:
                for kind in list(remaining):
                    if all(producer in done for _, producer in graph.nodes[kind].inputs):
                        running[threads.submit(run_node, kind)] = kind
                        remaining.remove(kind)
            if not running:
                break
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                kind = running.pop(fut)
                try:
                    finish(kind, fut.result())
                    done.add(kind)
                except BaseException as exc:  # noqa: BLE001 - re-raised below
                    error = error or exc
    except BaseException:
        # Ctrl-C: do not wait for a stage running in a thread (a simulation can take hours); its
        # temporary folder is swept once this process is gone
        threads.shutdown(wait=False, cancel_futures=True)
        raise
    threads.shutdown(wait=True)
    if error is not None:
        raise error


def _run_whole(p: Plan, node: Node, key: str, inputs: dict[str, Artifact], runnable: bool, forced: bool,
               bars: _Progress, allow_large: bool = False) -> tuple[StageReport, Path]:
    cache, config = p.cache, p.config
    sr = StageReport(node.kind, node.cls.name, node.cls.version, key, "cached")
    hit = None if (forced and runnable) else cache.lookup(node.kind, key)
    if hit is not None:
        _cached_times(sr, hit.manifest)
        return sr, hit.path
    if not runnable:
        raise CacheMissError(f"stage {node.label} is not cached (key {key[:12]}) and the selection does not run it; "
                             f"run without --only/--from first")
    with cache.lock(key, f"stage {node.label}"):
        hit = None if forced else cache.lookup(node.kind, key)  # another run may have made it meanwhile
        if hit is not None:
            _cached_times(sr, hit.manifest)
            return sr, hit.path
        tmp = cache.new_tmp(key)
        if forced:  # a killed run's checkpoints of this key: --force recomputes, it does not resume them
            shutil.rmtree(cache.checkpoint_dir(key), ignore_errors=True)
        resume = p.resume.get(node.kind)
        ctx = context(config, node, tmp, p.frames, checkpoint_dir=cache.checkpoint_dir(key),
                      resume_from=resume_source(cache, node.kind, resume) if resume and not forced else None,
                      allow_large=allow_large)
        ctx.make_progress = bars.make
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            node.cls().run(ctx, inputs, node.params)
            _check_wrote(tmp, node.cls)
            check_inputs_unchanged(config.dir, p.components[node.kind]["files"])
            seconds = time.perf_counter() - t0
            sr.cost_seconds = seconds - ctx.warmup_seconds
            sr.cpu_seconds = time.process_time() - c0 - ctx.warmup_cpu_seconds
            entry = cache.commit(node.kind, key, tmp, {
                "stage": node.label, "version": node.cls.version, "seconds": seconds,
                "cost_seconds": sr.cost_seconds, "cpu_seconds": sr.cpu_seconds,
                "components": p.components[node.kind]})
        except BaseException as exc:
            cache.discard(tmp)
            _raise_failed(node, key, config, exc, cache, "the stage")
        shutil.rmtree(cache.checkpoint_dir(key), ignore_errors=True)
        if resume:
            record_resume(cache, node.kind, resume, key)
    sr.status = "forced" if forced else "ran"
    return sr, entry.path


def _cached_times(sr: StageReport, manifest: dict) -> None:
    sr.seconds = float(manifest.get("seconds", 0.0))
    sr.cost_seconds = float(manifest.get("cost_seconds", sr.seconds))
    sr.cpu_seconds = float(manifest.get("cpu_seconds", 0.0))


def _run_per_frame(p: Plan, node: Node, key: str, inputs: dict[str, Artifact], runnable: bool, forced: bool,
                   executor: Executor, bars: _Progress, fault_log: str | None = None) -> tuple[StageReport, dict[int, Path]]:
    cache, config = p.cache, p.config
    sr = StageReport(node.kind, node.cls.name, node.cls.version, key, "cached", frames_total=len(p.frames))
    frames: dict[int, Path] = {}
    todo: list[int] = []
    for f in p.frames:
        hit = None if (forced and runnable) else cache.lookup(node.kind, frame_key(key, f))
        if hit is None:
            todo.append(f)
        else:
            frames[f] = hit.path
            sr.seconds += float(hit.manifest.get("seconds", 0.0))
            sr.cpu_seconds += float(hit.manifest.get("cpu_seconds", 0.0))
    sr.cost_seconds = sr.seconds  # the cached frames' own seconds, as a cached whole-run stage reports its run's
    if not todo:
        return sr, frames
    if not runnable:
        raise CacheMissError(f"stage {node.label} has {len(todo)} frame(s) not cached (first: {todo[0]}) and the "
                             f"selection does not run it; run without --only/--from first")
    scene = SceneReads(config.sections(), node.cls.reads)
    jobs = [FrameJob(cache_root=str(cache.root), kind=node.kind, stage_cls=node.cls, params=node.params,
                     scene=scene, config_dir=str(config.dir), frames=p.frames,
                     inputs=inputs, stage_key=key, frame=f, force=forced, lock_timeout=cache.lock_timeout,
                     fault_log=fault_log, files=p.components[node.kind]["files"]) for f in todo]
    bar = bars.make(f"{node.kind} frames", len(jobs))
    try:
        for frame, path, seconds, cpu, ran in executor.map_unordered(run_frame_job, jobs):
            frames[frame] = Path(path)
            sr.frames_ran += int(ran)
            sr.cost_seconds += seconds
            sr.cpu_seconds += cpu
            bar.advance()
    except BaseException as exc:
        if isinstance(exc, SystemExit):
            raise
        _raise_failed(node, key, config, exc, cache, "the stage")
    sr.status = "forced" if forced else "ran"
    frames = dict(sorted(frames.items()))
    if sr.frames_ran:  # each worker saw only its own frames: the stage's word on all of them, once, here
        try:
            node.cls().summarise(context(config, node, None, p.frames), node.params, frames)
        except BaseException as exc:  # noqa: BLE001 - a failed summary is a failed stage, with its traceback saved
            _raise_failed(node, key, config, exc, cache, "its summarise()")
    return sr, frames


# -- library entry points ------------------------------------------------------------------------
def default_cache_dir(config: Config) -> Path:
    return config.dir / ".pipeline"


def default_out_dir(config: Config) -> Path:
    return config.dir / "out" / config.name


def select(graph: Graph, only: str | None = None, from_: str | None = None, until: str | None = None) -> Graph:
    if only and (from_ or until):
        raise ConfigError("--only cannot be combined with --from/--until")
    if only:
        graph = graph.only(only)
    if from_ and until and from_ in graph.nodes and until in graph.nodes and from_ != until \
            and from_ not in graph.upstream(until):
        # the until-graph no longer holds from_: it was called "not a stage this config runs", though it is
        where = "comes after" if from_ in graph.downstream(until) else "is not upstream of"
        raise ConfigError(f"--from {from_} {where} --until {until}: nothing would run (--from names the first "
                          "stage to run, --until the last)")
    if until:
        graph = graph.until(until)
    if from_:
        graph = graph.from_(from_)
    return graph


def parse_frames(text: str | None) -> tuple[int, ...] | None:
    """``"0:10"`` (end exclusive), ``"5"``, or ``"0,3,7"``; sorted, each frame once ("0,0,3" was three frames in
    run.json and status, and keyed the movie apart from "0,3")."""
    if text is None:
        return None
    try:
        if ":" in text:
            a, _, b = text.partition(":")
            frames = tuple(range(int(a or 0), int(b)))
        else:
            frames = tuple(sorted({int(t) for t in text.split(",")}))
    except ValueError:
        raise ConfigError(f"--frames {text}: expected START:END, N or N,M,...") from None
    if not frames:  # 5:2 or 1:1: nothing to compute, and a movie of no frames would fail only at the end
        raise ConfigError(f"--frames {text}: selects no frame (START:END is end exclusive: END must exceed START)")
    return frames


def run(config_path: str | Path, *, registry: Registry | None = None, overrides: tuple[str, ...] = (),
        cache_dir: str | Path | None = None, out_dir: str | Path | None = None, only: str | None = None,
        from_: str | None = None, until: str | None = None, force: tuple[str, ...] = (),
        frames: tuple[int, ...] | None = None, executor: Executor | None = None,
        progress: bool | str = False, lock_timeout: float | None = None, allow_large: bool = False,
        events: Events | None = None, workers: int = 1) -> RunReport:
    """Run what the config's outputs need; returns the report (also written to out/run.json).

    The library's entry point (the CLI's ``pipeline run`` calls it): ``overrides`` are ``--set`` assignments
    ("simulate.cfl=0.3", a sequence), ``workers`` > 1 runs per-frame jobs in that many processes (a pool
    made and closed here; a script using it needs the ``if __name__ == "__main__":`` guard of spawned
    processes), or pass an ``executor`` (pipeline.executors.make_executor) to keep one across runs. Errors
    are ``PipelineError`` subclasses with ``exit_code``; ``report.artifact(name)`` finds an artifact's entry.

    Refuses (exit 2, nothing written) an output folder holding things the pipeline did not publish
    where it would write, and a plan whose memory estimate exceeds the available memory unless
    ``allow_large`` (or the config's ``allow_large: true``)."""
    if isinstance(overrides, str):  # iterated, a string is one --set per character
        raise ConfigError(f"overrides: expected a sequence of path=value assignments, got the string {overrides!r} "
                          f"(write ({overrides!r},))")
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        # a spawned worker importing the caller's script (no __main__ guard) reached its pipeline.run: say so
        # once per worker instead of Python's bootstrapping traceback (about 290 lines for two workers)
        print("error: pipeline.run was called while a worker process imported the calling script: put the call "
              "under if __name__ == \"__main__\": (worker processes import the script again)", file=sys.stderr)
        os._exit(1)
    if executor is None and workers > 1:
        pool = make_executor("processes", workers)
        try:
            report = run(config_path, registry=registry, overrides=overrides, cache_dir=cache_dir, out_dir=out_dir,
                         only=only, from_=from_, until=until, force=force, frames=frames, executor=pool,
                         progress=progress, lock_timeout=lock_timeout, allow_large=allow_large, events=events)
        except BaseException:
            pool.abort()  # as the CLI: do not wait for queued or running jobs
            raise
        pool.close()
        return report
    registry = registry or Registry.from_entry_points()
    config = load_config(config_path, registry, overrides)
    graph = select(build_graph(config), only, from_, until)
    if config.scene.fluid is None and any(kind != "mesh_import" for kind in graph.nodes):
        # refused by sdf_bake only after the walls had been imported and cached, naming no file or line
        raise ConfigError(f"{config.path}: the config has no 'fluid' section; its spacing sets the SDF grid and the "
                          f"particles, which {', '.join(graph.outputs)} need")
    check_stages(config, graph)
    for f in force:
        # graph.nodes also holds the stages --only/--from read from the cache: forcing one was ignored without a word
        if f != "all" and f not in graph.runnable:
            runs = [k for k in graph.order() if k in graph.runnable]
            raise ConfigError(f"--force {f}: not a stage this run includes ({', '.join(runs)})")
    cache = Cache(Path(cache_dir) if cache_dir else default_cache_dir(config), lock_timeout=lock_timeout)
    out = Path(os.path.abspath(out_dir)) if out_dir else default_out_dir(config)
    real_out, real_cache = Path(os.path.realpath(out)), Path(os.path.realpath(cache.root))
    if real_out == real_cache or real_cache in real_out.parents or real_out in real_cache.parents:
        # the cache's entries would be published over (or its sweep would delete published outputs)
        raise ConfigError(f"the output folder {out} and the cache folder {cache.root} overlap; "
                          "choose another --out or --cache (nothing was changed)")
    check_out_dir(out, [n for n in graph.outputs] + ["run.json"], shot=shot_of(config))
    why = unwritable(cache.root)
    if why is not None:  # found before any stage runs, not when the first entry is committed
        raise ConfigError(f"cache folder {cache.root} cannot be written: {why} (choose another with --cache)")
    try:
        try:
            p = plan(config, graph, cache, frames)
        except OSError as exc:  # an input file that exists but cannot be read (permissions, I/O)
            raise StageFailed(f"cannot read input file {exc.filename}: {exc.strerror or exc}", user_error=True) from None
        for kind, node in graph.nodes.items():
            changed = changed_since_loaded(p.components[kind]["code"])
            if changed:
                raise CodeChanged(f"stage {node.label}: {', '.join(changed)} changed on disk since this process "
                                  "imported it; run again in a new process (or restart the notebook's kernel) to "
                                  "run the new code (nothing was run)")
        allow_large = allow_large or config.allow_large
        check_size(p, allow_large=allow_large)
        with ExitStack() as held:
            try:
                held.enter_context(cache.in_use())
            except OSError as exc:  # a full disk, a read-only cache: one line and a log, as any cache write
                raise _outside(f"cache {cache.root}", exc, cache) from exc
            return execute(p, out_dir=out, force=frozenset(force), executor=executor, progress=progress,
                           events=events, allow_large=allow_large)
    except (PipelineError, KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - anything else is still one line, exit 1, and a log
        raise _outside("pipeline", exc, cache) from exc
