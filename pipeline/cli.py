"""The ``pipeline`` command: a thin click layer over the library; user mistakes exit 2 with one line."""
from __future__ import annotations

import logging
import os
import signal
import shutil
import sys
import threading
from pathlib import Path

import click

from . import runner
from .cache import check_env
from .status import clean_cache, status as config_status
from .errors import PipelineError
from .registry import Registry
from .stage import STAGE_KINDS

KINDS = click.Choice(STAGE_KINDS)
# numba probes TBB first and warns about the old TBB some distributions ship; OpenMP is always there
os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")


def _setup_logging(verbose: int, quiet: bool) -> None:
    from rich.console import Console
    from rich.logging import RichHandler

    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    if not sys.stderr.isatty():  # a log file: whole lines (rich wrapped them at 80 columns), each with its time
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("[%(asctime)s] %(levelname)-7s %(message)s", datefmt="%X"))
        logging.basicConfig(level=level, handlers=[handler], force=True)
        return
    logging.basicConfig(level=level, format="%(message)s", datefmt="[%X]",
                        handlers=[RichHandler(console=Console(stderr=True), show_path=False, rich_tracebacks=False, markup=False)], force=True)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a batch scheduler's time limit or preemption, docker stop) or SIGHUP (the ssh session that started
    the run closed; it ended without a word, exit 129): stopped like Ctrl-C, exit 128 + the signal's number."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__()
        self.signum = int(signum)


def _terminated(signum, frame):
    raise Terminated(signum)


def _hang_up_handled() -> None:
    """SIGHUP stops the run like SIGTERM. multiprocessing's resource tracker (a process of the run's group, which
    ignores SIGINT and SIGTERM itself) is started first with SIGHUP ignored, which it keeps: killed by the hang-up,
    it printed a KeyError for each of the stopped pool's semaphores."""
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
    except Exception:  # noqa: BLE001 - best effort: without it the hang-up is still handled
        pass
    signal.signal(signal.SIGHUP, _terminated)


def _guard(fn):
    """Map every error to one line and an exit code: 2 for user mistakes, 1 for failures (the library
    saves tracebacks under the cache's logs/), 130 for Ctrl-C."""

    def wrapper(*args, **kwargs):
        try:
            check_env()  # PIPELINE_LOCK_TIMEOUT=abc: one line naming it, not a traceback
            _check_options(kwargs)
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGTERM, _terminated)
                if signal.getsignal(signal.SIGHUP) is signal.SIG_DFL:  # not under nohup, which ignores it
                    _hang_up_handled()
            return fn(*args, **kwargs)
        except PipelineError as e:
            click.echo(f"error: {_one_line(e)}", err=True)
            sys.exit(e.exit_code)
        except KeyboardInterrupt as e:
            signum = e.signum if isinstance(e, Terminated) else signal.SIGINT
            what = {signal.SIGTERM: "terminated (SIGTERM)", signal.SIGHUP: "hung up (SIGHUP)"}.get(signum, "interrupted")
            try:  # after a hang-up the terminal may be gone
                click.echo(f"{what}; the cache holds only finished entries (unfinished ones are swept by the next run)",
                           err=True)
            except OSError:
                pass
            # a stage may still run in a thread (a simulation): exit now instead of waiting for it, after
            # multiprocessing's own exit clean-up (the stopped pool's semaphores, no warnings)
            try:
                import multiprocessing.util

                multiprocessing.util._exit_function()
            except Exception:  # noqa: BLE001 - best effort before a hard exit
                pass
            sys.stderr.flush()
            sys.stdout.flush()
            os._exit(128 + int(signum))
        except click.exceptions.Exit:
            raise
        except BrokenPipeError:  # `pipeline stages | head`: the reader left; nothing to say to it
            try:
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
            except OSError:
                pass
            sys.exit(141)
        except Exception as e:  # noqa: BLE001 - outside the library's contract: still one line
            click.echo(f"error: {type(e).__name__}: {_one_line(e)}", err=True)
            sys.exit(1)

    wrapper.__name__ = fn.__name__
    wrapper.__doc__ = fn.__doc__
    return wrapper


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="fluid-pipeline")
def main() -> None:
    """Polygon/USD walls -> SDF -> SPH/MPS fluid -> surface -> wall snap -> frames, movie, OpenUSD."""


class FolderPath(click.Path):
    """A folder option's path; an empty or blank value (``--cache "$CACHE"`` with the variable unset) stays the
    text it is, for _guard to refuse: click made it Path(""), the current folder, so a run cached (and swept)
    or published into wherever it was started."""

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            return value
        return super().convert(value, param, ctx)


FOLDER_OPTIONS = {"cache_dir": "--cache", "out_dir": "--out"}


def _check_options(kwargs: dict) -> None:
    """Refuse a blank folder option and a repeated --frames (one line, exit 2); ``kwargs["frames"]`` becomes its
    one value (or None)."""
    for name, flag in FOLDER_OPTIONS.items():
        value = kwargs.get(name)
        if isinstance(value, str) and not value.strip():
            raise PipelineError(f"{flag} {value!r}: an empty path (an unset shell variable?); give a folder, or leave "
                                "the option out for the default")
    if "frames" in kwargs:
        given = kwargs["frames"] or ()
        if len(given) > 1:
            raise PipelineError(f"--frames given {len(given)} times ({', '.join(given)}): give one selection "
                                "(N,M,... lists several frames)")
        kwargs["frames"] = given[0] if given else None


config_arg = click.argument("config", type=click.Path(path_type=Path))
set_opt = click.option("--set", "overrides", multiple=True, metavar="PATH=VALUE",
                       help="Override a config value, e.g. --set simulate.cfl=0.3 (repeatable).")
cache_opt = click.option("--cache", "cache_dir", type=FolderPath(path_type=Path),
                         help="Cache folder (default: .pipeline/ beside the config).")
# multiple=True only to see a repeated --frames (click keeps the last, silently dropping the others); _guard
# refuses a repeat and passes the one value on
frames_opt = click.option("--frames", multiple=True, help="Frames for per-frame stages: START:END (end exclusive), N or N,M.")


@main.command()
@click.argument("configs", nargs=-1, required=True, type=click.Path(path_type=Path))
@set_opt
@cache_opt
@frames_opt
@click.option("--out", "out_dir", type=FolderPath(path_type=Path), help="Output folder (default: out/<scene>/ beside the config).")
@click.option("--only", type=KINDS, help="Run only this stage; its inputs must be cached.")
@click.option("--from", "from_", type=KINDS, help="Run this stage and the stages downstream of it; upstream from cache. Outputs not made from "
                   "it (export for --from render) are not made, and need not be cached.")
@click.option("--until", type=KINDS, help="Run up to and including this stage.")
@click.option("--force", multiple=True, type=click.Choice(STAGE_KINDS + ("all",)), help="Recompute this stage even if cached.")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Local worker processes for per-frame stages (with --executor dask and no --scheduler: the "
                   "LocalCluster's worker processes).")
@click.option("--executor", type=click.Choice(["auto", "inline", "processes", "dask"]), default="auto", show_default=True,
              help="With several configs and dask, each shot is a task on the cluster.")
@click.option("--scheduler", help="Dask scheduler address for --executor dask, e.g. tcp://host:8786 "
                                  "(default: a LocalCluster of --workers processes).")
@click.option("--lock-timeout", type=click.FloatRange(0), default=None, metavar="SECONDS",
              help="Give up waiting for another run's lock on a cache entry after this long "
                   "(default 3600, or env PIPELINE_LOCK_TIMEOUT).")
@click.option("--yes", "allow_large", is_flag=True,
              help="Run even if the plan's memory estimate exceeds the available memory (config: allow_large: true).")
@click.option("-v", "--verbose", count=True, help="More logging.")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors; no progress bars.")
@_guard
def run(configs, overrides, cache_dir, frames, out_dir, only, from_, until, force, workers, executor, scheduler,
        lock_timeout, allow_large, verbose, quiet):
    """Run every stage the config's outputs need (cached stages are not run again). Several configs are
    a batch of shots: all run, one summary table at the end, exit 1 if any failed."""
    from .executors import make_executor

    _setup_logging(verbose, quiet)
    if scheduler and executor != "dask":
        raise PipelineError("--scheduler needs --executor dask")
    if len(configs) > 1:
        if out_dir is not None:
            raise PipelineError("--out: with several configs each shot publishes to out/<scene>/ beside its config")
        _run_batch(configs, dict(overrides=tuple(overrides), cache_dir=cache_dir, frames=runner.parse_frames(frames),
                                 only=only, from_=from_, until=until, force=tuple(force), lock_timeout=lock_timeout,
                                 allow_large=allow_large), executor, workers, scheduler, quiet)
        return
    config = configs[0]
    ex = make_executor(executor, workers, scheduler)
    try:
        report = runner.run(config, overrides=tuple(overrides), cache_dir=cache_dir, out_dir=out_dir, only=only,
                            from_=from_, until=until, force=tuple(force), frames=runner.parse_frames(frames),
                            executor=ex, progress=_progress_mode(quiet), lock_timeout=lock_timeout,
                            allow_large=allow_large)
    except BaseException:
        ex.abort()  # stop the workers now (Ctrl-C, a failed frame): do not wait for queued or running jobs
        raise
    ex.close()
    if not quiet:
        for s in report.stages:
            extra = f"  {s.frames_ran}/{s.frames_total} frames computed" if s.frames_total else ""
            click.echo(f"  {s.kind:<16} {s.implementation:<15} {s.key[:12]}  {s.status:<7} {s.seconds:8.2f} s{extra}")
        for name, path in report.outputs.items():
            # top-level files named, every file counted (usd/ keeps its assets/ and layer folders below)
            files = sorted(p.name for p in Path(path).iterdir() if p.is_file())
            total = sum(1 for p in Path(path).rglob("*") if p.is_file())
            shown = ", ".join(files[:3]) + (f" ... ({total} files)" if total > min(len(files), 3) else "")
            click.echo(f"  -> {name}: {path}/  [{shown}]")
        click.echo(f"done in {report.seconds:.2f} s; report: {Path(report.out) / 'run.json'}")


def _progress_mode(quiet: bool) -> bool | str:
    """Bars on a terminal; a line every half minute of a long stage in a log file (a farm's); nothing when quiet."""
    return False if quiet else (True if sys.stderr.isatty() else "log")


def _run_batch(configs, options, executor, workers, scheduler, quiet) -> None:
    from rich.console import Console
    from rich.table import Table

    from .batch import run_batch
    from .live import LiveView

    with LiveView([str(c) for c in configs], enabled=not quiet and sys.stderr.isatty()) as view:
        outcomes = run_batch(list(configs), options, executor=executor, workers=workers, scheduler=scheduler,
                             events=view)
    if not quiet:
        table = Table("shot", "status", "wall (s)", "stages run", "stages cached")
        for o in outcomes:
            v = o.value or {}
            table.add_row(o.label, "[red]failed[/]" if o.error else "[green]ok[/]", f"{o.seconds:.2f}",
                          str(v.get("ran", "")), str(v.get("cached", "")))
        Console(width=max(100, 60 + max(len(o.label) for o in outcomes))).print(table)
    failed = [o for o in outcomes if o.error]
    for o in failed:  # a message that names the config already does not get it twice
        click.echo(f"error: {o.error}" if o.error.startswith(o.label) else f"error: {o.label}: {o.error}", err=True)
    if failed:
        click.echo(f"{len(failed)} of {len(outcomes)} shots failed", err=True)
        sys.exit(1)


@main.command()
@config_arg
@set_opt
@cache_opt
@frames_opt
@_guard
def status(config, overrides, cache_dir, frames):
    """Which stages are cached, stale (and why) or missing."""
    from rich.console import Console
    from rich.table import Table

    rows = config_status(config, overrides=tuple(overrides), cache_dir=cache_dir, frames=runner.parse_frames(frames))
    table = Table("stage", "implementation", "key", "state", "reason", "last (s)")
    colour = {"cached": "green", "stale": "yellow", "missing": "red", "partial": "yellow", "running": "cyan"}
    for r in rows:
        table.add_row(r.kind, r.implementation, r.key[:12], f"[{colour[r.state]}]{r.state}[/]", r.reason,
                      "" if r.seconds is None else f"{r.seconds:.2f}")
    # piped (a CI log, | cat) rich assumed 80 columns and cut 'surface_extract' to 'surface_ext…'
    Console(width=None if sys.stdout.isatty() else 160).print(table)


@main.command()
@click.option("--json", "as_json", is_flag=True, help="One JSON object per implementation (machine readable).")
@_guard
def stages(as_json):
    """Every installed stage implementation, its version and parameters; exit 1 if one cannot be loaded."""
    import json

    from rich.console import Console
    from rich.table import Table

    reg = Registry.from_entry_points()
    rows = []
    for kind, name, source in reg.entries():
        row = {"kind": kind, "name": name, "source": source}
        try:
            cls = reg.get(kind, name)
        except PipelineError as e:
            rows.append({**row, "error": str(e)})
            continue
        rows.append({**row, "version": cls.version, "default": bool(cls.default), "per_frame": bool(cls.per_frame),
                     "inputs": list(cls.inputs), "optional_inputs": list(cls.optional_inputs),
                     "outputs": list(cls.outputs), "description": cls.description,
                     "params": {n: {"default": None if f.is_required() else f.get_default(call_default_factory=True),
                                    "required": f.is_required(), "description": f.description or ""}
                                for n, f in cls.Params.model_fields.items()}})
    broken = [r for r in rows if "error" in r]
    if as_json:
        for r in rows:
            click.echo(json.dumps(r, default=str))
    else:
        table = Table("stage", "implementation", "version", "per frame", "parameters (default)")
        for r in rows:
            if "error" in r:
                table.add_row(r["kind"], r["name"], "-", "-", f"[red]{r['error']}[/]")
                continue
            params = ", ".join(f"{n}={p['default']!r}" if not p["required"] else f"{n} (required)"
                               for n, p in r["params"].items())
            table.add_row(r["kind"], r["name"] + (" *" if r["default"] else ""), r["version"],
                          "yes" if r["per_frame"] else "no", params or "-")
        Console(width=max(120, shutil.get_terminal_size((200, 24)).columns)).print(table)
        click.echo("* = default implementation of its kind")
    if broken:
        click.echo(f"error: {len(broken)} stage implementation(s) cannot be loaded: "
                   + "; ".join(f"{r['kind']}.{r['name']} ({r['source']})" for r in broken), err=True)
        sys.exit(1)


@main.command()
@config_arg
@set_opt
@cache_opt
@click.option("--stage", type=KINDS, help="Only this stage's entries.")
@_guard
def clean(config, overrides, cache_dir, stage):
    """Remove the config's cache entries (or one stage's): those of the config as it is now and of its
    last run; with --set (parsed as run's), those of the config with these overrides. Entries made under
    other --set overrides or earlier versions of the config stay (the cache does not record which config
    made an entry: entries are shared by every config that gives a stage the same inputs); give the same
    --set to drop a variant's, or remove the cache folder to drop everything."""
    n, missing = clean_cache(config, stage=stage, cache_dir=cache_dir, overrides=tuple(overrides))
    if missing is not None:  # exit 0 as `status` of a missing cache: nothing is cached, so nothing to remove
        click.echo(f"no cache at {missing}; nothing removed")
        return
    click.echo(f"removed {n} cache entr{'y' if n == 1 else 'ies'}")


@main.command()
@click.argument("study", type=click.Path(path_type=Path))
@cache_opt
@click.option("--out", "out_dir", type=FolderPath(path_type=Path), help="Report folder (default: out/<study>/ beside it).")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Variants run in parallel processes (with --executor dask and no --scheduler: the "
                   "LocalCluster's worker processes).")
@click.option("--executor", type=click.Choice(["auto", "inline", "dask"]), default="auto", show_default=True,
              help="dask: each variant is a task on Dask worker processes.")
@click.option("--scheduler", help="Dask scheduler address for --executor dask, e.g. tcp://host:8786.")
@click.option("-q", "--quiet", is_flag=True)
@_guard
def study(study, cache_dir, out_dir, workers, executor, scheduler, quiet):
    """Run the variants of a study and report accuracy against time (table + plots)."""
    from .live import LiveView
    from .study import load_study, run_study, variant_name, variants

    _setup_logging(0, quiet)

    if scheduler and executor != "dask":
        raise PipelineError("--scheduler needs --executor dask")
    live = not quiet and sys.stderr.isatty() and (executor == "dask" or workers == 1)
    labels = [variant_name(v) for v in variants(load_study(study.resolve()))] if live else []
    with LiveView(labels, enabled=live) as view:
        results, out = run_study(study, cache_dir=cache_dir, out_dir=out_dir, workers=workers, executor=executor,
                                 scheduler=scheduler, events=view if live else None)
    if not quiet:
        click.echo((out / "study.md").read_text())
    click.echo(f"report: {out / 'study.md'}; plots: {', '.join(p.name for p in sorted(out.glob('*_vs_time.png')))}")


if __name__ == "__main__":
    main()
