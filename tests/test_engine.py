"""The engine against small toy stages: cache hits and invalidation, partial runs, overrides,
killed and concurrent runs, damaged entries, plugin discovery."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import pipeline
from pipeline import CacheMissError, ConfigError, Registry, StageFailed
from pipeline.cache import Cache

from conftest import REPO, TESTS, ran, spans


def run(config, **kw):
    return pipeline.run(config, registry=Registry.from_entry_points(), **kw)


def statuses(report):
    return {s.kind: s.status for s in report.stages}


def test_plugin_discovered_through_entry_point(toy_plugin):
    reg = Registry.from_entry_points()
    assert "toy" in reg.implementations("simulate")
    cls = reg.get("simulate", "toy")
    assert cls.__name__ == "ToySimulate"


def test_first_run_runs_everything_second_run_nothing(toy_config):
    r1 = run(toy_config)
    assert set(statuses(r1).values()) == {"ran"}
    out = Path(r1.out)
    frames = sorted(p.name for p in (out / "frames").iterdir())
    assert frames == [f"frame_{i:05d}.txt" for i in range(4)]
    assert "surface 2" in (out / "frames" / "frame_00002.txt").read_text()
    r2 = run(toy_config)
    assert set(statuses(r2).values()) == {"cached"}
    assert ran(toy_config, "simulate") == 1 and ran(toy_config, "render") == 4  # nothing ran again
    manifest = json.loads((out / "run.json").read_text())
    assert [s["status"] for s in manifest["stages"]] == ["cached"] * 5
    assert manifest["overrides"] == [] and manifest["frames"] is None and manifest["finished"].endswith("Z")
    # a per-frame stage's cost is its frames' own seconds (it read 0: a study timing render charged nothing)
    render = next(s for s in manifest["stages"] if s["kind"] == "render")
    made = [json.loads(m.read_text()) for m in Path(r1.cache).rglob("manifest.json") if '"render' in m.read_text()]
    assert len(made) == 4 and render["cost_seconds"] > 0
    assert render["cost_seconds"] == pytest.approx(sum(m["seconds"] for m in made))
    assert render["cpu_seconds"] == pytest.approx(sum(m["cpu_seconds"] for m in made))
    # run.json says what the outputs were made with beyond the file: the --set values and the frame selection
    run(toy_config, overrides=("surface_extract.iso=0.7",), frames=(1, 2))
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["overrides"] == ["surface_extract.iso=0.7"] and manifest["frames"] == [1, 2]
    # and the settings themselves, as read (the file may be edited after the run: run.json kept only its path)
    assert manifest["settings"]["stages"]["surface_extract"]["iso"] == 0.7
    assert manifest["settings"]["scene"]["frames"]["count"] == 4


def test_only_the_stages_the_outputs_need_run(toy_config):
    r = run(toy_config, overrides=("outputs=[particles]",))
    assert statuses(r) == {"mesh_import": "ran", "sdf_bake": "ran", "simulate": "ran"}
    assert set(r.outputs) == {"particles"}
    assert ran(toy_config, "surface_extract") == 0 and ran(toy_config, "render") == 0


def test_param_change_reruns_stage_and_downstream_only(toy_config):
    run(toy_config)
    r = run(toy_config, overrides=("surface_extract.iso=0.7",))
    assert statuses(r) == {"mesh_import": "cached", "sdf_bake": "cached", "simulate": "cached",
                           "surface_extract": "ran", "render": "ran"}
    assert "iso 0.7" in (Path(r.out) / "frames" / "frame_00000.txt").read_text()
    r = run(toy_config, overrides=("render.width=32",))
    assert statuses(r)["surface_extract"] == "cached" and statuses(r)["render"] == "ran"


def test_scene_change_invalidates_stages_that_read_it(toy_config):
    run(toy_config)
    r = run(toy_config, overrides=("fluid.spacing=0.05",))
    # only simulate reads 'fluid'; sdf_bake does not
    assert statuses(r)["sdf_bake"] == "cached" and statuses(r)["simulate"] == "ran"


def test_code_version_change_invalidates(toy_config, monkeypatch):
    run(toy_config)
    import toy_stages

    monkeypatch.setattr(toy_stages.ToySimulate, "version", "2")
    r = run(toy_config)
    assert statuses(r)["simulate"] == "ran" and statuses(r)["sdf_bake"] == "cached"
    assert statuses(r)["render"] == "ran"  # upstream key changed


def test_external_file_content_is_hashed(toy_config):
    src = toy_config.parent / "model.txt"
    src.write_text("v1")
    run(toy_config, overrides=("mesh_import.source=model.txt",))
    src.write_text("v2")
    rows = {s.kind: s for s in pipeline.status(toy_config, registry=Registry.from_entry_points(),
                                               overrides=("mesh_import.source=model.txt",))}
    assert rows["mesh_import"].state == "stale" and "model.txt" in rows["mesh_import"].reason
    r = run(toy_config, overrides=("mesh_import.source=model.txt",))
    assert statuses(r)["mesh_import"] == "ran"
    assert "v2" in (Path(r.out) / "frames" / "frame_00000.txt").read_text()


def test_an_input_edited_during_the_run_leaves_no_entry_under_the_old_key(toy_config):
    """Keys hash the input files when the run is planned; a stage reads them later (a camera after the
    whole simulation). A user's edit in between made an entry under the old content's key from the new
    content, and later runs served it as up to date (a user's sweep: frames and USD from camera B where
    the key said A; frames 0-12 from A and 13-29 from B in one entry). Now the stage fails (exit 1, one
    line) and keeps nothing; the next run makes the entry from what the file holds then."""
    src = toy_config.parent / "model.txt"
    src.write_text("A")
    edit = ("mesh_import.source=model.txt", "mesh_import.edit=B")
    with pytest.raises(StageFailed, match=r"stage mesh_import.toy: model\.txt changed while the run used it") as e:
        run(toy_config, overrides=edit)
    assert e.value.exit_code == 1
    src.write_text("A")  # the user puts it back: nothing made under A's key from B (or from A) may be served
    rows = {s.kind: s.state for s in pipeline.status(toy_config, registry=Registry.from_entry_points(),
                                                     overrides=("mesh_import.source=model.txt",))}
    assert rows["mesh_import"] == "missing"
    r = run(toy_config, overrides=("mesh_import.source=model.txt",))
    assert "walls 1 A" in (Path(r.out) / "frames" / "frame_00000.txt").read_text()

    # per frame: a camera edited while frame 1 is drawn keeps frame 0 (made from A) and refuses frame 1
    cam = toy_config.parent / "cam.txt"
    cam.write_text("camera A")
    (toy_config.parent / "edit_camera").touch()
    shot = ("mesh_import.source=model.txt", "render.camera=cam.txt", "render.edit_at=1")
    with pytest.raises(StageFailed, match=r"stage render.toy frame 1 .*cam\.txt changed while the run used it"):
        run(toy_config, overrides=shot)
    assert ran(toy_config, "render") == 4 + 2
    cam.write_text("camera A")
    run(toy_config, overrides=shot)
    assert ran(toy_config, "render") == 4 + 2 + 3  # frame 0 served from cache, frames 1-3 made from A


def test_force_recomputes_instead_of_resuming_a_killed_runs_checkpoints(toy_config):
    """A killed run leaves checkpoints under its key; a later run resumes from them, but --force means
    "recompute": it resumed (a user's sweep: "resumed from the checkpoint at frame 30" in 1 s)."""
    r = run(toy_config, until="simulate")
    key = next(s.key for s in r.stages if s.kind == "simulate")
    cache = Cache(toy_config.parent / ".pipeline")
    cache.checkpoint_dir(key).mkdir(parents=True, exist_ok=True)
    (cache.checkpoint_dir(key) / "state_00030.npz").write_bytes(b"x")
    r = run(toy_config, until="simulate", force=("simulate",))
    entry = cache.lookup("simulate", key)
    assert statuses(r)["simulate"] == "forced" and (entry.path / "checkpoints_seen.txt").read_text() == ""


def test_only_needs_cached_inputs(toy_config):
    with pytest.raises(CacheMissError, match="mesh_import.toy is not cached"):
        run(toy_config, only="simulate")
    run(toy_config)
    r = run(toy_config, only="render", force=("render",))
    assert statuses(r) == {"mesh_import": "cached", "sdf_bake": "cached", "simulate": "cached",
                           "surface_extract": "cached", "render": "forced"}
    assert ran(toy_config, "render") == 8 and ran(toy_config, "simulate") == 1


def test_until_stops_and_from_reads_upstream_from_cache(toy_config):
    r = run(toy_config, until="simulate")
    assert [s.kind for s in r.stages] == ["mesh_import", "sdf_bake", "simulate"]
    assert ran(toy_config, "render") == 0
    r = run(toy_config, from_="surface_extract")
    assert statuses(r)["simulate"] == "cached" and statuses(r)["render"] == "ran"
    # --from a stage whose upstream is stale: the stale upstream is not run, that is an error
    with pytest.raises(CacheMissError):
        run(toy_config, from_="render", overrides=("simulate.steps=5",))


def test_from_runs_the_stage_and_its_descendants_only(toy_config):
    """--from render after a run stopped before export: export is not downstream of render, so it is neither
    run nor required in the cache (it was: CacheMissError 'stage export.toy is not cached')."""
    toy_config.write_text(toy_config.read_text().replace("outputs: [frames]", "outputs: [frames, usd]"))
    run(toy_config, until="surface_extract")
    r = run(toy_config, from_="render")
    assert statuses(r) == {"mesh_import": "cached", "sdf_bake": "cached", "simulate": "cached",
                           "surface_extract": "cached", "render": "ran"}
    assert set(r.outputs) == {"frames"} and ran(toy_config, "export") == 0
    # a full run then makes the export; --from render again leaves its published usd/ alone
    r = run(toy_config)
    assert statuses(r)["export"] == "ran" and statuses(r)["render"] == "cached"
    r = run(toy_config, from_="render", force=("render",))
    assert "export" not in statuses(r) and (Path(r.out) / "usd").is_dir() and ran(toy_config, "export") == 1
    with pytest.raises(ConfigError, match="--force export: not a stage this run includes"):
        run(toy_config, from_="render", force=("export",))
    # --from simulate still makes both branches
    r = run(toy_config, from_="simulate", force=("simulate",))
    assert set(r.outputs) == {"frames", "usd"}


def test_force_recomputes_one_stage(toy_config):
    run(toy_config)
    r = run(toy_config, force=("sdf_bake",))
    assert statuses(r)["sdf_bake"] == "forced" and statuses(r)["simulate"] == "cached"
    assert ran(toy_config, "sdf_bake") == 2


def test_per_frame_stages_cache_per_frame(toy_config):
    run(toy_config, frames=(0, 1))
    assert ran(toy_config, "render") == 2
    r = run(toy_config)
    assert r.stage("render").frames_ran == 2 and ran(toy_config, "render") == 4


def test_status_reports_missing_cached_stale_with_cause(toy_config):
    reg = Registry.from_entry_points()
    assert {r.state for r in pipeline.status(toy_config, registry=reg)} == {"missing"}
    run(toy_config)
    assert {r.state for r in pipeline.status(toy_config, registry=reg)} == {"cached"}
    rows = {r.kind: r for r in pipeline.status(toy_config, registry=reg, overrides=("sdf_bake.cell=0.25",))}
    assert rows["mesh_import"].state == "cached"
    assert rows["sdf_bake"].state == "stale" and "cell" in rows["sdf_bake"].reason and "0.25" in rows["sdf_bake"].reason
    assert rows["simulate"].state == "stale" and "upstream sdf" in rows["simulate"].reason


def test_damaged_entry_is_rebuilt(toy_config):
    run(toy_config)
    cache = Cache(toy_config.parent / ".pipeline")
    entry = next((cache.root / "simulate").glob("*/*/particles.txt"))
    entry.write_text("garbage")  # same entry, different content
    rows = {r.kind: r for r in pipeline.status(toy_config, registry=Registry.from_entry_points())}
    assert rows["simulate"].state == "stale" and "damaged" in rows["simulate"].reason
    r = run(toy_config)
    assert statuses(r)["simulate"] == "ran"
    assert "garbage" not in entry.read_text()


def test_stage_errors_name_the_stage(toy_config):
    with pytest.raises(StageFailed, match=r"stage simulate.toy: the emitter box is empty") as e:
        run(toy_config, overrides=("simulate.fail=user",))
    assert e.value.exit_code == 2
    with pytest.raises(StageFailed, match=r"simulate.toy failed .*RuntimeError: boom") as e:
        run(toy_config, overrides=("simulate.fail=bug",))
    assert e.value.exit_code == 1
    cache = Cache(toy_config.parent / ".pipeline")
    assert not list((cache.root / "simulate").glob("*/*/manifest.json"))
    assert not list((cache.root / "tmp").iterdir())


def test_a_failed_run_that_exits_1_saves_its_traceback(toy_config):
    """A simulation's blow-up (an exit-1 PipelineError from the stage) left logs/ empty, though an exit 1
    promises a traceback there; a user's mistake (exit 2) saves none."""
    logs = toy_config.parent / ".pipeline" / "logs"
    with pytest.raises(StageFailed, match=r"^stage simulate.toy: the toy run blew up during frame 1 "
                                          r"\(traceback in .*/logs/simulate-\w{12}\.log\)$") as e:
        run(toy_config, overrides=("simulate.fail=diverged",))
    assert e.value.exit_code == 1
    saved = list(logs.glob("simulate-*.log"))
    assert len(saved) == 1 and "Diverged: the toy run blew up" in saved[0].read_text()
    saved[0].unlink()
    with pytest.raises(StageFailed) as e:
        run(toy_config, overrides=("simulate.fail=user",))
    assert e.value.exit_code == 2 and not list(logs.glob("simulate-*.log"))


def test_a_ctrl_c_wrapped_by_a_library_is_an_interrupt_not_a_failed_stage(toy_config):
    """A Ctrl-C arriving inside numba's dispatcher came out of a stage as a SystemError ("returned a result with an
    exception set"), and the run was said as a failed stage, exit 1, with a log (a tester's sweep)."""
    logs = toy_config.parent / ".pipeline" / "logs"
    with pytest.raises(KeyboardInterrupt):
        run(toy_config, overrides=("simulate.fail=interrupted",))
    assert not list(logs.glob("simulate-*.log"))
    cache = Cache(toy_config.parent / ".pipeline")
    assert not list((cache.root / "simulate").glob("*/*/manifest.json"))


def test_clean_removes_entries(toy_config):
    run(toy_config)
    n = pipeline.clean(toy_config, registry=Registry.from_entry_points(), stage="render")
    assert n == 4
    r = run(toy_config)
    assert statuses(r)["render"] == "ran" and statuses(r)["surface_extract"] == "cached"


def test_clean_removes_the_frames_of_a_shot_since_shortened(toy_config):
    """The last run made 4 frames, the config now has 2: clean looped over the config's frames only and
    left frames 2-3 of every per-frame stage behind (a user's sweep)."""
    run(toy_config)
    toy_config.write_text(toy_config.read_text().replace("count: 4", "count: 2"))
    n = pipeline.clean(toy_config, registry=Registry.from_entry_points(), stage="render")
    assert n == 4
    cache = Cache(toy_config.parent / ".pipeline")
    assert not any((cache.root / "render").rglob("manifest.json"))


def test_clean_while_a_run_uses_the_cache_is_refused_and_removes_nothing(toy_config):
    """A clean during a run removed entries the run had made and was about to read, and the run failed
    blaming the user (exit 2). The run holds the cache shared for its length; clean needs it alone."""
    run(toy_config)
    cache = Cache(toy_config.parent / ".pipeline")
    with cache.in_use():  # as a running shot does
        with pytest.raises(StageFailed, match=r"clean: a run is using the cache .*\(nothing was removed\)") as e:
            pipeline.clean(toy_config, registry=Registry.from_entry_points())
    assert e.value.exit_code == 1
    assert all(s == "cached" for s in statuses(run(toy_config)).values())
    assert pipeline.clean(toy_config, registry=Registry.from_entry_points()) > 0  # and after the run, it cleans


def _cli_env(toy_plugin) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(toy_plugin), str(TESTS), str(REPO), env.get("PYTHONPATH", "")])
    return env


def _cli(*args) -> list[str]:
    return [sys.executable, "-m", "pipeline.cli", *args]


def test_killed_run_leaves_consistent_cache(toy_config, toy_plugin):
    proc = subprocess.Popen(_cli("run", str(toy_config), "-q", "--set", "simulate.sleep=30", "--set", "simulate.steps=30"),
                            env=_cli_env(toy_plugin), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    cache = Cache(toy_config.parent / ".pipeline")
    deadline = time.time() + 60
    while time.time() < deadline and not list((cache.root / "tmp").glob("*/particles.txt")):
        time.sleep(0.1)
    assert list((cache.root / "tmp").glob("*/particles.txt")), "the stage never started writing"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # nothing that looks finished
    assert not list((cache.root / "simulate").glob("*/*/manifest.json"))
    rows = {r.kind: r.state for r in pipeline.status(toy_config, registry=Registry.from_entry_points(),
                                                      overrides=("simulate.sleep=30", "simulate.steps=30"))}
    assert rows["sdf_bake"] == "cached" and rows["simulate"] in ("missing", "stale")
    r = run(toy_config, overrides=("simulate.sleep=0", "simulate.steps=30"))
    assert statuses(r)["simulate"] == "ran"
    assert not list((cache.root / "tmp").iterdir()), "leftovers of the killed run were not swept"


def test_concurrent_runs_share_one_cache(toy_config, toy_plugin):
    cmd = _cli("run", str(toy_config), "-q", "--set", "simulate.sleep=2")
    procs = [subprocess.Popen(cmd, env=_cli_env(toy_plugin), stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert ran(toy_config, "simulate") == 1  # the second run waited on the lock, then hit the cache
    assert ran(toy_config, "render") == 4
    r = run(toy_config, overrides=("simulate.sleep=2",))
    assert set(statuses(r).values()) == {"cached"}


def test_process_pool_gives_same_result(toy_config):
    from pipeline.executors import ProcessExecutor

    r1 = run(toy_config)
    a = {p.name: p.read_text() for p in (Path(r1.out) / "frames").iterdir()}
    pipeline.clean(toy_config, registry=Registry.from_entry_points(), stage="render")
    ex = ProcessExecutor(2)
    try:
        r2 = run(toy_config, executor=ex)
    finally:
        ex.close()
    assert r2.stage("render").frames_ran == 4
    b = {p.name: p.read_text() for p in (Path(r2.out) / "frames").iterdir()}
    assert a == b


def test_unknown_force_and_frames_are_errors(toy_config):
    with pytest.raises(ConfigError, match="--frames: frame 9"):
        run(toy_config, frames=(9,))
    with pytest.raises(ConfigError, match="--only export"):
        run(toy_config, only="export")


def test_a_per_frame_stage_sums_up_all_of_a_runs_frames_once_in_this_process(toy_config):
    """Stage.summarise: a per-frame stage whose frames run in worker processes says what only all of them tell
    (surface_extract: how many frames came out empty) once per run, in the process driving it, over every frame
    of the run (cached ones too) once they are all in the cache; not when the whole stage came from the cache,
    nor when a frame failed; a failing summary fails the stage as any failure does (its traceback saved)."""
    from pipeline.executors import ProcessExecutor

    log = toy_config.parent / "summarised.log"

    def calls():
        return log.read_text().splitlines() if log.exists() else []

    ex = ProcessExecutor(2)
    try:
        assert run(toy_config, executor=ex).stage("surface_extract").frames_ran == 4
    finally:
        ex.close()
    assert calls() == [f"{os.getpid()} 0 1 2 3 out_dir=None"]
    run(toy_config)
    run(toy_config, frames=(1, 2))
    assert len(calls()) == 1  # all from the cache
    run(toy_config, overrides=("surface_extract.iso=0.4",), frames=(1, 2))
    run(toy_config, overrides=("surface_extract.iso=0.4",))  # 0 and 3 run, 1 and 2 from the cache
    assert calls()[1:] == [f"{os.getpid()} 1 2 out_dir=None", f"{os.getpid()} 0 1 2 3 out_dir=None"]
    with pytest.raises(StageFailed, match="frame 2 has no particles"):
        run(toy_config, overrides=("surface_extract.fail=frame",))
    assert len(calls()) == 3
    with pytest.raises(StageFailed, match=r"stage surface_extract.toy failed .*RuntimeError: summary boom "
                                          r"\(traceback in .*\.log\)") as e:
        run(toy_config, overrides=("surface_extract.fail=summary",))
    assert "in summarise" in Path(str(e.value).rsplit("traceback in ", 1)[1].rstrip(")")).read_text()


def test_independent_branches_run_concurrently_with_a_pool(toy_config):
    """render (per-frame, in worker processes) and export (whole-run) only share upstream: with a pool
    they overlap in time; inline they run one after the other. Same outputs either way."""
    from pipeline.executors import ProcessExecutor

    sets = ("outputs=[frames, usd]", "render.sleep=0.6", "export.sleep=0.5", "export.wait_for=render")
    ex = ProcessExecutor(2)
    try:
        r = run(toy_config, overrides=sets, executor=ex)
    finally:
        ex.close()
    assert statuses(r)["export"] == "ran" and r.stage("render").frames_ran == 4
    (e0, e1), = spans(toy_config, "export")
    render = spans(toy_config, "render")
    assert any(a < e1 and b > e0 for a, b in render), (render, (e0, e1))
    assert (Path(r.out) / "usd" / "scene.txt").read_text().endswith("...")


def test_dask_executor_gives_same_result(toy_config, toy_plugin):
    """A real (local, in-process) Dask cluster runs the per-frame jobs; outputs equal the inline run."""
    from distributed import LocalCluster

    from pipeline.executors import DaskExecutor

    r1 = run(toy_config)
    a = {p.name: p.read_text() for p in (Path(r1.out) / "frames").iterdir()}
    pipeline.clean(toy_config, registry=Registry.from_entry_points(), stage="render")
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        ex = DaskExecutor(cluster.scheduler_address)
        try:
            r2 = run(toy_config, executor=ex)
        finally:
            ex.close()
    assert r2.stage("render").frames_ran == 4
    assert a == {p.name: p.read_text() for p in (Path(r2.out) / "frames").iterdir()}


def test_a_second_scene_published_into_the_same_folder_is_refused(toy_config, tmp_path):
    """Two scenes run one after the other with the same --out: the second replaced the first's outputs, exit 0,
    without a word (a batch refuses this). The folder's record names the scene it holds; another scene is refused
    before anything runs and the first's outputs stay; the same scene (an edit, a re-run) still replaces them."""
    from pipeline.publish import OutputRefused

    out, cache = tmp_path / "out", tmp_path / "cache"
    pipeline.run(toy_config, cache_dir=cache, out_dir=out)
    before = sorted(p.name for p in (out / "frames").iterdir())
    other = toy_config.parent / "other.yaml"
    other.write_text(toy_config.read_text().replace("name: toy", "name: other"))
    with pytest.raises(OutputRefused, match=r"holds the outputs of scene 'toy' \(.*toy.yaml\); this run of scene "
                                            r"'other' would replace them"):
        pipeline.run(other, cache_dir=cache, out_dir=out)
    assert sorted(p.name for p in (out / "frames").iterdir()) == before
    assert ran(other, "simulate") == ran(toy_config, "simulate") == 1  # refused before anything ran
    toy_config.write_text(toy_config.read_text().replace("count: 4", "count: 3"))
    pipeline.run(toy_config, cache_dir=cache, out_dir=out)  # the same scene, edited
    assert len(list((out / "frames").iterdir())) == 3
