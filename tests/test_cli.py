"""The CLI: malformed configs give exit code 2 and one line naming the file, line and field; no traceback."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import main

from conftest import REPO, TESTS

BAD = sorted((TESTS / "bad_configs").glob("*.yaml"))


def expected(path: Path) -> str:
    return path.read_text().splitlines()[0].removeprefix("# expect:").strip() if path.stat().st_size > 1 else ""


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
