"""Cache keys hold exactly what a result depends on: the declared config fields, the frame selection,
input files, the code; a longer shot continues from the cached shorter one, bitwise."""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

import pipeline
from pipeline import Registry
from pipeline.cache import Cache
from pipeline.config import load_config
from pipeline.graph import build_graph
import pipeline.keys as keys_module
from pipeline.errors import CodeChanged
from pipeline.keys import plan
from pipeline.reads import UndeclaredRead
from pipeline.testing import scene_sections, stage_context
from stages.common.formats import frame_path

TINY = """\
config_version: 1
scene:
  name: tiny
  frames: {fps: 30, count: FRAMES}
walls:
  - builtin: box_tank
    size: [0.4, 0.3, 0.3]
fluid:
  spacing: 0.04
  emitters:
    - box: {min: [-0.2, -0.15, 0.0], max: [-0.05, 0.15, 0.16]}
    - mesh: drop.obj
effects:
  gravity: {}
stages:
  simulate: {use: sph, threads: 1, checkpoint_every: 1}
  render: {use: pyvista, show: surface, resolution: [32, 18], label: false}
outputs: OUTPUTS
"""


def tiny(tmp_path: Path, frames: int = 3, outputs: str = "[usd, movie]") -> Path:
    drop = trimesh.creation.box(extents=(0.08, 0.08, 0.08))
    drop.apply_translation((0.1, 0.0, 0.15))
    drop.export(tmp_path / "drop.obj")
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY.replace("FRAMES", str(frames)).replace("OUTPUTS", outputs))
    return path


def keys(config: Path, *sets: str) -> dict[str, str]:
    cfg = load_config(config, Registry.from_entry_points(), sets)
    return plan(cfg, build_graph(cfg), Cache(config.parent / ".pipeline")).keys


def statuses(report) -> dict[str, str]:
    return {s.kind: s.status for s in report.stages}


# -- keys on the fields a stage reads ----------------------------------------------------------------
def test_stages_are_keyed_on_the_fields_they_read(tmp_path):
    config = tiny(tmp_path)
    base = keys(config)
    longer = keys(config, "scene.frames.count=5")
    assert longer["mesh_import"] == base["mesh_import"] and longer["sdf_bake"] == base["sdf_bake"]
    assert longer["simulate"] != base["simulate"]
    faster = keys(config, "fluid.emitters.0.velocity=[1,0,0]")
    assert faster["sdf_bake"] == base["sdf_bake"] and faster["simulate"] != base["simulate"]
    assert faster["render"] != base["render"]  # downstream of the particles
    assert keys(config, "camera.view_angle=40")["simulate"] == base["simulate"]


def test_a_stage_sees_only_what_it_declares(tmp_path):
    from stages.sdf_bake.open3d_bake import Open3dBake

    sections = scene_sections({"scene": {"name": "t"}, "fluid": {"spacing": 0.1, "emitters": [{"box": {
        "min": [0, 0, 0], "max": [1, 1, 1]}}]}})
    ctx = stage_context(Open3dBake, tmp_path, scene=sections)
    assert ctx.scene["fluid"].spacing == 0.1 and ctx.scene["scene"].domain is None
    with pytest.raises(UndeclaredRead, match="fluid.density"):
        ctx.scene["fluid"].density
    with pytest.raises(UndeclaredRead, match="scene.frames"):
        ctx.scene["scene"].frames
    with pytest.raises(UndeclaredRead, match="walls"):
        ctx.scene["walls"]
    with pytest.raises(UndeclaredRead, match="frames"):
        ctx.frames


def test_a_read_that_is_not_a_config_field_is_a_contract_error():
    from pipeline.stage import Stage

    class Typo(Stage):
        kind, name, version, outputs, reads = "movie", "typo", "1", ("movie",), ("scene.frame.fps",)

        def run(self, ctx, inputs, params):
            pass

    with pytest.raises(TypeError, match="scene.frame"):
        Typo.check_contract()


# -- every file a stage reads is in its key ----------------------------------------------------------
def test_mesh_emitter_file_is_in_the_simulate_key(tmp_path):
    config = tiny(tmp_path)
    before = keys(config)
    drop = trimesh.creation.box(extents=(0.06, 0.08, 0.08))
    drop.apply_translation((0.1, 0.0, 0.15))
    drop.export(tmp_path / "drop.obj")
    after = keys(config)
    assert after["simulate"] != before["simulate"]
    assert after["sdf_bake"] == before["sdf_bake"] and after["mesh_import"] == before["mesh_import"]
    (tmp_path / "drop.obj").unlink()
    with pytest.raises(pipeline.StageFailed, match=r"fluid.emitters.1.mesh: input file not found"):
        keys(config)


def test_a_usd_emitters_sublayer_is_in_the_simulate_key(tmp_path):
    """The drop as USD whose mesh sits in a sublayer: editing the sublayer (not the file the config names)
    is a new simulate key, for every simulate implementation."""
    from pxr import Sdf, Usd, UsdGeom

    config = tiny(tmp_path)
    drop = trimesh.load(tmp_path / "drop.obj")
    inner = Usd.Stage.CreateNew(str(tmp_path / "drop_mesh.usda"))
    mesh = UsdGeom.Mesh.Define(inner, "/Drop")
    mesh.GetPointsAttr().Set([tuple(map(float, v)) for v in drop.vertices])
    mesh.GetFaceVertexCountsAttr().Set([3] * len(drop.faces))
    mesh.GetFaceVertexIndicesAttr().Set([int(i) for i in drop.faces.ravel()])
    inner.GetRootLayer().Save()
    root = Sdf.Layer.CreateNew(str(tmp_path / "drop.usda"))
    root.subLayerPaths.append("./drop_mesh.usda")
    root.Save()
    config.write_text(config.read_text().replace("- mesh: drop.obj", "- mesh: drop.usda"))
    for k, solver in enumerate(("sph", "dfsph", "mps")):
        before = keys(config, f"simulate.use={solver}")
        mesh.GetPointsAttr().Set([tuple(map(float, v + 0.01 * (k + 1))) for v in drop.vertices])
        inner.GetRootLayer().Save()
        assert keys(config, f"simulate.use={solver}")["simulate"] != before["simulate"], solver


def test_a_camera_usds_sublayer_is_in_the_render_and_export_keys(tmp_path):
    """camera.usd naming a file that only sublayers the layer holding the camera: an edit of that layer (same size,
    the camera moved) is a new render and export key (both stayed cached and showed the old camera)."""
    from pxr import Gf, Sdf, Usd, UsdGeom

    config = tiny(tmp_path)
    inner = Usd.Stage.CreateNew(str(tmp_path / "cam_sub.usda"))
    op = UsdGeom.Camera.Define(inner, "/Cam").AddTranslateOp()
    op.Set(Gf.Vec3d(0.0, -0.9, 0.15))
    inner.GetRootLayer().Save()
    root = Sdf.Layer.CreateNew(str(tmp_path / "shot.usda"))
    root.subLayerPaths.append("./cam_sub.usda")
    root.Save()
    config.write_text(config.read_text() + "camera: {usd: shot.usda}\n")
    before = keys(config)
    op.Set(Gf.Vec3d(0.2, -0.9, 0.15))
    inner.GetRootLayer().Save()
    after = keys(config)
    assert after["render"] != before["render"] and after["export"] != before["export"]
    assert after["simulate"] == before["simulate"]


def test_status_says_a_sublayer_gone_is_missing_not_changed(tmp_path):
    """A USD wall's sublayer deleted or renamed: status says the file is missing (it said "changed", sending a
    user to look for an edit); one the root layer no longer composes is "no longer read"."""
    from pxr import Sdf, Usd, UsdGeom

    sub = Usd.Stage.CreateNew(str(tmp_path / "sub.usda"))
    UsdGeom.Cube.Define(sub, "/W/box").GetSizeAttr().Set(1.0)
    sub.GetRootLayer().Save()
    root = Sdf.Layer.CreateNew(str(tmp_path / "walls.usda"))
    root.subLayerPaths.append("sub.usda")
    root.Save()
    config = tmp_path / "c.yaml"
    config.write_text("config_version: 1\nscene: {name: t, frames: {fps: 20, count: 2}}\nwalls: [{usd: walls.usda}]\n"
                      "outputs: [walls]\n")
    pipeline.run(config, progress=False)
    reg = Registry.from_entry_points()

    def reason() -> str:
        (row,) = pipeline.status(config, registry=reg)
        assert row.state == "stale"
        return row.reason

    (tmp_path / "sub.usda").rename(tmp_path / "moved.usda")
    assert reason() == "input file missing: sub.usda"
    (tmp_path / "moved.usda").rename(tmp_path / "sub.usda")
    root.subLayerPaths.clear()
    root.Save()
    assert reason() == "input file no longer read: sub.usda"


def test_another_spelling_of_the_same_input_path_keeps_the_keys(tmp_path):
    """'./drop.obj', 'sub/../drop.obj' and 'drop.obj' name one file: the same keys (each spelling re-ran every
    stage from the one that reads the file)."""
    config = tiny(tmp_path)
    (tmp_path / "sub").mkdir()
    base = keys(config)
    for spelling in ("./drop.obj", "sub/../drop.obj", ".//drop.obj"):
        other = tmp_path / "other.yaml"
        other.write_text(config.read_text().replace("mesh: drop.obj", f"mesh: {spelling}"))
        assert keys(other) == base, spelling


def test_a_moved_project_keeps_its_keys(tmp_path):
    """Input files are keyed by their path relative to the config (and their content), not where the project
    sits on disk: a project folder moved or cloned elsewhere keeps every key, so its cache is still used; a
    file with other content is still a new key."""
    a, b = tmp_path / "studio" / "shot", tmp_path / "elsewhere" / "copy_of_shot"
    for d in (a, b):
        d.mkdir(parents=True)
    ka, kb = keys(tiny(a)), keys(tiny(b))
    assert ka == kb
    drop = trimesh.creation.box(extents=(0.06, 0.08, 0.08))
    drop.apply_translation((0.1, 0.0, 0.15))
    drop.export(b / "drop.obj")
    assert keys(b / "tiny.yaml")["simulate"] != ka["simulate"]


# -- code changes invalidate without a version bump ---------------------------------------------------
STAGE_MODULE = """\
from pipeline.stage import Stage
from .helper import text


class CodeSim(Stage):
    kind, name, version = "simulate", "code", "1"
    inputs, outputs = ("sdf",), ("particles",)

    def run(self, ctx, inputs, params):
        with open(ctx.config_dir / "ran_code.log", "a") as fh:
            fh.write("x\\n")
        (ctx.out_dir / "particles.txt").write_text(text())
"""


def test_a_code_change_in_an_imported_module_invalidates(tmp_path, toy_config, monkeypatch):
    pkg = tmp_path / "codepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "sim.py").write_text(STAGE_MODULE)
    (pkg / "helper.py").write_text("def text():\n    return 'one'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    from codepkg.sim import CodeSim

    registry = Registry.from_entry_points()
    registry.add(CodeSim)
    sets = ("simulate.use=code", "outputs=[particles]")
    r1 = pipeline.run(toy_config, registry=registry, overrides=sets)
    assert statuses(r1)["simulate"] == "ran"
    assert statuses(pipeline.run(toy_config, registry=registry, overrides=sets))["simulate"] == "cached"
    (pkg / "helper.py").write_text("def text():\n    return 'two'  # changed arithmetic, no version bump\n")
    rows = {s.kind: s for s in pipeline.status(toy_config, registry=registry, overrides=sets)}
    assert rows["simulate"].state == "stale" and "code changed: codepkg.helper" in rows["simulate"].reason
    assert rows["sdf_bake"].state == "cached"
    # this process still holds the old helper: a run here would key the new source and execute the old one
    with pytest.raises(CodeChanged, match="codepkg.helper changed on disk since this process imported it"):
        pipeline.run(toy_config, registry=registry, overrides=sets)
    assert len((toy_config.parent / "ran_code.log").read_text().split()) == 1
    import importlib

    import codepkg.helper
    importlib.reload(codepkg.helper)  # what a new process would load
    monkeypatch.setattr(codepkg.sim, "text", codepkg.helper.text)
    monkeypatch.setattr(keys_module, "_FIRST_SEEN", {})
    r3 = pipeline.run(toy_config, registry=registry, overrides=sets)
    assert statuses(r3)["simulate"] == "ran" and statuses(r3)["sdf_bake"] == "cached"
    assert len((toy_config.parent / "ran_code.log").read_text().split()) == 2
    particles = next((toy_config.parent / "out").rglob("particles.txt"), None)
    assert particles is None or particles.read_text() == "two"


def test_code_outside_the_stage_package_is_keyed(tmp_path, toy_config, monkeypatch):
    """A studio library beside the plugin (not installed in site-packages), a sibling top-level module and
    a module loaded by import_module("...") are hashed; installed packages count by their version."""
    (tmp_path / "studiolib").mkdir()
    (tmp_path / "studiolib" / "__init__.py").write_text("")
    (tmp_path / "studiolib" / "colors.py").write_text("RED = 1\n")
    (tmp_path / "solohelp.py").write_text("def f():\n    return 1\n")
    (tmp_path / "dynhelp.py").write_text("X = 1\n")
    (tmp_path / "solo.py").write_text(
        "import importlib\nimport numpy\nfrom pipeline.stage import Stage\nfrom studiolib.colors import RED\n"
        "import solohelp\n\n\nclass Solo(Stage):\n    kind, name, version = 'simulate', 'solo', '1'\n"
        "    inputs, outputs = ('sdf',), ('particles',)\n\n    def run(self, ctx, inputs, params):\n"
        "        importlib.import_module('dynhelp')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    from solo import Solo

    code = keys_module.code_hashes(Solo)
    assert {"studiolib.colors", "solohelp", "dynhelp", "solo"} <= set(code)
    assert code["numpy"] == f"version {np.__version__}"
    assert not any(name.startswith("numpy.") for name in code)  # installed: its version, not its sources


def test_a_stage_without_a_source_file_is_never_served_from_cache():
    """A class made in a notebook cell or by python -c has no file to hash: every plan keys it anew."""
    namespace: dict = {"__name__": "__main__"}
    exec("from pipeline.stage import Stage\n"
         "class Cell(Stage):\n    kind, name, version = 'simulate', 'cell', '1'\n"
         "    inputs, outputs = ('sdf',), ('particles',)\n    def run(self, ctx, inputs, params): pass\n", namespace)
    cell = namespace["Cell"]
    cell.__module__ = "__notebook_cell__"
    first, second = keys_module.code_hashes(cell), keys_module.code_hashes(cell)
    assert first["__notebook_cell__"].startswith("unhashable") and first != second


# -- a partial frame run does not poison whole-run stages -----------------------------------------------
def test_partial_frames_then_full_run_covers_every_frame(tmp_path):
    import imageio.v3 as iio
    from pxr import Usd

    config = tiny(tmp_path, frames=3)
    r1 = pipeline.run(config, frames=(0, 1))
    assert statuses(r1)["movie"] == "ran"
    r2 = pipeline.run(config)
    st = statuses(r2)
    assert st["simulate"] == "cached" and st["movie"] == "ran" and st["export"] == "ran"
    assert r2.stage("render").frames_ran == 1  # only the new frame
    out = Path(r2.out)
    assert len(list(iio.imiter(out / "movie" / "movie.mp4"))) == 3
    stage = Usd.Stage.Open(str(out / "usd" / "fluid_surface.usdc"))
    points = stage.GetPrimAtPath("/World/Fluid/Surface").GetAttribute("points")
    assert points.GetTimeSamples() == [0.0, 1.0, 2.0]


# -- a longer shot continues from the cached shorter one --------------------------------------------
def test_extending_a_shot_resumes_and_equals_a_fresh_run(tmp_path, caplog):
    config = tiny(tmp_path, frames=3, outputs="[particles]")
    pipeline.run(config)
    row = next(r for r in pipeline.status(config, overrides=("scene.frames.count=5",)) if r.kind == "simulate")
    assert "scene.frames.count 3 -> 5" in row.reason and "continues the cached shorter run" in row.reason
    with caplog.at_level(logging.INFO, logger="stage.simulate.sph"):
        longer = pipeline.run(config, overrides=("scene.frames.count=5",))
    assert statuses(longer)["simulate"] == "ran" and statuses(longer)["sdf_bake"] == "cached"
    assert "resumed from the checkpoint at frame 2" in caplog.text
    fresh = pipeline.run(config, overrides=("scene.frames.count=5",), cache_dir=tmp_path / "fresh",
                         out_dir=tmp_path / "fresh_out")
    assert statuses(fresh)["simulate"] == "ran"
    a, b = Path(longer.outputs["particles"]), Path(fresh.outputs["particles"])
    for f in range(5):
        assert frame_path(a, f).read_bytes() == frame_path(b, f).read_bytes(), f"frame {f} differs"


def test_an_extension_stopped_midway_resumes_from_its_own_checkpoints(tmp_path, caplog, monkeypatch):
    """A 60-frame extension of a 30-frame shot killed at frame 48 went back to frame 29 on the next run: its
    checkpoints (frames 30 and 40) were passed over, since its checkpoint folder holds only the frames after the
    shorter run's. Here 3 -> 7 frames, stopped writing frame 5."""
    import stages.simulate.driver as driver

    config = tiny(tmp_path, frames=3, outputs="[particles]")
    sets = ("scene.frames.count=7", "simulate.checkpoint_every=1")
    pipeline.run(config, overrides=sets[1:])
    real = driver.write_frame

    def stops_at_5(out_dir, frame, *a, **k):
        if frame == 5:
            raise RuntimeError("killed")
        return real(out_dir, frame, *a, **k)

    monkeypatch.setattr(driver, "write_frame", stops_at_5)
    with pytest.raises(pipeline.StageFailed):
        pipeline.run(config, overrides=sets)
    monkeypatch.setattr(driver, "write_frame", real)
    with caplog.at_level(logging.INFO, logger="stage.simulate.sph"):
        longer = pipeline.run(config, overrides=sets)
    assert "resumed from the checkpoint at frame 4" in caplog.text, caplog.text
    fresh = pipeline.run(config, overrides=sets, cache_dir=tmp_path / "fresh", out_dir=tmp_path / "fresh_out")
    a, b = Path(longer.outputs["particles"]), Path(fresh.outputs["particles"])
    for f in range(7):
        assert frame_path(a, f).read_bytes() == frame_path(b, f).read_bytes(), f"frame {f} differs"


def test_an_unreadable_input_file_is_one_line_exit_2_and_nothing_written(tmp_path, monkeypatch):
    """Issue 15: permission denied while hashing an input file (as root chmod does not deny, so the
    read fails by injection): exit 2, one line naming the file, no cache or output folder."""
    from click.testing import CliRunner

    from pipeline import cache as cache_module
    from pipeline.cli import main

    config = tiny(tmp_path)
    real = cache_module.file_sha256

    def denied(path, *a, **k):
        if Path(path).name == "drop.obj":
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr("pipeline.keys.file_sha256", denied)
    r = CliRunner().invoke(main, ["run", str(config)])
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in r.output, err
    assert "cannot read input file" in err and "drop.obj" in err and "Permission denied" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drop.obj", "tiny.yaml"]


def test_numba_cache_folder_follows_every_stage_source(tmp_path):
    """numba's cache checks only the defining module's source, not its callees' (an update of
    walls/maps.py alone left sph_kernels' integrate running the old push-out): stages/__init__ puts the
    cache in a folder named by all of the package's source, so any edit anywhere gets a fresh one."""
    import numba

    import stages
    from stages import numba_cache_dir

    root = Path(stages.__file__).resolve().parent
    assert Path(numba.config.CACHE_DIR).name == Path(numba_cache_dir(root, "base")).name
    tree = tmp_path / "pkg"
    (tree / "walls").mkdir(parents=True)
    (tree / "kernels.py").write_text("from .walls.maps import push\n")
    (tree / "walls" / "maps.py").write_text("def push(x):\n    return x + 1\n")
    first = numba_cache_dir(tree, "base")
    assert numba_cache_dir(tree, "base") == first  # stable
    (tree / "walls" / "maps.py").write_text("def push(x):\n    return x + 2\n")  # a callee's module only
    second = numba_cache_dir(tree, "base")
    assert second != first
    (tree / "walls" / "maps.py").rename(tree / "walls" / "other.py")  # same bytes, another module
    assert numba_cache_dir(tree, "base") not in (first, second)


@pytest.mark.parametrize("how", ["below_a_file", "read_only_home"])
def test_a_numba_cache_folder_that_cannot_be_written_is_not_replaced_by_the_source_tree(how, tmp_path):
    """NUMBA_CACHE_DIR below a file, or no NUMBA_CACHE_DIR and a home that cannot be written (a farm's service
    user): the first sent numba's cache files into stages/*/__pycache__ beside the sources (46 of them, which a
    later run loaded whatever its callees' sources), the second stopped the run at a stage's import, said as its
    config line. The versioned folder now goes under the temporary folder, said in one line."""
    import subprocess
    import sys

    (tmp_path / "afile").write_text("")
    (tmp_path / "tmp").mkdir()
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "kern.py").write_text("import numba\n\n@numba.njit(cache=True)\ndef f(x):\n    return x + 1\n")
    env = dict(os.environ, TMPDIR=str(tmp_path / "tmp"), PYTHONPATH=str(Path(pipeline.__file__).parents[1]))
    env.pop("XDG_CACHE_HOME", None)
    if how == "below_a_file":
        env["NUMBA_CACHE_DIR"] = str(tmp_path / "afile" / "numba")
    else:
        env.pop("NUMBA_CACHE_DIR", None)
        env["HOME"] = str(tmp_path / "afile")  # ~/.cache cannot be made below a file
    code = ("import logging, sys; logging.basicConfig(); import stages, numba; sys.path.insert(0, %r); import kern; "
            "assert kern.f(1) == 2; print(numba.config.CACHE_DIR)" % str(tmp_path / "m"))
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    cache = Path(r.stdout.strip())
    assert cache.is_relative_to(tmp_path / "tmp"), cache
    assert list(cache.rglob("kern.f-*.nbi")), sorted(cache.rglob("*"))  # the kernel is cached there
    assert not list((tmp_path / "m").rglob("*.nbi"))  # and not beside its source
    assert "cannot be written: numba's compiled kernels are cached in" in r.stderr, r.stderr


def test_a_missing_input_file_names_the_config_line(toy_config):
    """It named the stage and the field but not the config's file and line, as every other config error does."""
    from pipeline import StageFailed

    text = toy_config.read_text().replace("mesh_import: {use: toy}", "mesh_import: {use: toy, source: gone.txt}")
    toy_config.write_text(text.replace("fluid:\n", "walls:\n  - builtin: box_tank\n  - file: assets/dragon.obj\nfluid:\n"))
    lines = toy_config.read_text().splitlines()
    wall_line = lines.index("  - file: assets/dragon.obj") + 1
    with pytest.raises(StageFailed) as e:
        pipeline.run(toy_config, registry=Registry.from_entry_points())
    assert str(e.value).startswith(f"{toy_config}:{wall_line}: stage mesh_import.toy: walls.1.file: input file not found"), e.value
    assert e.value.exit_code == 2
    toy_config.write_text(text)  # the stage's own external file: the stage's line
    stage_line = next(i for i, line in enumerate(text.splitlines(), 1) if "source: gone.txt" in line)
    with pytest.raises(StageFailed, match=rf"^{toy_config}:{stage_line}: stage mesh_import.toy: external file: input "
                                          rf"file not found: .*gone.txt$"):
        pipeline.run(toy_config, registry=Registry.from_entry_points())
    assert not (toy_config.parent / ".pipeline").exists()


def test_a_file_replaced_by_a_same_size_same_mtime_copy_is_hashed_again(toy_config, monkeypatch):
    """The process-wide hash memo was keyed on (path, size, mtime): a wall replaced in place by another of the
    same size and mtime (cp -p, shutil.copy2, rsync -a) kept its old hash in a notebook calling pipeline.run
    twice, and the second run was served the first wall's results. ctime and the inode are in the memo's key now."""
    import os
    import shutil
    import time

    folder = toy_config.parent
    toy_config.write_text(toy_config.read_text().replace("fluid:\n", "walls:\n  - file: wall.obj\nfluid:\n"))
    a, b = folder / "a.obj", folder / "b.obj"
    a.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    b.write_text("v 0 0 0\nv 2 0 0\nv 0 2 0\nf 1 2 3\n")  # same size, other content
    for f in (a, b):
        os.utime(f, ns=(1_700_000_000_000_000_000,) * 2)
    for every_hash_memoised in (False, True):  # as it is; then recent files too, so the memo's key alone decides
        if every_hash_memoised:
            monkeypatch.setattr(keys_module, "_RACY_NS", 0, raising=False)
        keys_module._FILE_HASHES.clear()
        shutil.copy2(a, folder / "wall.obj")
        first = keys(toy_config)["mesh_import"]
        time.sleep(0.05)  # past the filesystem clock's tick, so the copy's ctime moves
        shutil.copy2(b, folder / "wall.obj")
        st = (folder / "wall.obj").stat()
        assert (st.st_size, st.st_mtime_ns) == (a.stat().st_size, a.stat().st_mtime_ns)
        assert keys(toy_config)["mesh_import"] != first
        shutil.copy2(a, folder / "wall.obj")
        assert keys(toy_config)["mesh_import"] == first


@pytest.mark.parametrize("case", ["symlink loop", "name too long"])
@pytest.mark.parametrize("command", ["run", "status", "clean"])
def test_an_input_path_the_os_refuses_names_the_config_line(case, command, toy_config):
    """A symlink loop (resolve() raised RuntimeError) or a 300-character file name (OSError from stat): exit 1
    with a traceback or a bare OSError in run, status and clean; now exit 2, one line naming the config line and
    field, as a missing file is, and nothing written."""
    from click.testing import CliRunner

    from pipeline.cli import main

    folder = toy_config.parent
    if case == "symlink loop":
        (folder / "a").mkdir()
        (folder / "a" / "loop2.obj").symlink_to("loop1")
        (folder / "a" / "loop1").symlink_to("loop2.obj")
        name, cause = "a/loop2.obj", "Too many levels of symbolic links"
    else:
        name, cause = "x" * 300 + ".obj", "File name too long"
    toy_config.write_text(toy_config.read_text().replace("fluid:\n", f"walls:\n  - builtin: box_tank\n  - file: {name}\nfluid:\n"))
    line = toy_config.read_text().splitlines().index(f"  - file: {name}") + 1
    before = sorted(p.name for p in folder.iterdir())
    r = CliRunner().invoke(main, [command, str(toy_config)])
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in r.output, err
    assert err.startswith(f"error: {toy_config}:{line}: stage mesh_import.toy: walls.1.file: cannot read input file"), err
    assert err.endswith(cause), err
    assert sorted(p.name for p in folder.iterdir()) == before
