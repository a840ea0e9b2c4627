"""The CLI: malformed configs give exit code 2 and one line naming the file, line and field; no traceback."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline import ConfigError
from pipeline.cli import main

from conftest import REPO, TESTS

BAD = sorted((TESTS / "bad_configs").glob("*.yaml"))


def expected(path: Path) -> str:
    first = path.read_bytes().decode("utf-8", "replace").splitlines()  # a corpus file may be no UTF-8 on purpose
    return first[0].removeprefix("# expect:").strip() if path.stat().st_size > 1 else ""


def test_corpus_is_large_enough():
    assert len(BAD) >= 15


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_malformed_config_exit_2_one_line(path, toy_plugin, tmp_path):
    result = CliRunner().invoke(main, ["run", str(path), "--cache", str(tmp_path / "c"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in result.output
    assert str(path) in err
    assert expected(path) in err, err
    assert not (tmp_path / "o").exists() and not (tmp_path / "c").exists()


@pytest.mark.parametrize("assignment,message", [
    ("simulate.steps=abc", "--set simulate.steps: stages.simulate.steps"),
    ("nosuch.x=1", "--set nosuch.x: unknown section"),
    ("fluid.emitters.5.velocity=[1,0,0]", "is a list of 1"),
    ("novalue", "expected path.to.field=value"),
    ("fluid.spacng=0.1", "--set fluid.spacng: fluid.spacng: unknown key (did you mean spacing?)"),
])
def test_bad_set_override(assignment, message, toy_config):
    result = CliRunner().invoke(main, ["run", str(toy_config), "--set", assignment])
    assert result.exit_code == 2, result.output
    assert message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_cli_run_status_clean_smoke(toy_config, toy_plugin):
    """One real subprocess through the console entry (not in-process)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(toy_plugin), str(TESTS), str(REPO)]))
    cli = [sys.executable, "-m", "pipeline.cli"]
    r = subprocess.run(cli + ["run", str(toy_config)], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "frames:" in r.stdout and "run.json" in r.stdout
    r = subprocess.run(cli + ["run", str(toy_config)], env=env, capture_output=True, text=True, timeout=120)
    assert r.stdout.count("cached") == 5, r.stdout
    r = subprocess.run(cli + ["status", str(toy_config)], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.count("cached") >= 5, r.stdout
    r = subprocess.run(cli + ["stages"], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "toy" in r.stdout
    r = subprocess.run(cli + ["clean", str(toy_config)], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "removed" in r.stdout
    r = subprocess.run(cli + ["run", str(toy_config), "--set", "simulate.fail=user"], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "the emitter box is empty" in r.stderr


def test_missing_config_file(tmp_path):
    result = CliRunner().invoke(main, ["run", str(tmp_path / "nope.yaml")])
    assert result.exit_code == 2 and "config file not found" in result.stderr


def test_a_folder_given_as_the_config(tmp_path):
    result = CliRunner().invoke(main, ["run", str(tmp_path)])
    assert result.exit_code == 2 and "a folder, not a config file" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not any(tmp_path.iterdir())


def _one_line_exit_2(result):
    assert result.exit_code == 2, result.output
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.output, result.stderr


@pytest.mark.parametrize("frames", ["5:2", "1:1"])
def test_a_frame_range_that_selects_nothing_is_refused_up_front(frames, toy_config, tmp_path):
    """Accepted before, it simulated and then failed at the movie with "no rendered frames"."""
    result = CliRunner().invoke(main, ["run", str(toy_config), "--frames", frames, "--cache", str(tmp_path / "c"),
                                       "--out", str(tmp_path / "o")])
    _one_line_exit_2(result)
    assert "selects no frame" in result.stderr
    assert not (tmp_path / "c").exists() and not (tmp_path / "o").exists()


@pytest.mark.parametrize("cache, out", [("o/c", "o"), ("c", "c/o"), ("c", "c")])
def test_a_cache_and_an_output_folder_that_overlap_are_refused_up_front(cache, out, toy_config, tmp_path):
    """--cache inside the output folder wrote entries among the published outputs and then blamed the user
    for "a file the pipeline did not publish" (and every later run too); --out inside the cache was
    accepted and its outputs deleted by a later run's sweep (a user's sweep)."""
    result = CliRunner().invoke(main, ["run", str(toy_config), "--cache", str(tmp_path / cache),
                                       "--out", str(tmp_path / out)])
    _one_line_exit_2(result)
    assert "overlap" in result.stderr
    assert not (tmp_path / cache).exists() and not (tmp_path / out).exists()


@pytest.mark.parametrize("flag", ["--out", "--cache"])
def test_an_unwritable_output_or_cache_folder_is_refused_before_any_stage(flag, toy_config, tmp_path):
    """--out /proc/x ran every stage and then failed to publish with a FileNotFoundError (exit 1)."""
    result = CliRunner().invoke(main, ["run", str(toy_config), flag, "/proc/x/y"])
    _one_line_exit_2(result)
    assert "cannot be written: /proc is not writable" in result.stderr
    assert not (toy_config.parent / "ran_mesh_import.log").exists()


def test_a_full_disk_is_no_unwritable_folder(tmp_path):
    """The up-front check refuses folders that cannot be written (exit 2, a user's choice), not a full disk
    (exit 1 where the run writes, as the disk-full suite checks)."""
    import errno
    from unittest import mock

    from pipeline.cache import unwritable

    full = OSError(errno.ENOSPC, "No space left on device")
    with mock.patch("tempfile.mkdtemp", side_effect=full):
        assert unwritable(tmp_path / "out") is None
    with mock.patch("tempfile.mkdtemp", side_effect=OSError(errno.EROFS, "Read-only file system")):
        assert "Read-only file system" in unwritable(tmp_path / "out")


def test_a_lock_timeout_that_is_not_a_number_is_refused(toy_config, tmp_path):
    """nan passed the option's range check and waited forever ("gives up after nan s")."""
    result = CliRunner().invoke(main, ["run", str(toy_config), "--lock-timeout", "nan", "--cache", str(tmp_path / "c")])
    _one_line_exit_2(result)
    assert "--lock-timeout nan" in result.stderr


def test_a_cache_path_that_is_a_file(toy_config, tmp_path):
    (tmp_path / "c").write_text("mine")
    result = CliRunner().invoke(main, ["run", str(toy_config), "--cache", str(tmp_path / "c"), "--out", str(tmp_path / "o")])
    _one_line_exit_2(result)
    assert "is a file, not a folder" in result.stderr and (tmp_path / "c").read_text() == "mine"


def test_a_scheduler_without_the_dask_executor_is_refused(toy_config, tmp_path):
    """It was silently ignored: the shot ran here, not on the cluster the user named."""
    result = CliRunner().invoke(main, ["run", str(toy_config), "--scheduler", "tcp://127.0.0.1:8786",
                                       "--cache", str(tmp_path / "c")])
    _one_line_exit_2(result)
    assert "--scheduler needs --executor dask" in result.stderr and not (tmp_path / "c").exists()


def test_a_batch_is_checked_before_any_shot_runs(toy_plugin, tmp_path):
    """Two shots publishing into the same folder (same scene.name side by side: the second replaced the
    first's frames), or a malformed config after a good one (which ran for its whole length first): exit 2
    before anything runs."""
    from conftest import TOY_CONFIG

    (tmp_path / "a.yaml").write_text(TOY_CONFIG)
    (tmp_path / "b.yaml").write_text(TOY_CONFIG.replace("count: 4", "count: 2"))  # the same scene.name: toy
    (tmp_path / "bad.yaml").write_text(TOY_CONFIG.replace("name: toy", "name: bad").replace("  frames:", "\tframes:"))
    for second, message in (("b.yaml", "the same scene.name"), ("bad.yaml", "bad.yaml:4: not valid YAML")):
        result = CliRunner().invoke(main, ["run", str(tmp_path / "a.yaml"), str(tmp_path / second),
                                           "--cache", str(tmp_path / "c")])
        _one_line_exit_2(result)
        assert message in result.stderr, result.stderr
        assert not (tmp_path / "c").exists() and not (tmp_path / "out").exists()


def test_a_default_stage_that_fails_to_import_is_named(toy_config):
    """A broken install (the default simulate's module missing): the error says which stage failed to load
    and why, not only that nothing produces the output."""
    from importlib.metadata import EntryPoint

    from pipeline.config import load_config
    from pipeline.graph import build_graph
    from pipeline.registry import Registry, _Entry

    reg = Registry.from_entry_points()
    for name in reg.implementations("simulate"):
        del reg._entries[("simulate", name)]
    ep = EntryPoint("simulate.sph", "no_such_module.sph:SPHSimulate", "fluid_pipeline.stages")
    reg._entries[("simulate", "sph")] = _Entry("simulate", "sph", ep.value, ep)
    toy_config.write_text(toy_config.read_text().replace("  simulate: {use: toy}\n", ""))
    with pytest.raises(ConfigError, match=r"'particles', which no configured stage produces; the default simulate stage "
                                          r"failed to load: .*ModuleNotFoundError: No module named 'no_such_module'"):
        build_graph(load_config(toy_config, reg))


def test_a_bad_value_set_over_a_section_is_blamed_on_the_set_not_the_file(toy_config, tmp_path):
    """--set 'effects.viscosity={mu: -1}' replaces the file's effects.viscosity: the error names the --set,
    not the file's line of the mu it replaced."""
    toy_config.write_text(toy_config.read_text() + "effects:\n  viscosity: {mu: 0.001}\n")
    result = CliRunner().invoke(main, ["run", str(toy_config), "--set", "effects.viscosity={mu: -1}",
                                       "--cache", str(tmp_path / "c")])
    _one_line_exit_2(result)
    assert "--set effects.viscosity: effects.viscosity.mu" in result.stderr, result.stderr


def test_a_section_check_a_set_breaks_names_the_set(tmp_path):
    """A check across a stage's fields that a --set broke was blamed on the file's 'render:' line alone."""
    cfg = REPO / "configs" / "dam_break.yaml"
    result = CliRunner().invoke(main, ["run", str(cfg), "--set", "render.color_range=[2,1]", "--cache", str(tmp_path / "c")])
    _one_line_exit_2(result)
    assert "(with --set render.color_range): stages.render: Value error, color_range [2.0, 1.0]" in result.stderr


def test_a_scene_config_given_to_study_says_so(tmp_path):
    cfg = REPO / "configs" / "dam_break.yaml"
    result = CliRunner().invoke(main, ["study", str(cfg)])
    _one_line_exit_2(result)
    assert "a scene config (config_version), not a study: run it with `pipeline run" in result.stderr


def test_python_dash_m_pipeline_is_the_command(tmp_path):
    """`python -m pipeline` (a habit when the console script is not on PATH) is the same command line; it was
    'No module named pipeline.__main__'."""
    cli = [sys.executable, "-m", "pipeline"]
    r = subprocess.run(cli + ["--help"], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 0 and "Usage: pipeline" in r.stdout and "study" in r.stdout, r.stderr
    r = subprocess.run(cli + ["run", str(tmp_path / "none.yaml")], capture_output=True, text=True, timeout=120,
                       cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 2 and r.stderr.strip() == f"error: {tmp_path / 'none.yaml'}: config file not found"


@pytest.mark.parametrize("where", ["default", "--out"])
def test_a_file_above_the_output_folder_is_refused_before_any_stage(where, toy_config, tmp_path):
    """A user's file named ``out`` beside the config: the stages ran, then publishing failed (exit 1)."""
    blocker = tmp_path / "out"
    blocker.write_text("mine")
    args = ["run", str(toy_config), "--cache", str(tmp_path / "c")]
    if where == "--out":
        args += ["--out", str(blocker / "shots" / "toy")]
    result = CliRunner().invoke(main, args)
    _one_line_exit_2(result)
    assert f"{blocker} is a file, not a folder" in result.stderr, result.stderr
    assert blocker.read_text() == "mine" and not (tmp_path / "c").exists()
    assert not (tmp_path / "ran_mesh_import.log").exists()


def test_a_file_above_the_cache_folder_is_refused(toy_config, tmp_path):
    (tmp_path / "f").write_text("mine")
    result = CliRunner().invoke(main, ["run", str(toy_config), "--cache", str(tmp_path / "f" / "c"),
                                       "--out", str(tmp_path / "o")])
    _one_line_exit_2(result)
    assert f"{tmp_path / 'f'} is a file, not a folder" in result.stderr and (tmp_path / "f").read_text() == "mine"
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["PIPELINE_LOCK_TIMEOUT", "PIPELINE_TMP_MAX_AGE", "PIPELINE_LOG_EVERY"])
@pytest.mark.parametrize("value", ["abc", "-5", "nan", "inf"])
def test_a_bad_environment_variable_is_one_line_exit_2(name, value, toy_config, tmp_path):
    """PIPELINE_LOCK_TIMEOUT=abc was a traceback at import (exit 1); -5 was accepted though --lock-timeout -5
    is refused; inf was said as "--lock-timeout None", a flag never given. A real subprocess: the values were read
    when pipeline.cache was imported."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), str(REPO)]), **{name: value})
    r = subprocess.run([sys.executable, "-m", "pipeline", "run", str(toy_config), "--cache", str(tmp_path / "c"),
                        "--out", str(tmp_path / "o")], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == f"error: environment variable {name}={value!r}: expected a finite number of seconds >= 0"
    assert not (tmp_path / "c").exists() and not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["abc", "0", "-2", "1.5"])
def test_a_bad_numba_thread_count_is_one_line_exit_2(value, toy_config, tmp_path):
    """NUMBA_NUM_THREADS=abc printed numba's traceback and the run went on; 0 failed in a stage's import, said as
    the config's simulate line being wrong."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), str(REPO)]), NUMBA_NUM_THREADS=value)
    r = subprocess.run([sys.executable, "-m", "pipeline", "run", str(toy_config), "--cache", str(tmp_path / "c"),
                        "--out", str(tmp_path / "o")], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == (f"error: environment variable NUMBA_NUM_THREADS={value!r}: expected a whole number of "
                                "threads >= 1 (or leave it unset: every core)")
    assert not (tmp_path / "c").exists() and not (tmp_path / "o").exists()


def test_a_run_logged_to_a_file_says_a_long_stages_progress(toy_config, tmp_path, monkeypatch, caplog):
    """A render farm's log (stderr no terminal) had nothing from a 2-minute simulation until the run's end: the
    bars are drawn on a terminal only. A stage now says where it is every PIPELINE_LOG_EVERY seconds (30 by
    default, so the toy's short stages say nothing)."""
    import logging

    from pipeline import cli, runner

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    assert cli._progress_mode(quiet=False) == "log" and cli._progress_mode(quiet=True) is False
    monkeypatch.setenv("PIPELINE_LOG_EVERY", "0")
    with caplog.at_level(logging.INFO, logger="pipeline"):
        runner.run(toy_config, cache_dir=tmp_path / "c1", out_dir=tmp_path / "o1", progress="log")
    lines = [r.getMessage() for r in caplog.records if "render frames:" in r.getMessage()]
    assert any(ln.startswith("render frames: 4 of 4 (100 %) in") for ln in lines), lines
    assert any(ln.endswith("s left") for ln in lines), lines  # and how long is left on the way
    caplog.clear()
    monkeypatch.delenv("PIPELINE_LOG_EVERY")
    with caplog.at_level(logging.INFO, logger="pipeline"):
        runner.run(toy_config, cache_dir=tmp_path / "c2", out_dir=tmp_path / "o2", progress="log")
    assert not [r for r in caplog.records if "render frames:" in r.getMessage()]


def test_a_good_environment_variable_is_used(monkeypatch, tmp_path):
    from pipeline.cache import Cache

    monkeypatch.setenv("PIPELINE_LOCK_TIMEOUT", "12.5")
    assert Cache(tmp_path / "c").lock_timeout == 12.5
    monkeypatch.setenv("PIPELINE_LOCK_TIMEOUT", "")
    assert Cache(tmp_path / "c").lock_timeout == 3600


def test_clean_with_set_drops_that_variants_entries(toy_config, tmp_path):
    """clean dropped only the entries of the config without overrides: a --set variant's stayed."""
    from conftest import ran

    cache = ["--cache", str(tmp_path / "c")]
    r = CliRunner().invoke(main, ["run", str(toy_config), "-q", *cache, "--set", "simulate.steps=5"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["run", str(toy_config), "-q", *cache])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["clean", str(toy_config), *cache, "--set", "simulate.steps=5", "--stage", "render"])
    assert r.exit_code == 0 and "removed 4 cache entries" in r.output, r.output
    r = CliRunner().invoke(main, ["run", str(toy_config), "-q", *cache, "--set", "simulate.steps=5"])
    assert r.exit_code == 0 and ran(toy_config, "render") == 12 and ran(toy_config, "simulate") == 2, r.output
    r = CliRunner().invoke(main, ["clean", str(toy_config), *cache, "--set", "simulate.steps=abc"])
    assert r.exit_code == 2 and "--set simulate.steps" in r.stderr, r.output
    assert "Entries made under other --set overrides or earlier versions of the config stay" in " ".join(
        CliRunner().invoke(main, ["clean", "--help"]).output.split())


@pytest.mark.parametrize("args, message", [
    (["--force", "simulate", "--only", "render"], "--force simulate: not a stage this run includes (render)"),
    (["--force", "simulate", "--from", "render"], "--force simulate: not a stage this run includes (render)"),
    (["--force", "render", "--until", "simulate"], "--force render: not a stage this run includes (mesh_import, "
                                                   "sdf_bake, simulate)"),
    (["--from", "render", "--until", "simulate"], "--from render comes after --until simulate: nothing would run"),
])
def test_partial_run_options_that_contradict_are_refused(args, message, toy_config, tmp_path):
    """--force of a stage --only/--from reads from the cache was ignored without a word (all cached, exit 0),
    and --from after --until said "--from render: not a stage this config runs", though it is."""
    from conftest import ran

    cache = ["--cache", str(tmp_path / "c"), "--out", str(tmp_path / "o")]
    assert CliRunner().invoke(main, ["run", str(toy_config), "-q", *cache]).exit_code == 0
    result = CliRunner().invoke(main, ["run", str(toy_config), "-q", *cache, *args])
    _one_line_exit_2(result)
    assert message in result.stderr, result.stderr
    assert ran(toy_config, "simulate") == 1


def test_clean_of_a_cache_that_is_not_there_says_so_and_makes_nothing(toy_config, tmp_path):
    """It made the folder (with locks/runs.lock) and said "removed 0 cache entries"; exit 0 as status of a
    missing cache."""
    result = CliRunner().invoke(main, ["clean", str(toy_config), "--cache", str(tmp_path / "nonexistent")])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"no cache at {tmp_path / 'nonexistent'}; nothing removed"
    assert not (tmp_path / "nonexistent").exists()
    assert CliRunner().invoke(main, ["status", str(toy_config), "--cache", str(tmp_path / "nonexistent")]).exit_code == 0
    assert not (tmp_path / "nonexistent").exists()


def test_frames_are_each_counted_once_and_given_once(toy_config, tmp_path):
    """--frames 0,0,3 kept the repeat (status counted 2 frames for "0,0", run.json recorded [0, 0, 3] and the movie
    was keyed apart from 0,3); a second --frames silently replaced the first."""
    import json

    from pipeline.runner import parse_frames

    assert parse_frames("3,0,0") == (0, 3) and parse_frames("0:3") == (0, 1, 2)
    cache = ["--cache", str(tmp_path / "c"), "--out", str(tmp_path / "o")]
    result = CliRunner().invoke(main, ["run", str(toy_config), "-q", *cache, "--frames", "0,0,3"])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "o" / "run.json").read_text())["frames"] == [0, 3]
    result = CliRunner().invoke(main, ["status", str(toy_config), *cache[:2], "--frames", "0,0"])
    assert result.exit_code == 0 and "1 frames" in result.output, result.output
    for command in (["run", "-q", *cache], ["status", *cache[:2]]):
        result = CliRunner().invoke(main, [command[0], str(toy_config), *command[1:], "--frames", "0:2", "--frames", "3"])
        _one_line_exit_2(result)
        assert "--frames given 2 times (0:2, 3)" in result.stderr, result.stderr
