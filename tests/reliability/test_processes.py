"""Real processes: concurrent runs sharing a cache, waiting for a lock, Ctrl-C with a process pool, and
a native crash in a pool worker."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from pipeline.cache import Cache
from rel_helpers import assert_consistent, cli_cmd, cli_env, run_cli, write_config


def _lines(path: Path) -> int:
    return len(path.read_text().split()) if path.exists() else 0


def _start(*args: str, env: dict | None = None) -> subprocess.Popen:
    # SIGHUP as a terminal leaves it, even where the tests run under nohup (which ignores it, and children inherit that)
    return subprocess.Popen(cli_cmd(*args), env=cli_env(env), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))


def test_two_concurrent_runs_of_the_same_config(tmp_path):
    cfg = write_config(tmp_path, count=4, sim_sleep=0.5)
    procs = [_start("run", str(cfg), "--workers", "2", "-q") for _ in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    # each entry was computed once: the second run waited for the first one's lock and used its entry
    assert _lines(tmp_path / "ran_simulate.log") == 1
    assert _lines(tmp_path / "ran_render.log") == 4
    out = tmp_path / "out" / "shot"
    assert len(list((out / "frames").glob("frame_*.txt"))) == 4
    assert_consistent(tmp_path / ".pipeline", out)


def test_two_concurrent_runs_of_different_configs_sharing_a_cache(tmp_path):
    # the same scene (the toy import reads the whole scene section, name included), other simulations
    a = write_config(tmp_path / "a", steps=3, sim_sleep=0.3, file="a.yaml")
    b = write_config(tmp_path / "b", steps=5, sim_sleep=0.3, file="b.yaml")
    cache = tmp_path / "shared"
    procs = [_start("run", str(c), "--cache", str(cache), "--workers", "2", "-q") for c in (a, b)]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    for cfg, dots in ((a, 3), (b, 5)):
        text = (cfg.parent / "out" / "shot" / "usd" / "scene.txt").read_text()
        assert text.endswith("| sim" + "." * dots), text
        assert_consistent(cache, cfg.parent / "out" / "shot")
    # the stages they share (same scene and walls) were computed once, by whichever run came first
    for kind in ("mesh_import", "sdf_bake"):
        assert sum(_lines(c.parent / f"ran_{kind}.log") for c in (a, b)) == 1, kind
    assert sum(_lines(c.parent / "ran_simulate.log") for c in (a, b)) == 2


def test_lock_wait_names_the_holder_and_gives_up(tmp_path):
    cfg = write_config(tmp_path)
    cache = tmp_path / "c"
    r = run_cli("run", str(cfg), "--cache", str(cache), "-q")
    assert r.returncode == 0, r.stderr
    key = next(s["key"] for s in json.loads((tmp_path / "out" / "shot" / "run.json").read_text())["stages"]
               if s["kind"] == "simulate")
    with Cache(cache).lock(key):  # this test process holds the simulate entry's lock
        t0 = time.monotonic()
        r = run_cli("run", str(cfg), "--cache", str(cache), "--force", "simulate", "--lock-timeout", "1", "-q")
        waited = time.monotonic() - t0
    assert r.returncode == 1, r.stderr
    assert "waiting for the cache lock held by" in r.stderr  # said while waiting
    err = r.stderr.strip().splitlines()[-1]
    assert err.startswith("error: "), r.stderr
    assert f"pid {os.getpid()}" in err and "since" in err and "stage simulate.toy" in err and "gave up" in err, err
    assert waited < 30
    assert_consistent(cache)


def test_a_run_during_a_clean_says_it_waits_and_gives_up_after_the_lock_timeout(tmp_path):
    """`pipeline clean` holds the cache alone while it removes entries; a run started meanwhile waited in silence,
    whatever --lock-timeout said (a long clean on a network disk looked like a hung run). It now says what it
    waits for and gives up after the timeout: exit 1, one line."""
    import fcntl

    cfg = write_config(tmp_path, count=2)
    cache = tmp_path / "c"
    (cache / "locks").mkdir(parents=True)
    with open(cache / "locks" / "runs.lock", "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # as clean takes it
        t0 = time.monotonic()
        r = run_cli("run", str(cfg), "--cache", str(cache), "--lock-timeout", "1", "-q")
        waited = time.monotonic() - t0
    assert r.returncode == 1, r.stderr
    assert "waiting for `pipeline clean`" in r.stderr
    err = r.stderr.strip().splitlines()[-1]
    assert err.startswith("error: ") and "gave up after 1 s waiting for `pipeline clean`" in err, err
    assert waited < 30
    r = run_cli("run", str(cfg), "--cache", str(cache), "-q")  # the clean done: the run goes ahead
    assert r.returncode == 0, r.stderr


def test_status_during_a_run_says_which_stage_is_being_computed(tmp_path):
    """`pipeline status` while a run computes the simulation called it "missing: never run with these inputs";
    it now says it is being computed, and by whom."""
    cfg = write_config(tmp_path, count=2)
    cache = tmp_path / "c"
    proc = _start("run", str(cfg), "--cache", str(cache), "-q", "--set", "simulate.sleep=60")
    try:
        deadline = time.monotonic() + 60
        while _lines(tmp_path / "ran_simulate.log") == 0:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        r = run_cli("status", str(cfg), "--cache", str(cache), "--set", "simulate.sleep=60")
        assert r.returncode == 0, r.stderr
        row = next(line for line in r.stdout.splitlines() if "simulate" in line)
        assert "running" in row and f"pid {proc.pid}" in r.stdout, r.stdout
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        proc.communicate(timeout=30)


def _interrupt_when(tmp_path: Path, marker: str, *sets: str, extra: tuple[str, ...] = (),
                    sig: int = signal.SIGINT) -> tuple[subprocess.Popen, float, str]:
    cfg = write_config(tmp_path, count=4)
    args = ["run", str(cfg), "--cache", str(tmp_path / "c"), "--workers", "2", "-q", *extra]
    for s in sets:
        args += ["--set", s]
    proc = _start(*args)
    deadline = time.monotonic() + 60
    while _lines(tmp_path / marker) == 0:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(0.3)
    t0 = time.monotonic()
    os.killpg(proc.pid, sig)  # what Ctrl-C in a terminal does (SIGINT): the whole foreground group
    _, err = proc.communicate(timeout=30)
    seconds = time.monotonic() - t0
    left = _group(proc.pid)
    for _ in range(20):  # orphans are reaped by init, which may take a moment
        if not left:
            break
        time.sleep(0.1)
        left = _group(proc.pid)
    assert not left, f"processes outlived the run: {left}"
    return proc, seconds, err


def _group(pgid: int) -> list[str]:
    """Live (not zombie) processes of a process group."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(f"{stat.parent.name} {(stat.parent / 'cmdline').read_bytes()[:120]!r}")
    return out


def test_pool_workers_end_when_the_run_is_killed_alone(tmp_path):
    """SIGKILL to the run's process only (what the OOM killer does) cannot stop its workers: they idled on,
    adopted by init, 380 MB each (a user's sweep). Each worker now ends once its parent is gone."""
    cfg = write_config(tmp_path, count=4)
    proc = _start("run", str(cfg), "--cache", str(tmp_path / "c"), "--workers", "2", "-q", "--set", "render.sleep=30")
    deadline = time.monotonic() + 60
    while _lines(tmp_path / "ran_render.log") == 0:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    proc.kill()  # the run's process alone, not its group
    proc.wait(timeout=30)  # (not communicate: the workers hold its pipes open while they live)
    left = _group(proc.pid)
    for _ in range(100):
        if not left:
            break
        time.sleep(0.1)
        left = _group(proc.pid)
    assert not left, f"workers outlived the killed run: {left}"


def _resume_is_consistent(tmp_path: Path) -> None:
    r = run_cli("run", str(tmp_path / "shot.yaml"), "--cache", str(tmp_path / "c"), "-q")
    assert r.returncode == 0, r.stderr
    assert_consistent(tmp_path / "c", tmp_path / "out" / "shot")


def test_ctrl_c_during_frames_in_worker_processes_stops_quickly(tmp_path):
    proc, seconds, err = _interrupt_when(tmp_path, "ran_render.log", "render.sleep=30")
    assert proc.returncode == 130, err
    assert seconds < 5, f"took {seconds:.1f} s to stop"
    # multiprocessing's resource tracker (its own process) may warn afterwards of a semaphore the
    # terminated pool left behind: Python's noise, not ours (noted in issue 15's closing note)
    ours = [line for line in err.strip().splitlines() if "resource_tracker" not in line]
    assert ours[-1].startswith("interrupted"), err
    _resume_is_consistent(tmp_path)


def test_ctrl_c_during_frames_on_a_local_dask_cluster_stops_quickly(tmp_path):
    """--executor dask without a scheduler: a LocalCluster of worker processes, ended with the run (a
    frame job sleeping 30 s does not hold it up); one line, exit 130, the cache consistent."""
    proc, seconds, err = _interrupt_when(tmp_path, "ran_render.log", "render.sleep=30", extra=("--executor", "dask"))
    assert proc.returncode == 130, err
    assert seconds < 10, f"took {seconds:.1f} s to stop"
    ours = [line for line in err.strip().splitlines() if "resource_tracker" not in line]
    assert len(ours) == 1 and ours[0].startswith("interrupted"), err
    _resume_is_consistent(tmp_path)


def test_ctrl_c_during_a_long_whole_run_stage_stops_quickly(tmp_path):
    proc, seconds, err = _interrupt_when(tmp_path, "ran_simulate.log", "simulate.sleep=60")
    assert proc.returncode == 130, err
    assert seconds < 5, f"took {seconds:.1f} s to stop"
    _resume_is_consistent(tmp_path)


@pytest.mark.parametrize("sig, said", [(signal.SIGTERM, "terminated (SIGTERM)"), (signal.SIGHUP, "hung up (SIGHUP)")])
@pytest.mark.parametrize("marker, sleep", [("ran_simulate.log", "simulate.sleep=60"), ("ran_render.log", "render.sleep=30")])
def test_sigterm_stops_like_ctrl_c(tmp_path, marker, sleep, sig, said):
    """A batch scheduler's time limit or preemption (SLURM, docker stop, Kubernetes) sends SIGTERM to the
    group: it ended with 143 and nothing said (with workers, the resource tracker's leaked-semaphore noise).
    Now one line, exit 143, and the next run resumes. The same for SIGHUP (the ssh session closed), which
    ended with 129 and nothing said."""
    proc, seconds, err = _interrupt_when(tmp_path, marker, sleep, sig=sig)
    assert proc.returncode == 128 + sig, err
    assert seconds < 5, f"took {seconds:.1f} s to stop"
    # (multiprocessing's resource tracker, its own process, may warn of the stopped pool's semaphore: Python's
    # noise, as after Ctrl-C)
    lines = [ln for ln in err.strip().splitlines() if "resource_tracker" not in ln and "warnings.warn" not in ln]
    assert len(lines) == 1 and lines[0].startswith(said), err
    _resume_is_consistent(tmp_path)


def test_native_crash_in_a_worker_is_one_line_and_leaves_a_trace(tmp_path):
    cfg = write_config(tmp_path, count=3)
    cache = tmp_path / "c"
    r = run_cli("run", str(cfg), "--cache", str(cache), "--workers", "2", "-q", env={"TOY_SEGV_FRAME": "1"})
    assert r.returncode == 1, r.stderr
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1, err
    assert "stage render.toy" in err and "worker process died" in err, err
    logs = "".join(p.read_text() for p in (cache / "logs").glob("run-*.log"))
    assert "Segmentation fault" in logs and "_crashing" in logs, logs
    _resume = run_cli("run", str(cfg), "--cache", str(cache), "-q")
    assert _resume.returncode == 0, _resume.stderr
    assert_consistent(cache, tmp_path / "out" / "shot")
