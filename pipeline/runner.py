"""Run a config's graph against the cache: keys, hits, misses, per-frame jobs, publishing, run.json.

A stage's key is the sha256 of its implementation and code version, its validated params (defaults
included), the scene sections it reads, its upstream keys and the content hashes of the external files
it names. A per-frame stage's frame key adds the frame index to its stage key. Whole-run stages run in
dependency order in this process; per-frame jobs go to the executor.
"""
from __future__ import annotations

import faulthandler
import logging
import os
import shutil
import sys
import threading
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .cache import Cache, file_sha256, hash_key, owner_tag
from .config import Config, dump_model, load_config
from .errors import CacheMissError, ConfigError, FrameError, PipelineError, StageFailed
from .estimate import check_size
from .executors import Executor, make_executor
from .graph import Graph, Node, build_graph
from .publish import check_out_dir, publish, write_run_json
from .registry import Registry
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


@dataclass
class RunReport:
    config: str
    scene: str
    cache: str
    out: str
    seconds: float = 0.0
    stages: list[StageReport] = field(default_factory=list)
    outputs: dict[str, str] = field(default_factory=dict)

    def stage(self, kind: str) -> StageReport:
        return next(s for s in self.stages if s.kind == kind)

    def ran(self) -> list[str]:
        return [s.kind for s in self.stages if s.status != "cached"]


@dataclass
class Plan:
    config: Config
    graph: Graph
    cache: Cache
    keys: dict[str, str]
    components: dict[str, dict[str, Any]]
    frames: tuple[int, ...]


# -- keys ------------------------------------------------------------------------------------------
def _context(config: Config, node: Node, out_dir: Path, frames: tuple[int, ...],
             checkpoint_dir: Path | None = None) -> Context:
    sections = config.sections()
    ctx = Context(out_dir=out_dir, scene={s: sections[s] for s in node.cls.reads}, config_dir=config.dir,
                  frames=frames, log=logging.getLogger(f"stage.{node.label}"), checkpoint_dir=checkpoint_dir)
    return ctx


def plan(config: Config, graph: Graph, cache: Cache, frames: tuple[int, ...] | None = None) -> Plan:
    count = config.scene.scene.frames.count
    if frames is None:
        frames = tuple(range(count))
    bad = [f for f in frames if not 0 <= f < count]
    if bad:
        raise ConfigError(f"--frames: frame {bad[0]} is outside the scene's frames 0..{count - 1}")
    sections = {k: dump_model(v) for k, v in config.sections().items()}
    keys: dict[str, str] = {}
    components: dict[str, dict[str, Any]] = {}
    for kind in graph.order():
        node = graph.nodes[kind]
        files: dict[str, str] = {}
        stage = node.cls()
        try:
            external = stage.external_files(_context(config, node, config.dir, frames), node.params)
        except StageError as e:
            raise StageFailed(f"stage {node.label}: {e}", user_error=True) from None
        for f in external:
            f = Path(f)
            if not f.is_file():
                raise StageFailed(f"stage {node.label}: input file not found: {f}", user_error=True)
            files[str(f)] = file_sha256(f)
        comp = {
            "stage": node.label,
            "version": node.cls.version,
            "params": dump_model(node.params),
            "scene": {s: sections[s] for s in node.cls.reads},
            "inputs": {name: keys[producer] for name, producer in node.inputs},
            "files": files,
        }
        components[kind] = comp
        keys[kind] = hash_key(comp)
    return Plan(config=config, graph=graph, cache=cache, keys=keys, components=components, frames=tuple(frames))


def frame_key(stage_key: str, frame: int) -> str:
    return hash_key({"stage_key": stage_key, "frame": frame})


# -- per-frame job (top level so process pools can pickle it) -----------------------------------
@dataclass
class FrameJob:
    cache_root: str
    kind: str
    stage_cls: type[Stage]
    params: Any
    scene: dict[str, Any]
    config_dir: str
    frames: tuple[int, ...]
    inputs: dict[str, Artifact]
    stage_key: str
    frame: int
    force: bool
    lock_timeout: float | None = None
    fault_log: str | None = None  # the run's log: faulthandler writes native crashes of workers there


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


def run_frame_job(job: FrameJob) -> tuple[int, str, float, bool]:
    """Compute one frame's entry unless it is cached; returns (frame, entry path, seconds, ran).
    Any failure comes back as FrameError naming the frame (with the worker's traceback)."""
    try:
        return _frame_job(job)
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # noqa: BLE001 - re-raised with the frame, picklable
        user = isinstance(exc, StageError) or (isinstance(exc, PipelineError) and exc.exit_code == 2)
        raise FrameError(job.frame, f"{type(exc).__name__}: {exc}" if not user else str(exc),
                         "".join(traceback.format_exception(exc)), user) from None


def _frame_job(job: FrameJob) -> tuple[int, str, float, bool]:
    _enable_faulthandler(job.fault_log)
    cache = Cache(Path(job.cache_root), lock_timeout=job.lock_timeout)
    key = frame_key(job.stage_key, job.frame)
    with cache.lock(key, f"stage {job.stage_cls.qualname()} frame {job.frame}"):
        hit = None if job.force else cache.lookup(job.kind, key)
        if hit is not None:
            return job.frame, str(hit.path), float(hit.manifest.get("seconds", 0.0)), False
        tmp = cache.new_tmp(key)
        t0 = time.perf_counter()
        try:
            ctx = Context(out_dir=tmp, scene=job.scene, config_dir=Path(job.config_dir), frames=job.frames,
                          log=logging.getLogger(f"stage.{job.stage_cls.qualname()}"))
            job.stage_cls().run_frame(ctx, job.inputs, job.params, job.frame)
            seconds = time.perf_counter() - t0
            entry = cache.commit(job.kind, key, tmp, {"stage_key": job.stage_key, "frame": job.frame,
                                                      "stage": job.stage_cls.qualname(), "seconds": seconds})
        except BaseException:
            cache.discard(tmp)
            raise
    return job.frame, str(entry.path), seconds, True


# -- running ---------------------------------------------------------------------------------------
class _Progress:
    """Rich progress bars for long stages; silent when quiet or not on a terminal."""

    def __init__(self, enabled: bool) -> None:
        self._bar = None
        if enabled:
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
        if self._bar is None:
            return Progress()
        task = self._bar.add_task(description, total=total)
        return Progress(lambda amount: self._bar.advance(task, amount))


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


def _fail(node: Node, key: str, config: Config, exc: BaseException, cache: Cache) -> StageFailed:
    if isinstance(exc, FrameError):
        where = f"stage {node.label} frame {exc.frame}"
        if exc.user_error:
            return StageFailed(f"{where}: {exc.cause}", user_error=True)
        saved = write_log(cache, f"{node.kind}-{key[:12]}-frame{exc.frame}", exc.traceback)
        return StageFailed(f"{where} failed (key {key[:12]}, config {config.path.name}): {exc.cause} ({saved})",
                           user_error=False)
    if isinstance(exc, StageError):
        return StageFailed(f"stage {node.label}: {exc}", user_error=True)
    if isinstance(exc, PipelineError):
        return StageFailed(f"stage {node.label}: {exc}", user_error=exc.exit_code == 2)
    if type(exc).__name__ == "BrokenProcessPool":
        exc_text = "a worker process died (killed, out of memory or a native crash; faulthandler output in the run log)"
    else:
        exc_text = f"{type(exc).__name__}: {exc}"
    saved = write_log(cache, f"{node.kind}-{key[:12]}", "".join(traceback.format_exception(exc)))
    return StageFailed(f"stage {node.label} failed (key {key[:12]}, config {config.path.name}): "
                       f"{exc_text} ({saved})", user_error=False)


def _outside(what: str, exc: BaseException, cache: Cache) -> StageFailed:
    """An error outside a stage's own work (publishing, saving state): exit 1, one line, a log."""
    saved = write_log(cache, f"{what.split()[0]}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}",
                      "".join(traceback.format_exception(exc)))
    return StageFailed(f"{what}: {type(exc).__name__}: {exc} ({saved})", user_error=False)


def execute(p: Plan, *, out_dir: Path, force: frozenset[str] = frozenset(), executor: Executor | None = None,
            progress: bool = False) -> RunReport:
    """Run the plan. Inline, stages go one by one in dependency order; with a pool executor, independent
    branches (e.g. render frames and export) are driven concurrently by threads of this process while
    their per-frame jobs run in the pool's worker processes. faulthandler writes native crashes (VTK,
    numba) of this process and of the workers into the run's log under the cache's logs/."""
    cache = p.cache
    try:
        cache.root.mkdir(parents=True, exist_ok=True)
        cache.sweep_tmp()
        (cache.root / "logs").mkdir(exist_ok=True)
        fault_log = cache.root / "logs" / f"run-{time.strftime('%Y%m%d-%H%M%S')}-{owner_tag()}.log"
        fault_fh = open(fault_log, "w")
    except OSError as exc:
        raise _outside(f"cache {cache.root}", exc, cache) from exc
    was_enabled = faulthandler.is_enabled()
    faulthandler.enable(fault_fh)
    try:
        return _execute(p, out_dir, force, executor, progress, str(fault_log))
    finally:
        faulthandler.disable()
        if was_enabled:  # e.g. pytest's or PYTHONFAULTHANDLER's, to the real stderr
            try:
                faulthandler.enable(sys.__stderr__)
            except (AttributeError, ValueError, OSError):
                pass
        fault_fh.close()
        try:
            if fault_log.stat().st_size == 0:
                fault_log.unlink()
        except OSError:
            pass


def _execute(p: Plan, out_dir: Path, force: frozenset[str], executor: Executor | None, progress: bool,
             fault_log: str) -> RunReport:
    config, graph, cache = p.config, p.graph, p.cache
    t_start = time.perf_counter()
    report = RunReport(config=str(config.path), scene=config.name, cache=str(cache.root), out=str(out_dir))
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
        t0 = time.perf_counter()
        try:
            if node.per_frame:
                sr, frames = _run_per_frame(p, node, key, inputs, runnable, forced, executor, bars, fault_log)
                made = {out: Artifact(name=out, key=key, frames=frames) for out in node.cls.outputs}
            else:
                sr, path = _run_whole(p, node, key, inputs, runnable, forced, bars)
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
            try:
                cache.write_state(config.path, state)
            except OSError as exc:
                raise _outside(f"stage {graph.nodes[kind].label}: saving the cache state", exc, cache) from exc
        log.debug("%-16s %-16s %s  %s", kind, sr.implementation, sr.key[:12], sr.status)

    order = graph.order()
    with _Progress(progress) as bars:
        if executor.name == "inline" or len(order) < 2:
            for kind in order:
                finish(kind, run_node(kind, bars))
        else:
            _run_branches(graph, order, lambda k: run_node(k, bars), finish)
    report.stages = [reports[k] for k in order]
    try:
        # two runs publishing into one folder (the same config run twice) take turns
        with cache.lock(hash_key({"publish": str(out_dir)}), f"publish into {out_dir}"):
            report.outputs = publish(graph, artifacts, out_dir, p.frames)
            report.seconds = time.perf_counter() - t_start
            write_run_json(report, out_dir)
    except OSError as exc:
        raise _outside(f"publish into {out_dir}", exc, cache) from exc
    return report


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
               bars: _Progress) -> tuple[StageReport, Path]:
    cache, config = p.cache, p.config
    sr = StageReport(node.kind, node.cls.name, node.cls.version, key, "cached")
    hit = None if (forced and runnable) else cache.lookup(node.kind, key)
    if hit is not None:
        sr.seconds = float(hit.manifest.get("seconds", 0.0))
        return sr, hit.path
    if not runnable:
        raise CacheMissError(f"stage {node.label} is not cached (key {key[:12]}) and the selection does not run it; "
                             f"run without --only/--from first")
    with cache.lock(key, f"stage {node.label}"):
        hit = None if forced else cache.lookup(node.kind, key)  # another run may have made it meanwhile
        if hit is not None:
            sr.seconds = float(hit.manifest.get("seconds", 0.0))
            return sr, hit.path
        tmp = cache.new_tmp(key)
        ctx = _context(config, node, tmp, p.frames, checkpoint_dir=cache.checkpoint_dir(key))
        ctx.make_progress = bars.make
        t0 = time.perf_counter()
        try:
            node.cls().run(ctx, inputs, node.params)
            seconds = time.perf_counter() - t0
            entry = cache.commit(node.kind, key, tmp, {
                "stage": node.label, "version": node.cls.version, "seconds": seconds,
                "components": p.components[node.kind]})
        except BaseException as exc:
            cache.discard(tmp)
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            raise _fail(node, key, config, exc, cache) from exc
        shutil.rmtree(cache.checkpoint_dir(key), ignore_errors=True)
    sr.status = "forced" if forced else "ran"
    return sr, entry.path


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
    if not todo:
        return sr, frames
    if not runnable:
        raise CacheMissError(f"stage {node.label} has {len(todo)} frame(s) not cached (first: {todo[0]}) and the "
                             f"selection does not run it; run without --only/--from first")
    sections = config.sections()
    jobs = [FrameJob(cache_root=str(cache.root), kind=node.kind, stage_cls=node.cls, params=node.params,
                     scene={s: sections[s] for s in node.cls.reads}, config_dir=str(config.dir), frames=p.frames,
                     inputs=inputs, stage_key=key, frame=f, force=forced, lock_timeout=cache.lock_timeout,
                     fault_log=fault_log) for f in todo]
    bar = bars.make(f"{node.kind} frames", len(jobs))
    try:
        for frame, path, _seconds, ran in executor.map_unordered(run_frame_job, jobs):
            frames[frame] = Path(path)
            sr.frames_ran += int(ran)
            bar.advance()
    except BaseException as exc:
        if isinstance(exc, (KeyboardInterrupt, SystemExit)):
            raise
        raise _fail(node, key, config, exc, cache) from exc
    sr.status = "forced" if forced else "ran"
    return sr, dict(sorted(frames.items()))


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
    if until:
        graph = graph.until(until)
    if from_:
        graph = graph.from_(from_)
    return graph


def parse_frames(text: str | None) -> tuple[int, ...] | None:
    """``"0:10"`` (end exclusive), ``"5"``, or ``"0,3,7"``."""
    if text is None:
        return None
    try:
        if ":" in text:
            a, _, b = text.partition(":")
            return tuple(range(int(a or 0), int(b)))
        return tuple(int(t) for t in text.split(","))
    except ValueError:
        raise ConfigError(f"--frames {text}: expected START:END, N or N,M,...") from None


def run(config_path: str | Path, *, registry: Registry | None = None, overrides: tuple[str, ...] = (),
        cache_dir: str | Path | None = None, out_dir: str | Path | None = None, only: str | None = None,
        from_: str | None = None, until: str | None = None, force: tuple[str, ...] = (),
        frames: tuple[int, ...] | None = None, executor: Executor | None = None,
        progress: bool = False, lock_timeout: float | None = None, allow_large: bool = False) -> RunReport:
    """Run what the config's outputs need; returns the report (also written to out/run.json).

    Refuses (exit 2, nothing written) an output folder holding things the pipeline did not publish
    where it would write, and a plan whose memory estimate exceeds the available memory unless
    ``allow_large`` (or the config's ``allow_large: true``)."""
    registry = registry or Registry.from_entry_points()
    config = load_config(config_path, registry, overrides)
    graph = select(build_graph(config), only, from_, until)
    for f in force:
        if f != "all" and f not in graph.nodes:
            raise ConfigError(f"--force {f}: not a stage this run includes ({', '.join(graph.order())})")
    cache = Cache(Path(cache_dir) if cache_dir else default_cache_dir(config), lock_timeout=lock_timeout)
    out = Path(os.path.abspath(out_dir)) if out_dir else default_out_dir(config)
    check_out_dir(out, [n for n in graph.outputs] + ["run.json"])
    try:
        try:
            p = plan(config, graph, cache, frames)
        except OSError as exc:  # an input file that exists but cannot be read (permissions, I/O)
            raise StageFailed(f"cannot read input file {exc.filename}: {exc.strerror or exc}", user_error=True) from None
        check_size(p, allow_large=allow_large or config.allow_large)
        return execute(p, out_dir=out, force=frozenset(force), executor=executor, progress=progress)
    except (PipelineError, KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - anything else is still one line, exit 1, and a log
        raise _outside("pipeline", exc, cache) from exc


# -- status ----------------------------------------------------------------------------------------
@dataclass
class StageStatus:
    kind: str
    implementation: str
    key: str
    state: str  # cached / stale / missing / partial
    reason: str
    seconds: float | None


def _diff(old: dict[str, Any], new: dict[str, Any], graph: Graph) -> str:
    if old.get("stage") != new.get("stage"):
        return f"implementation {old.get('stage')} -> {new.get('stage')}"
    if old.get("version") != new.get("version"):
        return f"code version {old.get('version')} -> {new.get('version')}"
    for section in ("params", "scene"):
        a, b = _flatten(old.get(section, {})), _flatten(new.get(section, {}))
        changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        if changed:
            k = changed[0]
            more = f" (+{len(changed) - 1} more)" if len(changed) > 1 else ""
            return f"{section}: {k} {a.get(k, '<unset>')!r} -> {b.get(k, '<unset>')!r}{more}"
    oi, ni = old.get("inputs", {}), new.get("inputs", {})
    for name in sorted(set(oi) | set(ni)):
        if oi.get(name) != ni.get(name):
            return f"upstream {name} changed"
    of, nf = old.get("files", {}), new.get("files", {})
    for name in sorted(set(of) | set(nf)):
        if of.get(name) != nf.get(name):
            return f"input file changed: {name}"
    return "key schema changed"


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix.rstrip("."): value}


def status(config_path: str | Path, *, registry: Registry | None = None, overrides: tuple[str, ...] = (),
           cache_dir: str | Path | None = None, frames: tuple[int, ...] | None = None) -> list[StageStatus]:
    registry = registry or Registry.from_entry_points()
    config = load_config(config_path, registry, overrides)
    graph = build_graph(config)
    cache = Cache(Path(cache_dir) if cache_dir else default_cache_dir(config))
    p = plan(config, graph, cache, frames)
    last = cache.read_state(config.path)
    rows: list[StageStatus] = []
    for kind in graph.order():
        node, key = graph.nodes[kind], p.keys[kind]
        prev = last.get(kind, {})
        if node.per_frame:
            hits = [cache.lookup(kind, frame_key(key, f)) for f in p.frames]
            n = sum(h is not None for h in hits)
            seconds = sum(float(h.manifest.get("seconds", 0)) for h in hits if h is not None) if n else None
            if n == len(p.frames):
                rows.append(StageStatus(kind, node.cls.name, key, "cached", f"{n} frames", seconds))
                continue
            if n:
                rows.append(StageStatus(kind, node.cls.name, key, "partial", f"{n}/{len(p.frames)} frames cached", seconds))
                continue
        else:
            hit = cache.lookup(kind, key)
            if hit is not None:
                rows.append(StageStatus(kind, node.cls.name, key, "cached", "up to date",
                                        float(hit.manifest.get("seconds", 0.0))))
                continue
            if cache.exists(kind, key):
                rows.append(StageStatus(kind, node.cls.name, key, "stale", "entry damaged (files differ from manifest)", None))
                continue
        if prev.get("key") and prev["key"] != key:
            rows.append(StageStatus(kind, node.cls.name, key, "stale", _diff(prev.get("components", {}), p.components[kind], graph),
                                    prev.get("seconds")))
        else:
            rows.append(StageStatus(kind, node.cls.name, key, "missing", "never run with these inputs", None))
    return rows


def clean(config_path: str | Path, *, registry: Registry | None = None, stage: str | None = None,
          cache_dir: str | Path | None = None) -> int:
    """Remove this config's cache entries (all frames), or only one stage's; returns how many."""
    registry = registry or Registry.from_entry_points()
    config = load_config(config_path, registry)
    graph = build_graph(config)
    if stage is not None and stage not in graph.nodes:
        raise ConfigError(f"--stage {stage}: not a stage of this config ({', '.join(graph.order())})")
    cache = Cache(Path(cache_dir) if cache_dir else default_cache_dir(config))
    p = plan(config, graph, cache, tuple(range(config.scene.scene.frames.count)))
    last = cache.read_state(config.path)
    removed = 0
    for kind in graph.order():
        if stage is not None and kind != stage:
            continue
        keys = {p.keys[kind]} | ({last[kind]["key"]} if kind in last else set())
        for key in keys:
            if graph.nodes[kind].per_frame:
                removed += sum(cache.remove(kind, frame_key(key, f)) for f in p.frames)
            else:
                removed += int(cache.remove(kind, key))
                shutil.rmtree(cache.checkpoint_dir(key), ignore_errors=True)
    return removed
