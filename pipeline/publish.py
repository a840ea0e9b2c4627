"""Publishing a run's artifacts into its output folder, touching only what the pipeline put there.

The output folder keeps a record of what the pipeline published, ``.pipeline-published.json``: each
published name (``frames``, ``usd``, ``run.json``...) with the files it held. A name is replaced only
when the record lists it and it holds no file the record does not list; anything else in the folder
(a user's ``walls/`` folder, notes, renders) is never replaced or removed: the run stops with exit 2
instead, before any stage runs. The record also keeps each published file's size and modification time: a
published file changed since (a lighter's edit to scene.usda, a retouched frame) is the user's, and the run
stops the same way (it was replaced by the cache's copy without a word). Every write goes to a
``.pipeline-tmp.*`` name first and is renamed into place; the record lists the union of old and new files
while a replacement is under way, so a run killed at any point leaves a folder the next run can still replace.
``.pipeline-tmp.*`` entries left by a killed run are removed when their process is provably dead (see ``cache.owner_is_dead``).
"""
from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterable

from .cache import file_in_the_way, owner_is_dead, owner_tag, parse_owner_tag, unwritable
from .errors import PipelineError
from .graph import Graph
from .stage import Artifact

RECORD = ".pipeline-published.json"
TMP_PREFIX = ".pipeline-tmp."


class OutputRefused(PipelineError):
    """The output folder holds something the pipeline did not publish where it would write (exit 2)."""


# -- the record ------------------------------------------------------------------------------------
def read_record(out_dir: Path) -> dict[str, list[str]]:
    path = out_dir / RECORD
    if not path.exists():
        return _record_from_old_run_json(out_dir)
    try:
        data = json.loads(path.read_text())
        published = data["published"]
        assert isinstance(published, dict)
        return {str(k): [str(f) for f in v] for k, v in published.items()}
    except (OSError, ValueError, KeyError, TypeError, AssertionError):
        raise OutputRefused(f"{path}: the record of what the pipeline published here is unreadable; "
                            f"move the folder away or remove the record to publish here again") from None


def _record_from_old_run_json(out_dir: Path) -> dict[str, list[str]]:
    """A folder published before the record existed: its run.json (the pipeline's report, naming this
    folder and the outputs it published there) is the proof of what is ours."""
    try:
        report = json.loads((out_dir / "run.json").read_text())
        outputs = report["outputs"]
        if Path(report["out"]).resolve() != out_dir.resolve() or not {"config", "stages"} <= set(report):
            return {}
        owned = {name: _files(out_dir / name) for name, where in outputs.items()
                 if Path(where).resolve() == (out_dir / name).resolve() and (out_dir / name).is_dir()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}
    return {**owned, "run.json": ["run.json"]}


def read_record_keys(out_dir: Path) -> dict[str, dict[str, Any]]:
    """What each published name was made from: ``{"key": its stage's cache key, "frames": the run's frame
    selection, None for all}``; empty for a record written before these were kept."""
    try:
        keys = json.loads((out_dir / RECORD).read_text()).get("keys", {})
        return {str(n): dict(k) for n, k in keys.items() if isinstance(k, dict) and "key" in k}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}


def read_shot(out_dir: Path) -> dict[str, str] | None:
    """The shot whose outputs the folder holds (``{"scene": name, "config": path}``), None when not recorded."""
    try:
        shot = json.loads((out_dir / RECORD).read_text()).get("shot")
        return {str(k): str(v) for k, v in shot.items()} if isinstance(shot, dict) and "scene" in shot else None
    except (OSError, ValueError, AttributeError, TypeError):
        return None


def read_record_stats(out_dir: Path) -> dict[str, dict[str, list[int]]]:
    """Each published name's files as published: ``{name: {file: [size, mtime_ns]}}``; empty for a record
    written before these were kept, or a name being replaced (its files then are not checked)."""
    try:
        stats = json.loads((out_dir / RECORD).read_text()).get("stats", {})
        return {str(n): {str(f): [int(a), int(b)] for f, (a, b) in fs.items()} for n, fs in stats.items()}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}


def _stats(target: Path) -> dict[str, list[int]]:
    out = {}
    for f in _files(target):
        st = (target / f if target.is_dir() else target).lstat()
        out[f] = [st.st_size, st.st_mtime_ns]
    return out


def changed_file(out_dir: Path, name: str, stats: dict[str, dict[str, list[int]]]) -> str | None:
    """The first file of published ``name`` whose size or modification time is not what the pipeline published
    (a hand edit), else None."""
    target = out_dir / name
    for f, was in sorted(stats.get(name, {}).items()):
        path = target / f if target.is_dir() else target
        try:
            st = path.lstat()
        except OSError:
            continue  # removed: nothing of the user's to keep
        if [st.st_size, st.st_mtime_ns] != was:
            return f
    return None


def _write_record(out_dir: Path, published: dict[str, list[str]], keys: dict[str, dict] | None = None,
                  shot: dict[str, str] | None = None, stats: dict[str, dict] | None = None) -> None:
    keys = {n: k for n, k in {**read_record_keys(out_dir), **(keys or {})}.items() if n in published}
    stats = {n: s for n, s in {**read_record_stats(out_dir), **(stats or {})}.items() if n in published and s}
    shot = shot or read_shot(out_dir)
    _atomic_write(out_dir / RECORD, json.dumps({"version": 1, "published": published, "keys": keys, "stats": stats,
                                                **({"shot": shot} if shot else {})}, indent=1, sort_keys=True))


def _atomic_write(path: Path, text: str | bytes) -> None:
    tmp = path.parent / f"{TMP_PREFIX}{path.name}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
    try:
        with open(tmp, "wb" if isinstance(text, bytes) else "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _files(path: Path) -> list[str]:
    if path.is_dir() and not path.is_symlink():
        return sorted(f.relative_to(path).as_posix() for f in path.rglob("*") if not f.is_dir() or f.is_symlink())
    return [path.name]


# -- the promise -------------------------------------------------------------------------------------
def check_out_dir(out_dir: Path, names: Iterable[str], files: Iterable[str] = ("run.json",),
                  shot: dict[str, str] | None = None) -> None:
    """Raise OutputRefused (exit 2) unless every name the run will publish can be written: absent, or
    published by the pipeline and holding only files it published. ``files``: the names published as
    plain files (the rest are folders). ``shot`` (``{"scene", "config"}``): the folder must not hold another
    scene's outputs (a second scene run with the same --out replaced the first's without a word)."""
    files = set(files)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputRefused(f"output folder {out_dir} is a file, not a folder; choose another --out")
    why = unwritable(out_dir)
    if why is not None:
        raise OutputRefused(f"output folder {out_dir} cannot be written: {why}; choose another --out")
    blocker = file_in_the_way(out_dir)
    if blocker is not None:
        raise OutputRefused(f"output folder {out_dir} cannot be made: {blocker} is a file, not a folder; move it away "
                            f"or choose another --out (nothing was changed)")
    if not out_dir.is_dir():
        return
    record, stats = read_record(out_dir), read_record_stats(out_dir)
    was = read_shot(out_dir)
    if shot is not None and was is not None and was["scene"] != shot["scene"] and any(n in record for n in names):
        raise OutputRefused(f"output folder {out_dir} holds the outputs of scene {was['scene']!r} ({was['config']}); "
                            f"this run of scene {shot['scene']!r} would replace them: choose another --out, or remove "
                            f"that folder (nothing was changed)")
    for name in names:
        target = out_dir / name
        if not target.exists() and not target.is_symlink():
            continue
        if name not in record:
            what = "folder" if target.is_dir() else "file"
            raise OutputRefused(f"{target}: a {what} the pipeline did not create is in the way of output {name!r}; "
                                f"move it away or choose another --out (nothing was changed)")
        if target.is_symlink() or (name not in files) != target.is_dir():
            raise OutputRefused(f"{target}: not what the pipeline published here; move it away or choose another --out")
        foreign = sorted(set(_files(target)) - set(record[name]))
        if foreign:
            raise OutputRefused(f"{target / foreign[0]}: a file the pipeline did not publish is inside output {name!r}; "
                                f"move it away (nothing was changed)")
        edited = changed_file(out_dir, name, stats)
        if edited is not None:
            where = target / edited if target.is_dir() else target
            raise OutputRefused(f"{where}: changed since the pipeline published it (edited by hand?): it is yours now; "
                                f"move output {name!r} away or choose another --out (nothing was changed)")
        if target.is_dir() and (not os.access(target, os.W_OK) or not target.stat().st_mode & 0o200):
            # a folder someone locked (chmod a-w: an approved movie) is theirs to unlock, not ours to replace (it was
            # swapped anyway, and its old files, undeletable, stayed behind as a hidden folder)
            raise OutputRefused(f"{target}: output {name!r} is read-only (locked?); make it writable to let the run "
                                f"replace it, or choose another --out (nothing was changed)")


def sweep_out_dir(out_dir: Path) -> None:
    """Remove ``.pipeline-tmp.*`` entries whose writer is provably dead (a killed run's staging)."""
    if not out_dir.is_dir():
        return
    for p in out_dir.iterdir():
        if not p.name.startswith(TMP_PREFIX):
            continue
        owner = parse_owner_tag(p.name[len(TMP_PREFIX):])
        if owner is None or not owner_is_dead(*owner, mtime=_mtime(p)):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _mtime(p: Path) -> float | None:
    try:
        return p.lstat().st_mtime
    except OSError:
        return None


# -- publishing --------------------------------------------------------------------------------------
FICLONE = 0x40049409  # linux/fs.h: the copy shares the source's blocks until either is written (btrfs, XFS)


def _clone_or_copy(src: Path, dst: Path) -> None:
    """A published file is its own file, never a hard link to the cache entry: a user editing a published frame
    in place (``cat new.png > frame.png``) changed the cache entry and every other output folder published from
    it. A copy-on-write clone where the filesystem has one (free), else a copy (0.6 s for the demo's 257 MB)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    with open(src, "rb") as fi, open(dst, "wb") as fo:
        try:
            import fcntl

            fcntl.ioctl(fo.fileno(), FICLONE, fi.fileno())
        except (ImportError, OSError):  # ext4, tmpfs, another filesystem, not Linux: copy
            shutil.copyfileobj(fi, fo, 1 << 22)
    shutil.copystat(src, dst)


def publish(graph: Graph, artifacts: dict[str, Artifact], out_dir: Path, frames: tuple[int, ...],
            keys: dict[str, dict] | None = None, shot: dict[str, str] | None = None) -> dict[str, str]:
    """Copy (``_clone_or_copy``) each wanted artifact into ``out_dir/<name>/``, replacing the old folder whole,
    and only if the pipeline published it (``check_out_dir``); a per-frame output of a ``--frames`` run keeps
    the other frames published from the same stage key. ``keys``: what each name is made from (``_made_from``:
    its stage's key, the run's frames), kept in the record for ``drop_stale``."""
    out_dir = Path(out_dir)
    names = [n for n in graph.outputs if artifacts.get(n) is not None]
    check_out_dir(out_dir, names, shot=shot)
    out_dir.mkdir(parents=True, exist_ok=True)
    sweep_out_dir(out_dir)
    record, earlier = read_record(out_dir), read_record_keys(out_dir)
    keys = {n: dict(k) for n, k in (keys or {}).items()}
    staged: dict[str, Path] = {}
    try:
        for name in names:
            art = artifacts[name]
            staging = out_dir / f"{TMP_PREFIX}{name}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
            staging.mkdir()
            staged[name] = staging
            made, was = keys.get(name, {}), earlier.get(name, {})
            if art.path is None and made.get("frames") is not None and made.get("key") == was.get("key") \
                    and (out_dir / name).is_dir():
                # a --frames run adds its frames to those published from the same settings (as a farm renders a
                # range into a shot's folder); it replaced the whole shot's frames/ with its few
                for f in _files(out_dir / name):
                    _clone_or_copy(out_dir / name / f, staging / f)
                made["frames"] = None if was.get("frames") is None else sorted(set(was["frames"]) | set(made["frames"]))
            sources = [art.path] if art.path is not None else [art.frames[f] for f in frames if f in art.frames]
            for src_dir in sources:
                for f in src_dir.rglob("*"):
                    # dotfiles are a stage's bookkeeping (render's skipped-frame marks), not output
                    if f.is_file() and f.name != "manifest.json" and not f.name.startswith("."):
                        _clone_or_copy(f, staging / f.relative_to(src_dir))
        new = {name: _files(staging) for name, staging in staged.items()}
        # while replacing, the record lists old and new files and no sizes for them: a kill here leaves a folder we
        # still own, whichever of the two it holds
        _write_record(out_dir, {**record, **{n: sorted(set(record.get(n, [])) | set(fs)) for n, fs in new.items()}},
                      stats={n: {} for n in new})
        for name, staging in staged.items():
            target = out_dir / name
            if target.exists():
                trash = out_dir / f"{TMP_PREFIX}old-{name}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
                os.replace(target, trash)
                try:
                    os.replace(staging, target)
                except BaseException:
                    os.replace(trash, target)  # the old folder back: nothing half-replaced
                    raise
                shutil.rmtree(trash, ignore_errors=True)
            else:
                os.replace(staging, target)
        _write_record(out_dir, {**record, **new}, {n: k for n, k in keys.items() if n in new}, shot,
                      {n: _stats(out_dir / n) for n in new})
    finally:
        for staging in staged.values():
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
    return {name: str(out_dir / name) for name in staged}


def write_run_json(report: Any, out_dir: Path) -> None:
    """Write the run's report as ``run.json`` (atomically) and record it as published."""
    publish_file(out_dir, "run.json", json.dumps(asdict(report), indent=1))


def publish_file(out_dir: Path, name: str, data: str | bytes) -> None:
    """Write ``data`` as the file ``name`` in ``out_dir`` (atomically) and record it as published; a file
    the pipeline did not publish in the way is refused (OutputRefused, exit 2), as for a run's outputs."""
    out_dir = Path(out_dir)
    check_out_dir(out_dir, [name], files=[name])
    out_dir.mkdir(parents=True, exist_ok=True)
    record = read_record(out_dir)
    _write_record(out_dir, {**record, name: [name]}, stats={name: {}})
    _atomic_write(out_dir / name, data)
    _write_record(out_dir, {**record, name: [name]}, stats={name: _stats(out_dir / name)})


def drop_stale(out_dir: Path, current: dict[str, str | None]) -> list[str]:
    """Remove the outputs an earlier run published here that the config, as it is now and for the same
    frames, would make differently (``current``: name -> its stage's key now; None when unknown, then kept):
    a run with ``--until simulate`` or fewer outputs after an edit left the old movie beside the new
    particles. Only what the record lists and the folder holds nothing else of; returns the names removed."""
    out_dir = Path(out_dir)
    record, was, stats = read_record(out_dir), read_record_keys(out_dir), read_record_stats(out_dir)
    # (a name holding a file edited by hand is the user's: kept, and the next run that would replace it stops)
    stale = [n for n, key in current.items() if key is not None and n in record and n in was and key != was[n]["key"]
             and (out_dir / n).is_dir() and not (out_dir / n).is_symlink() and set(_files(out_dir / n)) <= set(record[n])
             and changed_file(out_dir, n, stats) is None]
    for name in stale:
        trash = out_dir / f"{TMP_PREFIX}old-{name}.{owner_tag()}.{uuid.uuid4().hex[:8]}"
        os.replace(out_dir / name, trash)
        _write_record(out_dir, {n: f for n, f in read_record(out_dir).items() if n != name})
        shutil.rmtree(trash, ignore_errors=True)
    return stale
