"""kill -9 at random points of a real run (several stages, per-frame jobs in a process pool), then a
normal run: it completes, and every artifact is byte-identical to an uninterrupted run's."""
from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import time

from rel_helpers import assert_consistent, cli_cmd, cli_env, entries, run_cli, tree, write_config

KILLS = 20
SETTINGS = dict(count=6, steps=4, sim_sleep=0.3, render_sleep=0.05, export_sleep=0.1)


def _run_args(config, cache, out):
    return ("run", str(config), "--cache", str(cache), "--out", str(out), "--workers", "2", "-q")


def test_kill_9_at_20_random_points_then_resume_is_byte_identical(tmp_path):
    ref_cfg = write_config(tmp_path / "ref", **SETTINGS)
    t0 = time.monotonic()
    r = run_cli(*_run_args(ref_cfg, tmp_path / "ref_cache", tmp_path / "ref_out"))
    span = time.monotonic() - t0
    assert r.returncode == 0, r.stderr

    cfg = write_config(tmp_path / "killed", **SETTINGS)
    cache, out = tmp_path / "cache", tmp_path / "out"
    rng = random.Random(15)
    env = cli_env()
    killed = attempts = 0
    while killed < KILLS and attempts < 3 * KILLS:
        attempts += 1
        # the whole process group (the run and its pool workers) dies at once, as on a crash or OOM kill
        proc = subprocess.Popen(cli_cmd(*_run_args(cfg, cache, out)), env=env, start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.0, span))
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            killed += 1
        proc.wait()
        # a point after the run finished (resumed runs are shorter) does not count: start afresh
        if proc.returncode == 0:
            for d in (cache, out):
                shutil.rmtree(d, ignore_errors=True)
    assert killed == KILLS, f"only {killed} of {attempts} points fell inside a run"

    r = run_cli(*_run_args(cfg, cache, out))
    assert r.returncode == 0, r.stderr
    assert_consistent(cache, out)
    assert tree(out, skip=("run.json",)) == tree(tmp_path / "ref_out", skip=("run.json",))
    assert entries(cache) == entries(tmp_path / "ref_cache")
    print(f"kill -9 points: {killed} inside a run ({attempts} tried), all survived (run {span:.1f} s)")
