"""Content-addressed artifact cache on disk.

Layout: ``<root>/<kind>/<key[:2]>/<key>/`` holding the stage's files and ``manifest.json`` (what went
into the key, versions, timings, and size/mtime/sha256 of every file). An entry is written into
``<root>/tmp/`` and renamed into place only when complete, so a killed run never leaves an entry that
looks finished. A lock file per key serialises concurrent runs computing the same entry; the loser
finds the winner's entry and uses it. An entry whose files do not match its manifest is a miss and is
rebuilt (files whose size and mtime match the manifest are trusted, like git's index; others are
re-hashed).

Temporary folders are named ``<key>.<host>-<pid>-<start>.<random>``: the sweep removes one only when its
writer is provably dead (same host and that process gone, or older than ``TMP_MAX_AGE``), so a run on
host A never removes a folder a worker on host B is still writing into a shared cache. The lock file
of a key records who holds it; a run waiting for it says so and gives up after ``lock_timeout``.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import logging
import math
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from .errors import ConfigError, StageFailed

KEY_SCHEMA = 1
MANIFEST = "manifest.json"
# a temporary folder or file whose writer runs on another host is swept only after this age (seconds;
# env PIPELINE_TMP_MAX_AGE, read by tmp_max_age()): no simulation step or frame job runs that long without
# finishing
TMP_MAX_AGE = 7 * 24 * 3600.0
# how long a run waits for another run's lock on a key before giving up (seconds; --lock-timeout,
# env PIPELINE_LOCK_TIMEOUT, read by default_lock_timeout())
LOCK_TIMEOUT = 3600.0


def env_seconds(name: str, default: float) -> float:
    """A number of seconds >= 0 from the environment variable ``name`` (unset or empty: ``default``);
    ConfigError (exit 2, one line naming the variable and its value) otherwise, as ``--lock-timeout -5``
    is refused. Read when used, not at import: a bad value is a user's mistake, not a traceback."""
    text = os.environ.get(name, "")
    if not text.strip():
        return default
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value >= 0 and math.isfinite(value)):  # negative, NaN or inf (the lock's wait is refused at inf)
        raise ConfigError(f"environment variable {name}={text!r}: expected a finite number of seconds >= 0")
    return value


def tmp_max_age() -> float:
    return env_seconds("PIPELINE_TMP_MAX_AGE", TMP_MAX_AGE)


def default_lock_timeout() -> float:
    return env_seconds("PIPELINE_LOCK_TIMEOUT", LOCK_TIMEOUT)


def check_env() -> None:
    """ConfigError for a bad value of an environment variable the pipeline reads (the CLI calls it first)."""
    tmp_max_age()
    default_lock_timeout()
    env_seconds("PIPELINE_LOG_EVERY", 0.0)  # pipeline.runner's progress lines in a log file
    threads = os.environ.get("NUMBA_NUM_THREADS", "")
    if threads.strip() and not (threads.strip().isdigit() and int(threads) >= 1):
        # numba printed a traceback for 'abc' and went on; 0 failed in a stage's import, blamed on the config line
        raise ConfigError(f"environment variable NUMBA_NUM_THREADS={threads!r}: expected a whole number of threads "
                          ">= 1 (or leave it unset: every core)")
    default_lock_timeout()

def file_in_the_way(path: Path) -> Path | None:
    """The closest existing ancestor of ``path`` when it is not a folder (a file, or a link to none), else
    None: ``path`` could not be created below it (a user's file named ``out`` beside the config)."""
    for parent in Path(path).parents:
        if parent.is_dir():
            return None
        if parent.exists() or parent.is_symlink():
            return parent
    return None


def unwritable(path: Path) -> str | None:
    """Why ``path`` (a folder, maybe not there yet) cannot be written, else None: tried by making and
    removing a folder in it or in its closest existing ancestor (a run under /proc ran every stage and
    then failed to publish)."""
    base = next((p for p in (Path(path), *Path(path).parents) if p.is_dir()), None)
    if base is None:
        return None
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".pipeline-write-test.", dir=base))
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):  # full, not unwritable: the run fails where it writes (exit 1)
            return None
        return f"{base} is not writable ({exc.strerror or exc})"
    return None


log = logging.getLogger("pipeline")


class LockTimeout(StageFailed):
    """Another run held a key's lock longer than the lock timeout (exit 1, one line)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, user_error=False)


class CacheBusy(StageFailed):
    """``clean`` while a run uses the cache (exit 1, one line)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, user_error=False)


# -- who wrote a temporary file: host, pid, start time ------------------------------------------------
def _machine() -> str:
    """This process's host as a temporary file's owner tag names it: the host name, then (where Linux says them)
    the boot's id and the pid namespace. Containers with the host's network share its name but not its process
    ids (a second container's run took a live run's pid for a dead one and removed its temporary folder), and
    two machines may share a name; a writer on another machine is never judged by this one's pids."""
    name = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:64] or "host"
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip().replace("-", "")[:8]
        pid_ns = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return name
    return f"{name}-b{boot}n{pid_ns}"


_HOST = _machine()
_STARTED = int(time.time())


def _restart_clock() -> None:
    # a forked pool worker is a new writer: its own pid with its own start, not its parent's
    global _STARTED
    _STARTED = int(time.time())


os.register_at_fork(after_in_child=_restart_clock)


def owner_tag() -> str:
    """``<host>-<pid>-<start>`` of this process, for names of temporary files and folders (no dots)."""
    return f"{_HOST}-{os.getpid()}-{_STARTED}"


# what new_tmp, commit, remove and write_state name their temporary folders and files in <cache>/tmp/:
# ``[damaged-|removed-|state-]<key>.<host>-<pid>-<start>.<random hex>``
_TMP_NAME = re.compile(r"[\w-]+\.[A-Za-z0-9-]+-\d+-\d+\.[0-9a-f]+")


def parse_owner_tag(name: str) -> tuple[str, int, int] | None:
    """(host, pid, start) from a name ``<anything>.<host>-<pid>-<start>.<random>``, or None."""
    parts = name.split(".")
    if len(parts) < 3:
        return None
    m = re.fullmatch(r"(.+)-(\d+)-(\d+)", parts[-2])
    return (m.group(1), int(m.group(2)), int(m.group(3))) if m else None


def owner_is_dead(host: str, pid: int, started: int, *, mtime: float | None = None,
                  max_age: float | None = None) -> bool:
    """True only when the writer certainly no longer runs: on this host and its pid is gone (or reused
    by a later process), or the file is older than ``max_age`` (default TMP_MAX_AGE, env PIPELINE_TMP_MAX_AGE) wherever it ran."""
    max_age = tmp_max_age() if max_age is None else max_age
    newest = max(started, mtime or 0.0)
    if time.time() - newest > max_age:
        return True
    if host != _HOST:
        return False
    if pid == os.getpid():
        return started != _STARTED
    if not _alive(pid):
        return True
    began = _process_start(pid)
    return began is not None and began > started + 2  # the pid now belongs to a later process


def canonical_json(value: Any) -> str:
    """Sorted-key, separator-stable JSON; anything not JSON-serialisable is a hard error."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def hash_key(components: dict[str, Any]) -> str:
    return hashlib.sha256(canonical_json({"key_schema": KEY_SCHEMA, **components}).encode()).hexdigest()


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


@dataclass
class Entry:
    kind: str
    key: str
    path: Path
    manifest: dict[str, Any]


class Cache:
    def __init__(self, root: Path, lock_timeout: float | None = None) -> None:
        # absolute, so worker processes (other cwd, other host) see the same folder
        self.root = Path(os.path.abspath(root))
        if self.root.exists() and not self.root.is_dir():
            raise ConfigError(f"cache folder {self.root} is a file, not a folder (choose another with --cache)")
        blocker = file_in_the_way(self.root)
        if blocker is not None:
            raise ConfigError(f"cache folder {self.root} cannot be made: {blocker} is a file, not a folder "
                              f"(choose another with --cache)")
        check_env()  # before anything is swept or waited for
        self.lock_timeout = default_lock_timeout() if lock_timeout is None else float(lock_timeout)
        if not math.isfinite(self.lock_timeout) or self.lock_timeout < 0:  # nan passed the CLI's range and waited forever
            raise ConfigError(f"--lock-timeout {lock_timeout}: expected a number of seconds >= 0")

    # -- paths -----------------------------------------------------------------------------------
    def entry_dir(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / key

    def checkpoint_dir(self, key: str) -> Path:
        return self.root / "checkpoints" / key

    # -- lookup ----------------------------------------------------------------------------------
    def lookup(self, kind: str, key: str) -> Entry | None:
        """The finished, undamaged entry for ``key``, or None."""
        path = self.entry_dir(kind, key)
        try:
            manifest = json.loads((path / MANIFEST).read_text())
        except (OSError, ValueError):
            return None
        if manifest.get("key") != key or not self._files_match(path, manifest.get("files", {})):
            return None
        return Entry(kind, key, path, manifest)

    def exists(self, kind: str, key: str) -> bool:
        return (self.entry_dir(kind, key) / MANIFEST).is_file()

    @staticmethod
    def _files_match(path: Path, files: dict[str, list]) -> bool:
        for rel, (size, mtime_ns, sha) in files.items():
            f = path / rel
            try:
                st = f.stat()
            except OSError:
                return False
            if st.st_size != size:
                return False
            if st.st_mtime_ns != mtime_ns and file_sha256(f) != sha:
                return False
        return True

    # -- writing ---------------------------------------------------------------------------------
    @contextmanager
    def in_use(self) -> Iterator[None]:
        """Held, shared, by every run for its whole length: ``clean`` takes it alone, so it never removes
        an entry a running shot made and is about to read (a clean during a run broke the run)."""
        with self._runs_lock() as fh:
            # a clean holds it alone only while it removes entries: wait for it as for a key's lock (said, and
            # given up after lock_timeout; a run started during a long clean on a network disk looked hung)
            self._wait(fh, fcntl.LOCK_SH, f"cache {self.root}", lambda: "`pipeline clean`, which holds the cache alone")
            yield

    @contextmanager
    def alone(self, what: str) -> Iterator[None]:
        """Hold the cache with no run using it, or raise CacheBusy (exit 1) at once."""
        with self._runs_lock() as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise CacheBusy(f"{what}: a run is using the cache {self.root}; try again when it has ended "
                                "(nothing was removed)") from None
            yield

    def _wait(self, fh, mode: int, what: str, holder) -> None:
        """flock ``fh`` in ``mode``; while another holds it, say once what waits for whom (``holder()``) and give
        up with LockTimeout after ``lock_timeout`` seconds."""
        t0 = time.monotonic()
        told = False
        while True:
            try:
                fcntl.flock(fh, mode | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                pass
            waited = time.monotonic() - t0
            if waited >= self.lock_timeout:
                raise LockTimeout(f"{what}: gave up after {waited:.0f} s waiting for {holder()} (--lock-timeout)")
            if not told:
                log.warning("%s: waiting for %s (gives up after %.0f s)", what, holder(), self.lock_timeout)
                told = True
            time.sleep(min(0.2, max(0.0, self.lock_timeout - waited)))

    def _runs_lock(self):
        """The file runs share and clean takes alone (open for flock)."""
        path = self.root / "locks" / "runs.lock"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            return open(path, "a+")
        except PermissionError as exc:
            try:  # a cache another user made: flock needs no write access, and a run that finds all cached only reads
                return open(path, "r")
            except OSError:
                pass
            # one line naming it, exit 2 as for a cache folder that cannot be written (it was a raw PermissionError, 1)
            raise ConfigError(f"cache {self.root}: {path.relative_to(self.root)} cannot be opened ({exc.strerror}): "
                              "a cache another user made? choose one you can write with --cache") from None

    @contextmanager
    def lock(self, key: str, what: str = "") -> Iterator[None]:
        """Hold the key's lock; while another run holds it, say who (pid, host, since when) and give
        up with LockTimeout after ``lock_timeout`` seconds."""
        lock_dir = self.root / "locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        path = lock_dir / f"{key}.lock"
        with open(path, "a+") as fh:
            self._wait(fh, fcntl.LOCK_EX, what or "key " + key[:12], lambda: f"the cache lock held by {_holder(path)}")
            try:
                fh.seek(0)
                fh.truncate()
                fh.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "since": time.time()}))
                fh.flush()
            except OSError:
                pass  # the holder's record is a courtesy to waiting runs; a full disk must not block the work
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def new_tmp(self, key: str) -> Path:
        tmp = self.root / "tmp" / f"{key}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
        tmp.mkdir(parents=True)
        return tmp

    def commit(self, kind: str, key: str, tmp: Path, manifest: dict[str, Any]) -> Entry:
        """Record every file of ``tmp`` in the manifest, write it last, and move ``tmp`` into place."""
        files: dict[str, list] = {}
        for f in sorted(tmp.rglob("*")):
            if f.is_file():
                st = f.stat()
                files[f.relative_to(tmp).as_posix()] = [st.st_size, st.st_mtime_ns, file_sha256(f)]
        manifest = {**manifest, "key": key, "kind": kind, "files": files, "created": time.time()}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=True))
        final = self.entry_dir(kind, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():  # a damaged entry (caller holds the key's lock): move it aside first
            trash = self.root / "tmp" / f"damaged-{key}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
            os.replace(final, trash)
            shutil.rmtree(trash, ignore_errors=True)
        os.replace(tmp, final)
        return Entry(kind, key, final, manifest)

    def discard(self, tmp: Path) -> None:
        shutil.rmtree(tmp, ignore_errors=True)

    def sweep_tmp(self) -> int:
        """Remove temporary folders whose writer is provably dead (killed runs); see owner_is_dead. Only names
        the cache gives its own temporaries: a --cache pointed at a user's folder lost every item of its tmp/
        older than 7 days, whatever it was."""
        removed = 0
        tmp_root = self.root / "tmp"
        if not tmp_root.is_dir():
            return 0
        for d in tmp_root.iterdir():
            owner = parse_owner_tag(d.name) if _TMP_NAME.fullmatch(d.name) else None
            if owner is None:
                continue
            try:
                mtime = d.lstat().st_mtime
            except OSError:
                continue
            if not owner_is_dead(*owner, mtime=mtime):
                continue
            if d.is_dir() and not d.is_symlink():
                shutil.rmtree(d, ignore_errors=True)
            else:
                d.unlink(missing_ok=True)
            removed += 1
        return removed

    def remove(self, kind: str, key: str) -> bool:
        path = self.entry_dir(kind, key)
        if not path.exists():
            return False
        trash = self.root / "tmp" / f"removed-{key}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
        trash.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, trash)
        shutil.rmtree(trash, ignore_errors=True)
        return True

    # -- per-config state (for `status` causes) -----------------------------------------------
    def state_path(self, config_path: Path) -> Path:
        digest = hashlib.sha256(str(Path(config_path).resolve()).encode()).hexdigest()[:16]
        return self.root / "state" / f"{digest}.json"

    def read_state(self, config_path: Path) -> dict[str, Any]:
        try:
            return json.loads(self.state_path(config_path).read_text())
        except (OSError, ValueError):
            return {}

    def write_state(self, config_path: Path, state: dict[str, Any]) -> None:
        path = self.state_path(config_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.root / "tmp" / f"state-{path.stem}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
        tmp.parent.mkdir(parents=True, exist_ok=True)
        try:
            tmp.write_text(json.dumps(state, indent=1, sort_keys=True))
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def running(cache: "Cache", key: str) -> str | None:
    """Who holds ``key``'s lock now (a run computing it: "pid N on host since T"), or None (`pipeline status`
    during a run called the entry being computed "missing, never run")."""
    path = cache.root / "locks" / f"{key}.lock"
    if not path.is_file():
        return None
    try:
        with open(path, "a+") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return _holder(path)
            fcntl.flock(fh, fcntl.LOCK_UN)
    except OSError:
        return None
    return None


def _holder(lock_file: Path) -> str:
    try:
        info = json.loads(lock_file.read_text())
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(info["since"])))
        return f"pid {info['pid']} on {info['host']} since {since}"
    except (OSError, ValueError, KeyError, TypeError):
        return "another run"


def _proc_stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat after the command name (state first), or None when unknown."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _process_start(pid: int) -> float | None:
    """Wall-clock start time of a local process (Linux /proc), or None when unknown."""
    try:
        ticks = int(_proc_stat(pid)[19])
        btime = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                     if line.startswith("btime"))
        return btime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, TypeError, StopIteration):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    # a killed worker whose parent died too stays a zombie where no init reaps orphans (containers):
    # it answers signals but writes nothing
    stat = _proc_stat(pid)
    return not (stat and stat[0] in ("Z", "X"))
