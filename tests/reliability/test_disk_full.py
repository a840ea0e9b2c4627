"""Disk full at every write site: ENOSPC is injected at the n-th write (open for writing, mkdir, rename,
link; publishing copies, it does not link) under the test's folder, for every n a run makes; the disk then stays full, or frees up again.
Each time: exit 1, one line naming where and the cause, no temporary leftovers in the cache or the
output folder, every cache entry complete; and the next normal run gives the uninterrupted result.
A second test does the same on a real, tiny tmpfs (out of inodes) where the machine allows mounting."""
from __future__ import annotations

import builtins
import errno
import io
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import main
from pipeline.registry import Registry
from rel_helpers import assert_consistent, entries, tree, write_config
from toy_stages import TOY_STAGES

WRITE_MODES = set("wax+")


def _toy_registry(cls, group: str = "pipeline.stages") -> Registry:
    reg = cls()
    for stage in TOY_STAGES:
        reg.add(stage)
    return reg


class DiskFull:
    """Counts write operations under ``root``; from the ``fail_at``-th on (or only that one) they fail
    with ENOSPC."""

    def __init__(self, root: Path, fail_at: int | None = None, stays_full: bool = True) -> None:
        self.root, self.fail_at, self.stays_full = str(root), fail_at, stays_full
        self.count = 0
        self.sites: list[str] = []

    def hit(self, what: str, path) -> None:
        try:
            p = os.path.abspath(os.fspath(path))
        except TypeError:
            return
        # the run's up-front check that --out and --cache can be written (cache.unwritable) stores nothing: a full
        # disk there is no refusal (tested in test_cli) and the run goes on to fail where it writes
        if not p.startswith(self.root) or ".pipeline-write-test." in p:
            return
        self.count += 1
        self.sites.append(f"{what} {os.path.relpath(p, self.root)}")
        if self.fail_at is not None and (self.count == self.fail_at or (self.stays_full and self.count > self.fail_at)):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), p)

    def install(self, monkeypatch) -> None:
        real_open = builtins.open

        def open_(file, mode="r", *args, **kwargs):
            if isinstance(file, (str, bytes, os.PathLike)) and WRITE_MODES & set(mode):
                self.hit("open", file)
            return real_open(file, mode, *args, **kwargs)

        monkeypatch.setattr(builtins, "open", open_)
        monkeypatch.setattr(io, "open", open_)
        for name in ("mkdir", "replace", "rename", "link"):
            real = getattr(os, name)

            def wrapped(*args, _real=real, _name=name, **kwargs):
                if _name != "mkdir" or not os.path.exists(args[0]):  # an existing folder is EEXIST, no write
                    self.hit(_name, args[-1] if _name in ("replace", "rename", "link") else args[0])
                return _real(*args, **kwargs)

            monkeypatch.setattr(os, name, wrapped)


def _run(folder: Path, monkeypatch, disk: DiskFull | None):
    cfg = write_config(folder, count=2)
    with monkeypatch.context() as m:
        if disk is not None:
            disk.install(m)
        result = CliRunner().invoke(main, ["run", str(cfg), "--cache", str(folder / "cache"),
                                           "--out", str(folder / "out"), "-q"])
    return result


def test_enospc_at_every_write_site(tmp_path, monkeypatch):
    monkeypatch.setattr(Registry, "from_entry_points", classmethod(_toy_registry))
    ref = tmp_path / "ref"
    counter = DiskFull(ref)
    r = _run(ref, monkeypatch, counter)
    assert r.exit_code == 0, r.output
    sites = counter.sites
    assert len(sites) > 30, sites  # the counting itself works: cache entries, state, publish, run.json

    survived = 0
    for stays_full in (True, False):
        for n in range(1, len(sites) + 1):
            folder = tmp_path / f"{'full' if stays_full else 'once'}{n}"
            disk = DiskFull(folder, n, stays_full)
            r = _run(folder, monkeypatch, disk)
            site = disk.sites[n - 1] if len(disk.sites) >= n else "?"
            where = f"site {n}/{len(sites)} ({site}, disk {'stays full' if stays_full else 'frees up'})"
            assert r.exit_code == 1, f"{where}: exit {r.exit_code}: {r.output}"
            err = r.stderr.strip()
            assert len(err.splitlines()) == 1 and "Traceback" not in r.output, f"{where}: {err}"
            assert "No space left on device" in err, f"{where}: {err}"
            assert err.startswith("error: stage ") or err.startswith("error: publish") or err.startswith("error: cache"), \
                f"{where}: {err}"
            if site.split()[-1].startswith(("cache/surface_extract", "cache/render", "ran_surface", "ran_render")):
                assert " frame " in err, f"{where}: a per-frame failure names its frame: {err}"
            if not stays_full:
                assert "traceback in" in err, f"{where}: {err}"
                log = Path(err.rsplit("traceback in ", 1)[1].rstrip(")"))
                assert log.is_file() and "OSError" in log.read_text()
            if (folder / "cache").exists():
                assert_consistent(folder / "cache", folder / "out")
            if not stays_full:  # the recovery after each site is checked once, in the stays-full pass
                survived += 1
                shutil.rmtree(folder)
                continue
            # the disk has room again: the same run completes with the uninterrupted result
            r = _run(folder, monkeypatch, None)
            assert r.exit_code == 0, f"{where}: recovery run: {r.output}"
            assert_consistent(folder / "cache", folder / "out")
            assert tree(folder / "out", skip=("run.json",)) == tree(ref / "out", skip=("run.json",)), where
            assert entries(folder / "cache") == entries(ref / "cache"), where
            survived += 1
            shutil.rmtree(folder)
    print(f"ENOSPC fault points: {2 * len(sites)} tried ({len(sites)} write sites x disk stays full / frees up), "
          f"{survived} survived")


def _mount_tmpfs(where: Path, inodes: int) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size=4m,nr_inodes={inodes}", "tmpfs", str(where)],
                       capture_output=True)
    return r.returncode == 0


def test_real_small_filesystem_runs_out_of_space(tmp_path, monkeypatch):
    """A real tmpfs with few inodes: the run stops with exit 1 and one line wherever the disk fills up,
    and after the filesystem grows the same run completes with the uninterrupted result."""
    monkeypatch.setattr(Registry, "from_entry_points", classmethod(_toy_registry))
    ref = tmp_path / "ref"
    assert _run(ref, monkeypatch, None).exit_code == 0
    disk = tmp_path / "disk"
    if os.geteuid() != 0 or not _mount_tmpfs(disk, 8):
        pytest.skip("cannot mount a tmpfs here (needs root); the injected ENOSPC test covers every write site")
    failed = 0
    try:
        for inodes in (8, 16, 24, 32, 40, 48, 56):
            subprocess.run(["umount", str(disk)], check=True)
            assert _mount_tmpfs(disk, inodes)
            r = _run(disk / "run", monkeypatch, None)
            if r.exit_code == 0:
                continue
            failed += 1
            err = r.stderr.strip()
            assert r.exit_code == 1 and len(err.splitlines()) == 1, f"{inodes} inodes: {r.output}"
            assert "No space left on device" in err, err
            if (disk / "run" / "cache").exists():
                assert_consistent(disk / "run" / "cache", disk / "run" / "out")
            # a bigger disk: the same cache and output folder (copied with their times) complete the run
            bigger = tmp_path / f"bigger{inodes}"
            shutil.copytree(disk / "run", bigger, symlinks=True)
            r = _run(bigger, monkeypatch, None)
            assert r.exit_code == 0, f"{inodes} inodes, recovery: {r.output}"
            assert tree(bigger / "out", skip=("run.json",)) == tree(ref / "out", skip=("run.json",))
            assert entries(bigger / "cache") == entries(ref / "cache")
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)
    assert failed >= 5, f"only {failed} sizes ran out of space"
    print(f"tmpfs: {failed} fill-up points tried and survived")


def test_a_usd_write_over_the_file_size_limit_is_one_short_line(tmp_path):
    """USD reports a failed write as an ErrorException of 8.7 KB (\"File too large\" 36 times in C++ context):
    the run's one line said all of it. The line now names the cause, and the saved log keeps the rest."""
    script = tmp_path / "write.py"
    script.write_text(
        "import resource, sys\n"
        "import numpy as np\n"
        "from pxr import Usd, UsdGeom, Vt\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))\n"
        "stage = Usd.Stage.CreateNew(sys.argv[1])\n"
        "pts = UsdGeom.Points.Define(stage, '/P')\n"
        "for t in range(20):\n"
        "    pts.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.random.rand(20000, 3).astype(np.float32)), t)\n"
        "try:\n"
        "    stage.GetRootLayer().Save()\n"
        "except Exception as e:\n"
        "    sys.stdout.write(type(e).__name__ + '\\n' + str(e))\n")
    import sys as _sys
    out = subprocess.run([_sys.executable, str(script), str(tmp_path / "big.usdc")], capture_output=True, text=True)
    name, _, text = out.stdout.partition("\n")
    assert "File too large" in text and len(text) > 1000, out  # the library's own report: long

    from pipeline.runner import brief

    exc = type(name, (Exception,), {})(text)
    line = brief(exc)
    assert line == f"{name}: a write failed: File too large", line
    long = RuntimeError("x" * 5000 + "\nsecond line")
    assert len(brief(long)) < 330 and brief(long).endswith(" ...")
    assert brief(OSError(28, "No space left on device")) == "OSError: [Errno 28] No space left on device"
