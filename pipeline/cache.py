"""Content-addressed artifact cache on disk.

Layout: ``<root>/<kind>/<key[:2]>/<key>/`` holding the stage's files and ``manifest.json`` (what went
into the key, versions, timings, and size/mtime/sha256 of every file). An entry is written into
``<root>/tmp/`` and renamed into place only when complete, so a killed run never leaves an entry that
looks finished. A lock file per key serialises concurrent runs computing the same entry; the loser
finds the winner's entry and uses it. An entry whose files do not match its manifest is a miss and is
rebuilt (files whose size and mtime match the manifest are trusted, like git's index; others are
re-hashed).
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

KEY_SCHEMA = 1
MANIFEST = "manifest.json"


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
    def __init__(self, root: Path) -> None:
        self.root = Path(root)

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
    def lock(self, key: str) -> Iterator[None]:
        lock_dir = self.root / "locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        with open(lock_dir / f"{key}.lock", "a+") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def new_tmp(self, key: str) -> Path:
        tmp = self.root / "tmp" / f"{key}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
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
            trash = self.root / "tmp" / f"damaged.{key}.{uuid.uuid4().hex[:8]}"
            os.replace(final, trash)
            shutil.rmtree(trash, ignore_errors=True)
        os.replace(tmp, final)
        return Entry(kind, key, final, manifest)

    def discard(self, tmp: Path) -> None:
        shutil.rmtree(tmp, ignore_errors=True)

    def sweep_tmp(self) -> int:
        """Remove temporary folders left by processes that no longer run (killed runs)."""
        removed = 0
        tmp_root = self.root / "tmp"
        if not tmp_root.is_dir():
            return 0
        for d in tmp_root.iterdir():
            parts = d.name.split(".")
            pid = int(parts[1]) if len(parts) >= 3 and parts[1].isdigit() else None
            if pid is not None and _alive(pid):
                continue
            shutil.rmtree(d, ignore_errors=True)
            removed += 1
        return removed

    def remove(self, kind: str, key: str) -> bool:
        path = self.entry_dir(kind, key)
        if not path.exists():
            return False
        trash = self.root / "tmp" / f"removed.{key}.{uuid.uuid4().hex[:8]}"
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
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(state, indent=1, sort_keys=True))
        os.replace(tmp, path)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
