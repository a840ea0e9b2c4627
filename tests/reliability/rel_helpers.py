"""Shared pieces of the reliability tests: the toy config, the CLI as a real process, and checks that a
cache and an output folder are consistent and hold no leftovers."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from pipeline.cache import MANIFEST, Cache

TESTS = Path(__file__).resolve().parents[1]
REPO = TESTS.parent
KINDS = ("mesh_import", "sdf_bake", "simulate", "surface_extract", "wall_snap", "render", "movie", "export")

# several stages, per-frame work (surface, render) and a whole-run branch (export) beside the frames
CONFIG = """\
config_version: 1
scene:
  name: {name}
  frames: {{fps: 10, count: {count}}}
fluid:
  spacing: 0.1
  emitters:
    - box: {{min: [0, 0, 0], max: [1, 1, 1]}}
stages:
  mesh_import: {{use: toy}}
  sdf_bake: {{use: toy}}
  simulate: {{use: toy, steps: {steps}, sleep: {sim_sleep}}}
  surface_extract: {{use: toy}}
  render: {{use: toy, sleep: {render_sleep}}}
  export: {{use: toy, sleep: {export_sleep}}}
outputs: [frames, usd]
"""


def write_config(folder: Path, name: str = "shot", count: int = 6, steps: int = 3, sim_sleep: float = 0.0,
                 render_sleep: float = 0.0, export_sleep: float = 0.0, file: str | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / (file or f"{name}.yaml")
    path.write_text(CONFIG.format(name=name, count=count, steps=steps, sim_sleep=sim_sleep,
                                  render_sleep=render_sleep, export_sleep=export_sleep))
    return path


def cli_env(extra: dict | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), str(REPO)]))
    env.update(extra or {})
    return env


def cli_cmd(*args: str) -> list[str]:
    """The real CLI in a new process, with only the toy stages registered (tests/reliability/toy_cli.py)."""
    return [sys.executable, str(Path(__file__).with_name("toy_cli.py")), *args]


def run_cli(*args: str, timeout: float = 120, cwd: Path | None = None,
            env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cli_cmd(*args), env=cli_env(env), capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


def tree(folder: Path, skip: tuple[str, ...] = ()) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes), leaving out names in ``skip``; the publish record
    without its files' sizes and times (the times are when the files were made, so two runs differ there)."""
    def content(f: Path) -> bytes:
        if f.name != ".pipeline-published.json":
            return f.read_bytes()
        record = json.loads(f.read_text())
        record.pop("stats", None)
        return json.dumps(record, sort_keys=True).encode()

    return {f.relative_to(folder).as_posix(): content(f) for f in sorted(folder.rglob("*"))
            if f.is_file() and f.name not in skip}


def entries(cache_root: Path) -> dict[str, bytes]:
    """The artifact files of every cache entry (manifests hold timings, so they are left out)."""
    out: dict[str, bytes] = {}
    for kind in KINDS:
        if (cache_root / kind).is_dir():
            out.update({f"{kind}/{k}": v for k, v in tree(cache_root / kind, skip=(MANIFEST,)).items()})
    return out


def assert_consistent(cache_root: Path, out_dir: Path | None = None) -> None:
    """No temporary leftovers, every entry finished and matching its manifest, state readable, and the
    output folder's published folders hold only what its record lists."""
    cache = Cache(cache_root)
    tmp = cache_root / "tmp"
    assert not tmp.exists() or not any(tmp.iterdir()), sorted(p.name for p in tmp.iterdir())
    for kind in KINDS:
        for entry in (cache_root / kind).glob("*/*") if (cache_root / kind).is_dir() else []:
            assert (entry / MANIFEST).is_file(), f"unfinished entry {entry}"
            assert cache.lookup(kind, entry.name) is not None, f"entry {entry} does not match its manifest"
    for state in (cache_root / "state").glob("*") if (cache_root / "state").is_dir() else []:
        assert state.suffix == ".json", f"leftover {state}"
        json.loads(state.read_text())
    if out_dir is not None and out_dir.exists():
        names = {p.name for p in out_dir.iterdir()}
        assert not [n for n in names if n.startswith(".pipeline-tmp.")], names
        if (out_dir / ".pipeline-published.json").exists():
            record = json.loads((out_dir / ".pipeline-published.json").read_text())["published"]
            for name, files in record.items():  # what is published is complete and recorded
                if (out_dir / name).is_dir():
                    have = {f.relative_to(out_dir / name).as_posix() for f in (out_dir / name).rglob("*") if f.is_file()}
                    assert have <= set(files), f"{name}: {sorted(have - set(files))} not in the record"
