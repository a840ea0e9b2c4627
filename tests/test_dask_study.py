"""Studies and batches of shots on Dask worker processes (pipeline.cluster), on loopback with the toy
stages: the same results as inline, a worker killed mid-simulation, two clients sharing a cluster and a
cache, and a batch with a broken shot."""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")

from conftest import REPO, TESTS, TOY_CONFIG, ran, write_toy_plugin  # noqa: E402
from pipeline.study import run_study  # noqa: E402

sys.path.insert(0, str(TESTS / "reliability"))
from rel_helpers import assert_consistent, entries, tree, write_config  # noqa: E402

STUDY = """\
study_version: 1
name: {name}
base: toy.yaml
sweep:
  simulate.steps: {steps}
set: {set}
outputs: {outputs}
time: simulate
metrics:
  - {{name: error, file: particles/stats.json, key: stats.error}}
"""


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    """The toy stages, importable here and (sys.path is handed to spawned processes) in Dask workers."""
    root = write_toy_plugin(tmp_path_factory.mktemp("plugin"))
    saved = list(sys.path)
    sys.path[:0] = [str(root), str(TESTS)]
    yield root
    sys.path[:] = saved


@pytest.fixture(scope="module")
def scheduler(plugin):
    """A cluster of 2 worker processes shared by the tests that connect to a scheduler address."""
    from pipeline import cluster

    client = cluster.connect(None, 2)
    yield client.scheduler.address
    cluster.close(client)


def _study(folder: Path, name: str = "s", steps=(1, 2, 4), sets=(), outputs=("particles",)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "toy.yaml").write_text(TOY_CONFIG)
    path = folder / f"{name}.yaml"
    path.write_text(STUDY.format(name=name, steps=list(steps), set=list(sets), outputs=list(outputs)))
    return path


def _table(out: Path) -> list[list[str]]:
    """study.csv without its timing columns and its (empty) variant-error column."""
    rows = list(csv.reader(open(out / "study.csv")))
    assert all(r[-1] == "" for r in rows[1:]), rows
    keep = [i for i, h in enumerate(rows[0]) if not h.endswith("seconds") and h != "variant-error"]
    return [[r[i] for i in keep] for r in rows]


def _env(plugin: Path) -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(plugin), str(TESTS), str(REPO)]))


def test_study_on_worker_processes_equals_inline(tmp_path, plugin):
    path = _study(tmp_path, outputs=("particles", "frames"))
    inline, out_inline = run_study(path, cache_dir=tmp_path / "c1", out_dir=tmp_path / "o1", executor="inline")
    runs_inline = ran(path, "simulate"), ran(path, "render")
    dask, out_dask = run_study(path, cache_dir=tmp_path / "c2", out_dir=tmp_path / "o2", executor="dask", workers=2)
    assert (ran(path, "simulate"), ran(path, "render")) == (2 * runs_inline[0], 2 * runs_inline[1]) == (6, 24)
    # the per-frame stages ran on the worker processes, not here
    pids = set((tmp_path / "ran_render.log").read_text().split())
    assert str(os.getpid()) in pids and len(pids) >= 2
    assert entries(tmp_path / "c1") == entries(tmp_path / "c2") != {}
    skip = ("run.json", "study.json", "study.csv", "study.md", "error_vs_time.png")
    assert tree(out_inline, skip) == tree(out_dask, skip)
    assert _table(out_inline) == _table(out_dask)
    assert [r.metrics for r in inline] == [r.metrics for r in dask] == [{"error": e} for e in (1.0, 0.5, 0.25)]
    assert all(r.seconds > 0 and r.cpu_seconds >= 0 for r in dask)
    assert_consistent(tmp_path / "c2")


def test_cost_column_leaves_out_the_warm_up(tmp_path, plugin):
    # a 0.6 s warm-up (as a JIT compile) and 0.2 s of simulation: the study charges the simulation
    path = _study(tmp_path, steps=(2,), sets=("simulate.warm_up=0.6", "simulate.sleep=0.2"))
    results, out = run_study(path, executor="inline")
    run = json.loads((out / "variants" / "steps-2" / "run.json").read_text())
    assert next(s for s in run["stages"] if s["kind"] == "simulate")["seconds"] >= 0.8
    assert 0.2 <= results[0].seconds < 0.6 and results[0].cpu_seconds < 0.1  # sleeping costs no CPU
    assert float(list(csv.reader(open(out / "study.csv")))[1][1]) == round(results[0].seconds, 3)


def test_a_warm_up_run_per_process_before_timing(tmp_path, plugin, monkeypatch):
    import toy_stages

    monkeypatch.setattr(toy_stages.ToySimulate, "warm_up_run", True)
    path = _study(tmp_path, sets=("simulate.sleep=0.011",))
    path.write_text(path.read_text().replace("simulate.steps: [1, 2, 4]", "fluid.spacing: [0.1, 0.2]"))
    run_study(path, cache_dir=tmp_path / "c", executor="inline")
    # one untimed 2-frame run of the implementation (same parameters for both variants), then the two
    assert ran(path, "simulate") == 3
    assert len(list((tmp_path / "c" / "simulate").glob("*/*/manifest.json"))) == 2  # nothing of it cached
    run_study(path, cache_dir=tmp_path / "c", executor="inline")
    assert ran(path, "simulate") == 3  # cached variants need no warm-up


def test_worker_killed_mid_simulation_is_retried(tmp_path, plugin, scheduler):
    # each simulation sleeps 2 s in 2 or 3 steps; the first worker seen simulating is killed
    path = _study(tmp_path / "k", steps=(2, 3), sets=("simulate.sleep=2",))
    result = {}
    thread = threading.Thread(target=lambda: result.update(r=run_study(
        path, cache_dir=tmp_path / "ck", out_dir=tmp_path / "ok", executor="dask", scheduler=scheduler)))
    thread.start()
    log = path.parent / "ran_simulate.log"
    deadline = time.time() + 60
    while not (log.exists() and log.read_text().split()) and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # mid-write: the entry's temporary folder holds a partial particles.txt
    victim = int(log.read_text().split()[0])
    assert victim != os.getpid()
    os.kill(victim, signal.SIGKILL)
    thread.join(120)
    assert not thread.is_alive() and "r" in result
    results, out = result["r"]
    assert [r.metrics["error"] for r in results] == [0.5, 1 / 3]
    assert ran(path, "simulate") == 3  # two variants, one of them started again after the kill
    assert_consistent(tmp_path / "ck", out)
    # the same as a run nobody interrupted
    ref = _study(tmp_path / "ref", steps=(2, 3), sets=("simulate.sleep=2",))
    run_study(ref, cache_dir=tmp_path / "cref", out_dir=tmp_path / "oref", executor="inline")
    assert entries(tmp_path / "ck") == entries(tmp_path / "cref")
    assert _table(out) == _table(tmp_path / "oref")


def test_two_clients_with_overlapping_studies_compute_shared_keys_once(tmp_path, plugin, scheduler):
    folder = tmp_path / "shared"
    a = _study(folder, "a", steps=(1, 2), sets=("simulate.sleep=0.5",))
    b = _study(folder, "b", steps=(2, 4), sets=("simulate.sleep=0.5",))
    cmd = [sys.executable, "-m", "pipeline.cli", "study", "--executor", "dask", "--scheduler", scheduler,
           "--cache", str(folder / "cache"), "-q"]
    procs = [subprocess.Popen(cmd + [str(p)], env=_env(plugin), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for p in (a, b)]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    # steps 1, 2 and 4: the shared variant (2) and the shared upstream stages ran once
    assert ran(a, "simulate") == 3 and ran(a, "mesh_import") == 1 and ran(a, "sdf_bake") == 1
    assert _table(folder / "out" / "a")[1:] == [["1", "1.0"], ["2", "0.5"]]
    assert _table(folder / "out" / "b")[1:] == [["2", "0.5"], ["4", "0.25"]]
    assert_consistent(folder / "cache")


def test_a_failing_variant_on_dask_keeps_the_others(tmp_path, plugin, scheduler):
    """On Dask as inline: the failed variant is a row of the report with its reason, the others are reported, exit 1."""
    path = _study(tmp_path / "f", "f", steps=(1, 2))
    path.write_text(path.read_text().replace("sweep:\n", "mode: zip\nsweep:\n  simulate.fail: [bug, null]\n"))
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "study", str(path), "--executor", "dask", "--scheduler",
                        scheduler, "--cache", str(tmp_path / "f" / "cache"), "-q"], env=_env(plugin),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "1 of 2 variant(s) failed: variant fail-bug_steps-1" in r.stderr, r.stderr
    rows = list(csv.reader(open(tmp_path / "f" / "out" / "f" / "study.csv")))
    assert "RuntimeError: boom (traceback in" in rows[1][-1] and rows[2][-2:] == ["0.5", ""], rows


def test_batch_of_shots_with_a_broken_one(tmp_path, plugin, scheduler):
    good = [write_config(tmp_path / n, name=n, count=3) for n in ("a", "b")]
    broken = write_config(tmp_path / "c", name="c", count=3)
    broken.write_text(broken.read_text().replace("simulate: {use: toy,", "simulate: {use: toy, fail: bug,"))
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", *map(str, good), str(broken),
                        "--executor", "dask", "--scheduler", scheduler, "--cache", str(tmp_path / "cache")],
                       env=_env(plugin), capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and str(broken) in errors[0] and "RuntimeError: boom" in errors[0], r.stderr
    assert "Traceback" not in r.stderr
    table = [line for line in r.stdout.splitlines() if ".yaml" in line]
    assert len(table) == 3 and "failed" in table[2] and all(" ok " in line for line in table[:2]), r.stdout
    for cfg in good:
        out = cfg.parent / "out" / cfg.stem
        assert len(list((out / "frames").glob("frame_*.txt"))) == 3
        assert (out / "usd" / "scene.txt").is_file()
    assert_consistent(tmp_path / "cache")


# runs the README's SLURM code block in its own process, which keeps the cluster's scheduler: importing
# dask_jobqueue replaces the importing process's SIGINT handler (its runner module), which a test process
# that sends Ctrl-C to its children must not inherit any state of
RECIPE_HOST = """
import re, sys
from pathlib import Path
import dask_jobqueue

block = next(b for b in re.findall(r"```python\\n(.*?)```", Path(sys.argv[1]).read_text(), re.S) if "SLURMCluster" in b)
scaled = []
dask_jobqueue.SLURMCluster.scale = lambda self, *a, **kw: scaled.append(kw or a)  # sbatch is not here
scope = {}
exec(compile(block, "README.md", "exec"), scope)
cluster = scope["cluster"]
Path(sys.argv[2]).write_text(cluster.job_script())
print("recipe:", cluster.scheduler_address, scaled[0], flush=True)
sys.stdin.read()  # until the test is done
cluster.close()
"""


def test_the_readme_slurm_recipe_starts_workers_that_run_a_batch(tmp_path, plugin):
    """The README's SLURM recipe, executed as written (only ``scale``, which would call sbatch, is held
    back): the job script it makes, run by bash as SLURM would run it, starts a worker with one task
    thread, the declared resources and the numba threads; a batch of shots sent to its scheduler
    completes."""
    pytest.importorskip("dask_jobqueue")
    from distributed import Client

    script = tmp_path / "job.sh"
    host = subprocess.Popen([sys.executable, "-c", RECIPE_HOST, str(REPO / "README.md"), str(script)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            env=_env(plugin), start_new_session=True)  # the scheduler unpickles toy stages too
    worker = None
    try:
        line = ""
        while not line.startswith("recipe:"):  # the recipe prints the address itself first
            line = host.stdout.readline()
            assert line, "the recipe's process ended"
        _, address, scaled = line.split(" ", 2)
        assert scaled.strip() == "{'jobs': 4}"  # what the recipe asks of SLURM
        worker = subprocess.Popen(["bash", str(script)], env=_env(plugin), stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        client = Client(address, timeout="30s")
        client.wait_for_workers(1, timeout=60)
        (info,) = client.scheduler_info(n_workers=-1)["workers"].values()
        assert info["nthreads"] == 1  # one shot per worker at a time: the cores are numba's
        assert info["resources"] == {"threads": 8.0, "memory": 64e9}
        assert set(client.run(lambda: os.environ.get("NUMBA_NUM_THREADS")).values()) == {"8"}
        shots = [write_config(tmp_path / n, name=n, count=2) for n in ("a", "b")]
        r = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", *map(str, shots), "--executor", "dask",
                            "--scheduler", address, "--cache", str(tmp_path / "cache"), "-q"],
                           env=_env(plugin), capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        for cfg in shots:
            assert len(list((cfg.parent / "out" / cfg.stem / "frames").glob("frame_*.txt"))) == 2
        client.close()
    finally:
        if worker is not None:
            os.killpg(worker.pid, signal.SIGTERM)
            worker.wait(30)
        host.stdin.close()
        try:
            host.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(host.pid, signal.SIGKILL)
