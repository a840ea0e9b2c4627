"""A studio's own stages: the mistakes a plugin author makes are named in one line, and never leave a
result in the cache that a fresh run would not make."""
from __future__ import annotations

import textwrap

import pytest
from pydantic import Field

import pipeline
from pipeline import Registry
from pipeline.errors import ConfigError, PipelineError, StageFailed
from pipeline.stage import Params, Stage
from conftest import REPO
from toy_stages import ToySurface


def _registry(*classes):
    registry = Registry.from_entry_points()
    for cls in classes:
        registry.add(cls)
    return registry


def _render(name, body):
    """A toy render stage (per frame) whose run_frame is ``body``."""
    return type(f"Render_{name}", (Stage,), {
        "kind": "render", "name": name, "version": "1", "inputs": ("raw_surface",), "outputs": ("frames",),
        "per_frame": True, "run_frame": body})


def _cache_entries(cache, kind):
    root = cache / kind
    return [p for p in root.glob("*/*") if p.is_dir()] if root.is_dir() else []


@pytest.mark.parametrize("writes", ["nothing", "an empty folder"])
def test_a_stage_that_writes_nothing_fails_and_commits_nothing(toy_config, tmp_path, writes):
    quiet = _render("quiet", lambda self, ctx, inputs, params, frame: (ctx.out_dir / "sub").mkdir()
                    if writes != "nothing" else None)
    with pytest.raises(StageFailed, match=r"stage render.quiet frame \d failed .*: wrote nothing into its output folder") as exc:
        pipeline.run(toy_config, registry=_registry(quiet), overrides=("render.use=quiet",), cache_dir=tmp_path / "c")
    assert exc.value.exit_code == 1
    assert _cache_entries(tmp_path / "c", "render") == []  # nothing that looks done


def test_a_stage_calling_sys_exit_is_a_failed_stage_not_a_silent_exit(toy_config, tmp_path):
    def body(self, ctx, inputs, params, frame):
        raise SystemExit(3)

    with pytest.raises(StageFailed, match=r"stage render.exits frame \d failed .*the stage called sys.exit\(3\)"):
        pipeline.run(toy_config, registry=_registry(_render("exits", body)), overrides=("render.use=exits",),
                     cache_dir=tmp_path / "c")


@pytest.mark.parametrize("hook", ["check", "estimate"])
@pytest.mark.parametrize("bug", ["KeyError", "SystemExit"])
def test_a_bug_in_a_plan_time_hook_names_the_stage_and_where(toy_config, tmp_path, hook, bug):
    """sys.exit(0) in check() ended the run silently with exit 0 (and a library caller's script with it)."""
    def broken(self, ctx, params):
        if bug == "SystemExit":
            raise SystemExit(0)
        return {}["missing"]

    cls = type("Broken", (ToySurface,), {"name": "broken", hook: broken})
    what = "failed: KeyError: 'missing'" if bug == "KeyError" else r"called sys.exit\(0\)"
    with pytest.raises(StageFailed, match=rf"stage surface_extract.broken: its {hook}\(\) {what} "
                                          rf"\(at .*test_plugins.py:\d+\)"):
        pipeline.run(toy_config, registry=_registry(cls), overrides=("surface_extract.use=broken",),
                     cache_dir=tmp_path / "c")


def test_an_estimate_that_is_not_numbers_is_named(toy_config, tmp_path):
    cls = type("Junk", (ToySurface,), {"name": "junk", "estimate": lambda self, ctx, params: {"memory_bytes": "lots"}})
    with pytest.raises(StageFailed, match=r"surface_extract.junk: its estimate\(\) returned \{'memory_bytes': 'lots'\}"):
        pipeline.run(toy_config, registry=_registry(cls), overrides=("surface_extract.use=junk",),
                     cache_dir=tmp_path / "c")


def test_the_contract_refuses_what_would_run_wrongly():
    class BadDefault(ToySurface):
        name = "bad_default"

        class Params(Params):
            iterations: int = Field(-5, ge=0)

    class StringOutputs(ToySurface):
        name, outputs = "string_outputs", "raw_surface"

    class UseField(ToySurface):
        name = "use_field"

        class Params(Params):
            use: str = "x"

    class Required(ToySurface):
        name = "required"

        class Params(Params):
            lut: str  # required: no default to check

    registry = Registry()
    with pytest.raises(PipelineError, match=r"Params default of iterations \(-5\) is not valid: Input should be greater"):
        registry.add(BadDefault)
    with pytest.raises(PipelineError, match="outputs must be a tuple of names, not 'raw_surface'"):
        registry.add(StringOutputs)
    with pytest.raises(PipelineError, match="Params may not have a field named 'use'"):
        registry.add(UseField)
    registry.add(Required)


def _dist(root, dist, entries):
    info = root / f"{dist.replace('-', '_')}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[pipeline.stages]\n" + textwrap.dedent(entries))


def test_two_packages_registering_one_name_are_refused_not_picked_by_path_order(toy_config, tmp_path, monkeypatch):
    _dist(tmp_path / "a", "studio-a", "surface_extract.dup = toy_stages:ToySurface\n")
    _dist(tmp_path / "b", "studio-b", "surface_extract.dup = other_stages:Surface\n")
    _dist(tmp_path / "c", "studio-c", "wall_snap.distance = toy_stages:ToySurface\n")  # a built-in's name
    for d in "abc":
        monkeypatch.syspath_prepend(str(tmp_path / d))
    registry = Registry.from_entry_points()
    with pytest.raises(ConfigError, match=r"surface_extract.dup .*registered twice, as .*\(from studio-\w 0.1\) and as "
                                          r".*\(from studio-\w 0.1\): uninstall one"):
        pipeline.run(toy_config, registry=registry, overrides=("surface_extract.use=dup",), cache_dir=tmp_path / "c1")
    assert "registered twice" in registry.load_error("wall_snap", "distance")
    assert registry.load_error("surface_extract", "toy") is None  # the others load as before


def test_pipeline_stages_lists_json_and_fails_on_a_broken_plugin(toy_plugin, tmp_path, monkeypatch):
    import json

    from click.testing import CliRunner

    from pipeline.cli import main

    result = CliRunner().invoke(main, ["stages", "--json"])
    assert result.exit_code == 0, result.output
    rows = {(r["kind"], r["name"]): r for r in map(json.loads, result.output.splitlines())}
    toy = rows["surface_extract", "toy"]
    assert toy["source"] == "toy_stages:ToySurface" and toy["outputs"] == ["raw_surface"] and toy["per_frame"]
    assert toy["params"]["iso"] == {"default": 0.5, "required": False, "description": ""}
    _dist(tmp_path, "studio-broken", "render.broken = no_such_module:Render\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    result = CliRunner().invoke(main, ["stages"])
    assert result.exit_code == 1 and "1 stage implementation(s) cannot be loaded: render.broken" in result.output


def test_the_library_runs_with_workers_reads_artifacts_and_refuses_a_string_of_overrides(toy_config, tmp_path):
    report = pipeline.run(toy_config, cache_dir=tmp_path / "c", out_dir=tmp_path / "o", workers=2)
    assert report.stage("render").frames_ran == 4
    surface = report.artifact("raw_surface")
    assert surface.frame(2).joinpath("surface_00002.txt").read_text().endswith("surface 2 iso 0.5")
    with pytest.raises(KeyError, match="no artifact 'nothing'"):
        report.artifact("nothing")
    with pytest.raises(ConfigError, match="expected a sequence of path=value assignments, got the string"):
        pipeline.run(toy_config, overrides="surface_extract.iso=0.4", cache_dir=tmp_path / "c")


def test_a_plugins_cached_kernels_follow_an_edit_to_a_helper_kernel(tmp_path):
    """numba's on-disk cache checks only the file of the function it caches: a plugin kernel calling a helper
    kernel in another module kept the old helper after an edit (a user's sweep: max|v| 1.475 instead of 14.75).
    Decorated inside stages.numba_cache_for, the package's kernels are cached by all of its sources."""
    import os
    import subprocess
    import sys

    pkg = tmp_path / "nbpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("import stages\nwith stages.numba_cache_for(__file__):\n    from . import kern\n")
    (pkg / "kern.py").write_text("import numba\nfrom .kernhelp import f\n\n\n@numba.njit(cache=True)\n"
                                 "def scale(x):\n    return f(x) * 2.0\n")
    helper = pkg / "kernhelp.py"
    helper.write_text("import numba\n\n\n@numba.njit(cache=True)\ndef f(x):\n    return x * 1.0\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]),
               NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    code = "import nbpkg; print(nbpkg.kern.scale(1.5))"
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert first.stdout.strip() == "3.0", first.stderr
    helper.write_text("import numba\n\n\n@numba.njit(cache=True)\ndef f(x):\n    return x * 10.0\n")
    again = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert again.stdout.strip() == "30.0", again.stderr
    assert list((tmp_path / "numba" / "plugins").iterdir()), "the package's kernels are cached under plugins/"


def test_a_script_without_the_main_guard_is_told_so(toy_config, toy_plugin, tmp_path):
    """pipeline.run(workers=2) at a script's top level: each spawned worker imports the script again and
    reached pipeline.run while bootstrapping; about 290 lines of tracebacks ended in 'a worker process died
    (killed, out of memory or a native crash)'. Each worker now says what to do in one line."""
    import os
    import subprocess
    import sys

    script = tmp_path / "noguard.py"
    script.write_text(f"import pipeline\npipeline.run({str(toy_config)!r}, cache_dir={str(tmp_path / 'c')!r}, "
                      f"out_dir={str(tmp_path / 'o')!r}, workers=2)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(toy_plugin), str(REPO / "tests"), str(REPO)]))
    r = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0
    assert "put the call under if __name__ == \"__main__\":" in r.stderr
    assert "bootstrapping phase" not in r.stderr
