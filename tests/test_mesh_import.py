"""mesh_import: built-in walls, mesh files, USD (units, up axis, nested transforms), clean-up, bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from pipeline.stage import StageError
from pipeline.testing import run_stage
from stages.common.formats import WallMesh
from stages.mesh_import.trimesh_import import TrimeshImport
from stages.mesh_import.usd_import import UsdImport

SCENE = {"name": "t"}


def _import(tmp_path, walls, stage=TrimeshImport, scene=None, **params):
    out = run_stage(stage, tmp_path / "out", scene={"scene": scene or SCENE, "walls": walls}, params=params,
                    config_dir=tmp_path)
    return WallMesh.load(out)


def _signed_volume(v, f):
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def test_box_tank_is_closed_faces_inward_and_sits_on_its_floor(tmp_path):
    wm = _import(tmp_path, [{"builtin": "box_tank", "size": [2, 1, 0.5], "center": [1, 0, 0.25]}])
    assert np.allclose(wm.vertices.min(axis=0), [0, -0.5, 0.25])
    assert np.allclose(wm.vertices.max(axis=0), [2, 0.5, 0.75])
    # normals into the fluid = inwards for a container: negative signed volume
    assert _signed_volume(wm.vertices, wm.faces) == pytest.approx(-1.0)
    assert wm.walls[0]["fluid"] == "inside" and wm.walls[0]["report"]["watertight"]


def test_open_box_is_a_thick_solid_with_fluid_outside(tmp_path):
    wm = _import(tmp_path, [{"builtin": "open_box", "size": [1, 1, 1]}], open_box_thickness=0.1)
    assert wm.walls[0]["fluid"] == "outside" and wm.walls[0]["report"]["watertight"]
    # outer cube minus the cavity 0.8 x 0.8 x 0.9
    assert _signed_volume(wm.vertices, wm.faces) == pytest.approx(1 - 0.8 * 0.8 * 0.9)


def test_placement_scale_rotate_translate_and_fit(tmp_path):
    box = trimesh.creation.box(bounds=[[0, 0, 0], [1, 2, 3]])
    box.export(tmp_path / "b.obj")
    wm = _import(tmp_path, [{"file": "b.obj", "scale": 2, "rotate": [0, 0, 90], "translate": [10, 0, 0]}])
    assert np.allclose(wm.vertices.min(axis=0), [6, 0, 0]) and np.allclose(wm.vertices.max(axis=0), [10, 2, 6])
    wm = _import(tmp_path, [{"file": "b.obj", "fit": {"min": [0, 0, 0], "max": [1, 1, 1]}}])
    assert np.allclose(wm.vertices.min(axis=0), [1 / 3, 1 / 6, 0]) and np.allclose(wm.vertices.max(axis=0), [2 / 3, 5 / 6, 1])


def test_file_units_are_converted(tmp_path):
    trimesh.creation.box(bounds=[[0, 0, 0], [100, 100, 100]]).export(tmp_path / "cm.stl")
    wm = _import(tmp_path, [{"file": "cm.stl", "meters_per_unit": 0.01}])
    assert np.allclose(wm.vertices.max(axis=0), [1, 1, 1])


def test_gltf_is_metres_and_y_up_and_other_files_may_say_their_up_axis(tmp_path):
    """glTF is specified in metres with +Y up: a GLB tank (0.3 x 0.2 x 0.4 m, 0.4 m along its +Y) comes into a
    Z-up centimetre scene standing, 40 cm tall (it lay on its side, in the scene's units); an OBJ exported Y-up
    says so with up_axis: Y and comes in the same; in a Y-up scene neither turns."""
    box = trimesh.creation.box(bounds=[[0, 0, -0.2], [0.3, 0.4, 0.0]])  # Y-up: the tank's height along +Y
    box.export(tmp_path / "tank.glb")
    box.export(tmp_path / "tank_yup.obj")
    up_z = {"name": "t", "units": {"meters_per_unit": 0.01, "up_axis": "Z"}}
    for wall in ({"file": "tank.glb"}, {"file": "tank_yup.obj", "up_axis": "Y", "meters_per_unit": 1.0}):
        wm = _import(tmp_path, [wall], scene=up_z)
        np.testing.assert_allclose(wm.vertices.min(axis=0), [0, 0, 0], atol=1e-5)
        np.testing.assert_allclose(wm.vertices.max(axis=0), [30, 20, 40], atol=1e-5)
    up_y = {"name": "t", "units": {"meters_per_unit": 1.0, "up_axis": "Y"}}
    wm = _import(tmp_path, [{"file": "tank.glb"}], scene=up_y)
    np.testing.assert_allclose(wm.vertices.max(axis=0), [0.3, 0.4, 0.0], atol=1e-6)
    np.testing.assert_allclose(wm.vertices.min(axis=0), [0.0, 0.0, -0.2], atol=1e-6)


def test_a_gltf_emitter_is_metres_and_y_up_as_a_gltf_wall(tmp_path):
    """The same conversion for a fluid emitter: a GLB block 0.1 x 0.1 x 0.2 m tall along its +Y fills a Z-up
    centimetre scene 20 cm high, as the box emitter of those bounds does."""
    from pipeline.scene import BoxEmitter, MeshEmitter
    from stages.simulate.emitters import emit

    trimesh.creation.box(bounds=[[0, 0, -0.1], [0.1, 0.2, 0.0]]).export(tmp_path / "block.glb")
    x, _ = emit([MeshEmitter(mesh="block.glb")], 1.0, lambda p: tmp_path / p, 0.01, None, "Z")
    box, _ = emit([BoxEmitter(box={"min": [0, 0, 0], "max": [10, 10, 20]})], 1.0, lambda p: tmp_path / p, 0.01,
                  None, "Z")
    assert len(x) == len(box) and x[:, 2].max() == pytest.approx(box[:, 2].max(), abs=1e-6)


def test_cleanup_welds_and_drops_degenerate_and_duplicate_faces(tmp_path):
    (tmp_path / "bad.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 1 0 0\n"
        "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 5 3 4\n"  # tetrahedron; vertex 5 duplicates vertex 2
        "f 1 3 2\n"  # duplicate face
        "f 1 2 5\n"  # zero area once welded
    )
    wm = _import(tmp_path, [{"file": "bad.obj"}])
    r = wm.walls[0]["report"]
    assert r["welded_vertices"] == 1 and r["degenerate_faces_removed"] == 1 and r["duplicate_faces_removed"] == 1
    assert r["faces"] == 4 and r["watertight"] and r["boundary_edges"] == 0
    assert _signed_volume(wm.vertices, wm.faces) == pytest.approx(1 / 6)  # obstacle: outward


def test_holes_and_inconsistent_winding_are_reported_and_fixed(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    faces = sphere.faces.copy()
    faces[::7] = faces[::7, ::-1]  # flip some faces
    faces = faces[3:]  # and cut holes
    trimesh.Trimesh(sphere.vertices, faces, process=False).export(tmp_path / "holey.ply")
    wm = _import(tmp_path, [{"file": "holey.ply"}])
    r = wm.walls[0]["report"]
    assert not r["winding_consistent_in"] and r["winding_consistent"]
    assert r["boundary_edges"] > 0 and not r["watertight"]


def _usd_and_obj(tmp_path):
    """The same geometry as a Y-up centimetre USD with nested transforms and as a Z-up metre OBJ."""
    from pxr import Gf, Usd, UsdGeom

    pts = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0], [0, 0, 3], [2, 0, 3], [2, 1, 3], [0, 1, 3]], float)
    counts = [4, 4, 4, 4, 4, 4]
    idx = [0, 3, 2, 1, 4, 5, 6, 7, 0, 1, 5, 4, 1, 2, 6, 5, 2, 3, 7, 6, 3, 0, 4, 7]
    stage = Usd.Stage.CreateNew(str(tmp_path / "asset.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    outer = UsdGeom.Xform.Define(stage, "/World")
    outer.AddTranslateOp().Set(Gf.Vec3d(100, 50, -20))
    outer.AddRotateYOp().Set(30.0)
    inner = UsdGeom.Xform.Define(stage, "/World/Group")
    inner.AddScaleOp().Set(Gf.Vec3f(10, 10, 10))
    inner.AddRotateXOp().Set(-15.0)
    mesh = UsdGeom.Mesh.Define(stage, "/World/Group/Block")
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in pts])
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(idx)
    hidden = UsdGeom.Mesh.Define(stage, "/World/Hidden")
    hidden.CreatePointsAttr([Gf.Vec3f(500, 0, 0), Gf.Vec3f(600, 0, 0), Gf.Vec3f(500, 100, 0)])
    hidden.CreateFaceVertexCountsAttr([3])
    hidden.CreateFaceVertexIndicesAttr([0, 1, 2])
    hidden.MakeInvisible()
    stage.GetRootLayer().Save()
    # the same transform by hand: row vectors, p * M_inner * M_outer, then cm -> m and Y-up -> Z-up
    world = np.asarray(UsdGeom.XformCache().GetLocalToWorldTransform(mesh.GetPrim()))
    w = np.c_[pts, np.ones(8)] @ world
    w = w[:, :3] * 0.01
    z_up = np.c_[w[:, 0], -w[:, 2], w[:, 1]]
    tris = []
    for f in range(6):
        q = idx[4 * f:4 * f + 4]
        tris += [(q[0], q[1], q[2]), (q[0], q[2], q[3])]
    trimesh.Trimesh(z_up, np.array(tris), process=False).export(tmp_path / "asset.obj")
    return z_up


@pytest.mark.parametrize("stage", [TrimeshImport, UsdImport])
def test_usd_yup_centimetres_nested_transforms_match_the_obj_in_metres_zup(tmp_path, stage):
    expected = _usd_and_obj(tmp_path)
    usd = _import(tmp_path, [{"usd": "asset.usda", "prims": ["/World/Group"]}], stage=stage)
    obj = _import(tmp_path, [{"file": "asset.obj"}])
    assert usd.walls[0]["report"]["prims"] == ["/World/Group/Block"]
    assert np.allclose(np.sort(usd.vertices, axis=0), np.sort(expected, axis=0), atol=1e-9)
    assert np.allclose(np.sort(usd.vertices, axis=0), np.sort(obj.vertices, axis=0), atol=1e-9)
    assert len(usd.faces) == 12 and usd.walls[0]["report"]["watertight"]
    vol = _signed_volume(usd.vertices, usd.faces)
    assert vol == pytest.approx(6 * 0.1 ** 3) and vol == pytest.approx(_signed_volume(obj.vertices, obj.faces))


def test_usd_invisible_prims_skipped_unless_asked_and_holes_dropped(tmp_path):
    from pxr import Usd, UsdGeom

    _usd_and_obj(tmp_path)
    wm = _import(tmp_path, [{"usd": "asset.usda"}])
    assert wm.walls[0]["report"]["prims"] == ["/World/Group/Block"]
    wm = _import(tmp_path, [{"usd": "asset.usda", "include_invisible": True}])
    assert wm.walls[0]["report"]["prims"] == ["/World/Group/Block", "/World/Hidden"]
    stage = Usd.Stage.Open(str(tmp_path / "asset.usda"))
    UsdGeom.Mesh(stage.GetPrimAtPath("/World/Group/Block")).CreateHoleIndicesAttr([1])  # the top face is a hole
    stage.GetRootLayer().Save()
    wm = _import(tmp_path, [{"usd": "asset.usda", "prims": ["/World/*/Block"]}])
    assert len(wm.faces) == 10 and wm.walls[0]["report"]["boundary_edges"] == 4


def test_outputs_walls_usdc_with_stage_metrics(tmp_path):
    from pxr import Usd, UsdGeom

    run_stage(TrimeshImport, tmp_path, scene={"scene": {"name": "t", "units": {"meters_per_unit": 0.01, "up_axis": "Y"}},
                                              "walls": [{"builtin": "cylinder", "size": [1, 1, 2]}]})
    stage = Usd.Stage.Open(str(tmp_path / "walls.usdc"))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Walls/wall0_cylinder"))
    pts = np.asarray(mesh.GetPointsAttr().Get())
    assert pts[:, 1].min() == pytest.approx(0) and pts[:, 1].max() == pytest.approx(2)
    assert json.loads((tmp_path / "walls.json").read_text())[0]["fluid"] == "inside"


def test_external_files_list_usd_sublayers(tmp_path):
    from pxr import Sdf

    _usd_and_obj(tmp_path)
    root = Sdf.Layer.CreateNew(str(tmp_path / "root.usda"))
    root.subLayerPaths.append("asset.usda")
    root.Save()
    from pipeline import Registry
    from pipeline.cache import Cache
    from pipeline.config import load_config
    from pipeline.graph import build_graph
    from pipeline.keys import plan
    from pathlib import Path

    # the key of mesh_import hashes the wall files the config names and the layers a USD wall composes
    (tmp_path / "c.yaml").write_text("config_version: 1\nscene: {name: t}\nwalls: [{usd: root.usda}, {file: asset.obj}]\n"
                                     "outputs: [walls]\n")
    cfg = load_config(tmp_path / "c.yaml", Registry.from_entry_points())
    p = plan(cfg, build_graph(cfg), Cache(tmp_path / "cache"))
    files = {Path(f).name for f in p.components["mesh_import"]["files"]}
    assert files == {"root.usda", "asset.usda", "asset.obj"}


def test_a_gltf_walls_external_buffer_is_in_the_key(tmp_path):
    """A .gltf keeps its vertices in a separate .bin: an edit of the .bin (same size, the wall moved 2 cm) is a
    new mesh_import key, and so is the same edit for a .gltf fluid emitter's simulate key (both stayed cached
    with the old geometry)."""
    import trimesh

    from pipeline import Registry
    from pipeline.cache import Cache
    from pipeline.config import load_config
    from pipeline.graph import build_graph
    from pipeline.keys import plan

    box = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    box.apply_translation((0.075, 0.0, 0.0))
    files = box.export(file_type="gltf")  # {"model.gltf": json, "gltf_buffer_k.bin": bytes}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    gltf = next(n for n in files if n.endswith(".gltf"))
    buffer = "gltf_buffer_1.bin"  # the positions (buffer 0 holds the indices)
    (tmp_path / "c.yaml").write_text(f"config_version: 1\nscene: {{name: t}}\nwalls: [{{builtin: box_tank, size: [1, 1, 1]}},"
                                     f" {{file: {gltf}}}]\nfluid: {{spacing: 0.01, emitters: [{{mesh: {gltf}}}]}}\n"
                                     "outputs: [particles]\n")

    def keys():
        cfg = load_config(tmp_path / "c.yaml", Registry.from_entry_points())
        return plan(cfg, build_graph(cfg), Cache(tmp_path / "cache")).keys

    before = keys()
    moved = box.copy()
    moved.apply_translation((0.02, 0.0, 0.0))
    again = moved.export(file_type="gltf")
    assert len(again[buffer]) == len(files[buffer])
    (tmp_path / buffer).write_bytes(again[buffer])
    assert (tmp_path / gltf).read_bytes() != again[gltf]  # (the .gltf's min/max would change: keep the old one)
    after = keys()
    assert after["mesh_import"] != before["mesh_import"] and after["simulate"] != before["simulate"]


def _write(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    return name


@pytest.mark.parametrize("wall, message", [
    ({"file": "missing.obj"}, "file not found"),
    ({"file": "empty.obj"}, "no triangles read from its 10 bytes as OBJ"),
    ({"file": "zero.stl"}, "the file is empty"),
    ({"file": "obj_named.stl"}, "not a valid STL file"),  # an OBJ under the wrong extension
    ({"file": "nan.obj"}, "NaN or Inf"),
    ({"file": "range.obj"}, "out of range"),
    ({"file": "range.off"}, "out of range"),
    ({"usd": "asset.usda", "prims": ["/World/Nope"]}, "prim path /World/Nope not found"),
    ({"usd": "missing.usda"}, "not found"),
    ({"usd": "asset.usda", "prims": ["/Other*"]}, "no visible UsdGeom.Mesh"),
])
def test_bad_input_raises_stage_error_naming_the_file(tmp_path, wall, message):
    _usd_and_obj(tmp_path)
    _write(tmp_path, "model.xyz", "1 2 3\n")
    _write(tmp_path, "empty.obj", "# nothing\n")
    _write(tmp_path, "zero.stl", "")
    _write(tmp_path, "obj_named.stl", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    _write(tmp_path, "nan.obj", "v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    _write(tmp_path, "range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    _write(tmp_path, "range.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    with pytest.raises(StageError, match=message) as err:
        _import(tmp_path, [wall])
    name = wall.get("file") or wall.get("usd")
    assert name in str(err.value) and "\n" not in str(err.value)


def test_damaged_usd_is_a_stage_error(tmp_path):
    _write(tmp_path, "broken.usda", "#usda 1.0\ndef Mesh \"A\" {\n  point3f[] points = [(0, 0\n")
    with pytest.raises(StageError, match="broken.usda"):
        _import(tmp_path, [{"usd": "broken.usda"}])


@pytest.mark.parametrize("up", ["Y", "Z"])
@pytest.mark.parametrize("placement", [{}, {"scale": [2, 0.5, 3], "translate": [1, -2, 3]}, {"rotate": [0, 0, 90]},
                                       {"rotate": [90, 0, 0], "fit": {"min": [0, 0, 0], "max": [1, 2, 3]}}])
def test_builtin_corners_bound_the_imported_builtin_walls(tmp_path, up, placement):
    """The size estimate's builtin wall bounds (no mesh built) are the imported meshes' bounds."""
    from stages.mesh_import.builtin import builtin_corners
    from pipeline.testing import scene_sections

    walls = [{"builtin": kind, "size": [0.6, 0.8, 1.4], "center": [0.1, 0.2, 0.3], **placement}
             for kind in ("box_tank", "open_box", "cylinder", "plane")]
    wm = _import(tmp_path, walls, scene={"name": "t", "units": {"up_axis": up}})
    parsed = scene_sections({"scene": {"name": "t"}, "walls": walls + [{"file": "x.obj"}]})["walls"]
    for i, w in enumerate(parsed[:-1]):
        got = builtin_corners([w], up)
        v = wm.vertices[np.unique(wm.faces[wm.wall_id == i])]
        assert np.allclose(got.min(axis=0), v.min(axis=0)) and np.allclose(got.max(axis=0), v.max(axis=0)), w.builtin
    assert builtin_corners(parsed, up) is None  # a file's bounds need the file


def _cube_mesh(stage, path, centre, size=0.1, purpose=None, sampled_only=False):
    import trimesh
    from pxr import Usd, UsdGeom

    box = trimesh.creation.box(extents=(size, size, size))
    box.apply_translation(centre)
    mesh = UsdGeom.Mesh.Define(stage, path)
    points = [tuple(map(float, v)) for v in box.vertices]
    if sampled_only:  # a cached/deforming mesh: points at time codes only, no default
        mesh.GetPointsAttr().Set(points, Usd.TimeCode(1))
        mesh.GetPointsAttr().Set([(x, y, z + 0.5) for x, y, z in points], Usd.TimeCode(2))
    else:
        mesh.GetPointsAttr().Set(points)
    mesh.GetFaceVertexCountsAttr().Set([3] * len(box.faces))
    mesh.GetFaceVertexIndicesAttr().Set([int(i) for i in box.faces.ravel()])
    if purpose:
        mesh.CreatePurposeAttr(purpose)
    return mesh


def test_usd_walls_take_sampled_points_and_leave_out_guides_and_doubled_proxies(tmp_path, caplog):
    """A studio set: a static rock, a rock whose points exist only as time samples (a cache: read at its first
    sample; it was dropped without a word), a guide plate (a rig helper: renderers never draw it; it became a
    wall that held the fluid up), and one object as render and proxy meshes (the proxy left out, not the same
    object twice). What is left out is said, and a selection of nothing but a guide names why."""
    import logging

    from types import SimpleNamespace

    from pxr import Usd, UsdGeom

    from stages.mesh_import.usd_import import read_usd_wall

    stage = Usd.Stage.CreateNew(str(tmp_path / "set.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    _cube_mesh(stage, "/World/RockStatic", (0.0, 0.0, 0.05))
    _cube_mesh(stage, "/World/RockCached", (0.3, 0.0, 0.05), sampled_only=True)
    _cube_mesh(stage, "/World/Helpers/GuidePlate", (0.0, 0.3, 0.1), size=0.2, purpose="guide")
    _cube_mesh(stage, "/World/Statue/Render", (0.6, 0.0, 0.05), purpose="render")
    _cube_mesh(stage, "/World/Statue/Proxy", (0.6, 0.0, 0.05), size=0.12, purpose="proxy")
    stage.GetRootLayer().Save()
    wall = SimpleNamespace(prims=["/**"], include_invisible=False)
    with caplog.at_level(logging.INFO):
        v, f, used, _, _, _ = read_usd_wall(tmp_path / "set.usda", wall, 1.0, "Z", logging.getLogger("t"))
    assert used == ["/World/RockStatic", "/World/RockCached", "/World/Statue/Render"]
    cached = v[f[12:24].ravel()]  # the second cube's triangles: at its first sample, not 0.5 higher
    np.testing.assert_allclose(cached.min(axis=0), [0.25, -0.05, 0.0], atol=1e-7)
    assert "GuidePlate (purpose guide)" in caplog.text and "Proxy (purpose proxy beside render meshes)" in caplog.text
    assert "animated points" in caplog.text
    with pytest.raises(StageError, match=r"left out: /World/Helpers/GuidePlate \(purpose guide\)"):
        read_usd_wall(tmp_path / "set.usda", SimpleNamespace(prims=["/World/Helpers"], include_invisible=False), 1.0, "Z")


def test_a_copied_project_publishes_its_own_relative_sources(tmp_path):
    """walls.json and the exported walls' customData named the resolved, absolute path of each file: a copied or
    moved project reused the cache entry (same key) and published the first project's paths (a file that may be
    gone). The source is now the file as the config names it, so both projects' walls.json are byte-identical."""
    import shutil

    made = []
    for name in ("proj", "proj2"):
        root = tmp_path / name
        (root / "assets").mkdir(parents=True)
        trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(root / "assets" / "obstacle.obj")
        scene = {"scene": {"name": "t"}, "walls": [{"builtin": "box_tank", "size": [1, 1, 1]},
                                                   {"file": "assets/obstacle.obj"}]}
        out = run_stage(TrimeshImport, root / "walls", scene=scene, config_dir=root)
        made.append((out / "walls.json").read_bytes())
        info = json.loads(made[-1])
        assert [w["source"] for w in (info if isinstance(info, list) else info["walls"])] == [
            "builtin:box_tank", "assets/obstacle.obj"]
    assert made[0] == made[1]
    shutil.rmtree(tmp_path / "proj")


_CUBE_QUADS = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _gltf(path, prims, glb=False, extra=None):
    """A glTF of the 0.2 m cube (glTF's Y up) whose primitives are ``(mode, indices)`` over its 8 corners;
    written as .gltf with the buffer inline, or as a .glb."""
    import base64
    import struct

    pts = np.array([(x, y, z) for y in (0, 0.2) for x, z in ((0, 0), (0.2, 0), (0.2, 0.2), (0, 0.2))], "<f4")
    blob, views, accessors, primitives = pts.tobytes(), [{"buffer": 0, "byteOffset": 0, "byteLength": 96}], \
        [{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
          "min": pts.min(axis=0).tolist(), "max": pts.max(axis=0).tolist()}], []
    for mode, idx in prims:
        data = np.asarray(idx, "<u2").tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5123, "count": len(idx), "type": "SCALAR"})
        primitives.append({"attributes": {"POSITION": 0}, "indices": len(accessors) - 1, "mode": mode})
        blob += data + b"\0" * (-len(data) % 4)
    header = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
              "meshes": [{"name": "tank", "primitives": primitives}], "accessors": accessors, "bufferViews": views,
              "buffers": [{"byteLength": len(blob)}], **(extra or {})}
    if not glb:
        header["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path.write_text(json.dumps(header))
        return
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
    path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)


@pytest.mark.parametrize("glb", [False, True])
def test_gltf_triangle_fans_and_strips_are_walls_as_triangles_are(tmp_path, glb):
    """TRIANGLE_FAN primitives (mode 6) were skipped without a word: a cube of five fans and a strip lost the
    five faces (a tank without its floor, exit 0), and a cube of fans only was "not a valid GLTF". Each fan
    now gives its triangles, and the cube is the TRIANGLES cube, closed."""
    ext = "glb" if glb else "gltf"
    tris = [[q[0], q[1], q[2], q[0], q[2], q[3]] for q in _CUBE_QUADS]
    _gltf(tmp_path / f"tri.{ext}", [(4, sum(tris, []))], glb)
    _gltf(tmp_path / f"fan.{ext}", [(6, q) for q in _CUBE_QUADS], glb)
    # a quad as a strip: (0, 1, 3, 2) makes triangles (0, 1, 3) and (3, 1, 2) with the winding kept
    _gltf(tmp_path / f"mixed.{ext}", [(6, q) for q in _CUBE_QUADS[:5]] + [(5, [_CUBE_QUADS[5][i] for i in (0, 1, 3, 2)])], glb)
    ref = _import(tmp_path, [{"file": f"tri.{ext}", "fluid": "inside"}])
    for name in ("fan", "mixed"):
        wm = _import(tmp_path, [{"file": f"{name}.{ext}", "fluid": "inside"}])
        report = wm.walls[0]["report"]
        assert report["faces"] == 12 and report["watertight"], (name, report)
        assert _signed_volume(wm.vertices, wm.faces) == pytest.approx(_signed_volume(ref.vertices, ref.faces))
        np.testing.assert_allclose(wm.vertices.min(axis=0), ref.vertices.min(axis=0))
        np.testing.assert_allclose(wm.vertices.max(axis=0), ref.vertices.max(axis=0))


def test_gltf_points_lines_and_draco_are_refused_in_one_line(tmp_path):
    """A LINES primitive beside the faces was dropped and a Draco-compressed file read as zeros ("empty mesh
    after removing degenerate faces"): each is one line now, naming the mesh and primitive, or saying to
    re-export without Draco."""
    tris = sum([[q[0], q[1], q[2], q[0], q[2], q[3]] for q in _CUBE_QUADS], [])
    _gltf(tmp_path / "lines.gltf", [(4, tris), (1, [0, 1, 1, 2])])
    with pytest.raises(StageError, match=r"lines\.gltf: mesh 0 \(tank\) primitive 1 is LINES \(mode 1\), not triangles"):
        _import(tmp_path, [{"file": "lines.gltf"}])
    _gltf(tmp_path / "draco.gltf", [(4, tris)], extra={"extensionsUsed": ["KHR_draco_mesh_compression"],
                                                        "extensionsRequired": ["KHR_draco_mesh_compression"]})
    header = json.loads((tmp_path / "draco.gltf").read_text())
    header["meshes"][0]["primitives"][0]["extensions"] = {
        "KHR_draco_mesh_compression": {"bufferView": 1, "attributes": {"POSITION": 0}}}
    (tmp_path / "draco.gltf").write_text(json.dumps(header))
    with pytest.raises(StageError, match=r"draco\.gltf: Draco-compressed glTF is not supported: re-export without "
                                         r"Draco compression$"):
        _import(tmp_path, [{"file": "draco.gltf"}])
    # Draco only used, but with no uncompressed data to fall back on (the accessor has no bufferView)
    del header["extensionsRequired"], header["accessors"][0]["bufferView"]
    (tmp_path / "draco_used.gltf").write_text(json.dumps(header))
    with pytest.raises(StageError, match=r"draco_used\.gltf: Draco-compressed glTF is not supported"):
        _import(tmp_path, [{"file": "draco_used.gltf"}])


def test_a_container_missing_a_side_marked_inside_is_said_to_get_a_lid_without_distance(tmp_path, caplog):
    """fluid: inside on a tank with a whole side missing: the sign vote closes the opening, but the field has no
    distance to that lid (it jumps from +band to -band), so the water met it without wall pressure (279 Pa at it
    against 960 in the closed tank) and the warning said only 'not watertight'. It now names the opening and
    what to do; a small hole (a scan's) keeps the short warning."""
    import logging

    import trimesh

    box = trimesh.creation.box(extents=(0.4, 0.4, 0.3))
    keep = box.face_normals[:, 0] < 0.5  # the +x side's two triangles gone
    trimesh.Trimesh(box.vertices, box.faces[keep]).export(tmp_path / "open_tank.obj")
    fluid = {"spacing": 0.02, "emitters": [{"box": {"min": [-0.1, -0.1, -0.1], "max": [0.1, 0.1, 0.0]}}]}
    with caplog.at_level(logging.WARNING):
        run_stage(TrimeshImport, tmp_path / "out", config_dir=tmp_path,
                  scene={"scene": SCENE, "walls": [{"file": "open_tank.obj", "fluid": "inside"}], "fluid": fluid})
    assert "its opening, 25 l0 across, is closed as by a lid the field has no distance to" in caplog.text, caplog.text


@pytest.mark.parametrize("stated, trailing", [(0, 0), (20, 0), (12, 37)], ids=["count_0", "count_20", "trailing"])
def test_a_binary_stl_whose_header_count_is_off_is_read_from_its_size(tmp_path, caplog, stated, trailing):
    """Exporters that stream write 0 (or a stale count) in the header, some pad the file: trimesh refused all
    three as 'not a valid STL file'. The file's whole 50-byte records are read, and the mismatch said."""
    import logging

    import trimesh

    box = trimesh.creation.box(extents=(0.4, 0.4, 0.3))
    data = bytearray(trimesh.exchange.stl.export_stl(box))
    data[80:84] = np.uint32(stated).tobytes()
    (tmp_path / "tank.stl").write_bytes(bytes(data) + bytes(trailing))
    with caplog.at_level(logging.WARNING):
        mesh = _import(tmp_path, [{"file": "tank.stl", "fluid": "inside"}])
    assert len(mesh.faces) == 12
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [0.4, 0.4, 0.3], atol=1e-6)
    assert f"header says {stated} triangles and whose size holds 12" in caplog.text


def test_a_binary_stl_cut_off_inside_a_record_is_refused_naming_the_file(tmp_path):
    """A binary STL stating 12 triangles that ends 20 bytes into its fifth (a copy that stopped) was read as its
    4 whole records, a tank missing most walls, with a warning and exit 0. Refused now; a file ending on a
    record boundary short of its count (a stale count) is still read (the test above)."""
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.3))
    data = trimesh.exchange.stl.export_stl(box)
    (tmp_path / "cut.stl").write_bytes(data[:84 + 4 * 50 + 20])
    with pytest.raises(StageError, match=r"cut\.stl: binary STL cut off: its header says 12 triangles and the file "
                                         r"ends 20 bytes into triangle 5") as err:
        _import(tmp_path, [{"file": "cut.stl", "fluid": "inside"}])
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "off"])
def test_a_utf8_byte_order_mark_is_no_part_of_a_text_mesh_file(tmp_path, ext):
    """A UTF-8 BOM (Windows editors) before an OBJ's first `v` hid that vertex: every index one off, a tetrahedron
    came in with a loose vertex as a corner (exit 0); an ASCII STL with one was read as binary. Each text format
    with a BOM now reads as without it."""
    from stages.mesh_import.trimesh_import import read_mesh_file

    tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 5 5 5\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"  # vertex 5 is loose
    text = tet.encode() if ext == "obj" else trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]).export(
        file_type={"ply": "ply", "stl": "stl_ascii", "off": "off"}[ext], **({"encoding": "ascii"} if ext == "ply" else {}))
    text = text.encode() if isinstance(text, str) else text
    (tmp_path / f"plain.{ext}").write_bytes(text)
    (tmp_path / f"bom.{ext}").write_bytes(b"\xef\xbb\xbf" + text)
    v0, f0 = read_mesh_file(tmp_path / f"plain.{ext}")
    v, f = read_mesh_file(tmp_path / f"bom.{ext}")
    np.testing.assert_array_equal(v, v0)
    np.testing.assert_array_equal(f, f0)
    assert v[np.unique(f)].max() == 1.0  # the loose (5, 5, 5) is no corner
    wm = _import(tmp_path, [{"file": f"bom.{ext}"}])
    assert wm.walls[0]["report"]["watertight"] and _signed_volume(wm.vertices, wm.faces) == pytest.approx(1 / 6)


def test_a_nan_in_a_vertex_no_face_uses_is_left_out_and_in_a_used_one_refused(tmp_path):
    """A NaN in a vertex no face refers to (a leftover of an exporter) refused the whole file; such a vertex
    shapes nothing and is left out now. A NaN in a vertex a face uses is still refused in one line."""
    tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    _write(tmp_path, "unused.obj", "v nan nan nan\n" + tet.replace("f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4",
                                                                  "f 2 4 3\nf 2 3 5\nf 2 5 4\nf 3 4 5"))
    wm = _import(tmp_path, [{"file": "unused.obj"}])
    assert wm.walls[0]["report"]["watertight"] and _signed_volume(wm.vertices, wm.faces) == pytest.approx(1 / 6)
    _write(tmp_path, "used.obj", tet.replace("v 0 0 1", "v 0 0 nan"))
    with pytest.raises(StageError, match=r"used\.obj: vertex coordinates contain NaN or Inf"):
        _import(tmp_path, [{"file": "used.obj"}])


@pytest.mark.parametrize("fmt", ["obj", "usda"])
def test_a_vertex_no_face_uses_does_not_shape_a_fit(tmp_path, fmt):
    """`fit:` scales a wall into a box by the model's own box: a leftover vertex 10 x away counted in it, so the
    unit tetrahedron fitted into a 2 m box came in 0.2 m wide. The fit now sees the vertices faces use, and a USD
    wall's asset-to-scene matrix (export references the asset by it) places the asset's points where the wall is."""
    corners = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (10, 10, 10)]  # the last one no face uses
    tris = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]
    if fmt == "obj":
        _write(tmp_path, "w.obj", "".join(f"v {x} {y} {z}\n" for x, y, z in corners)
               + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in tris))
    else:
        _write(tmp_path, "w.usda", '#usda 1.0\n(\n    metersPerUnit = 1\n    upAxis = "Z"\n)\ndef Mesh "tet"\n{\n'
               f"    point3f[] points = [{', '.join(str(c) for c in corners)}]\n"
               f"    int[] faceVertexCounts = {[3] * len(tris)}\n"
               f"    int[] faceVertexIndices = {[i for t in tris for i in t]}\n}}\n")
    wall = {"file" if fmt == "obj" else "usd": f"w.{fmt}", "fit": {"min": [0, 0, 0], "max": [2, 2, 2]}}
    wm = _import(tmp_path, [wall])
    np.testing.assert_allclose(wm.vertices.min(axis=0), 0, atol=1e-12)
    np.testing.assert_allclose(wm.vertices.max(axis=0), 2, atol=1e-12)
    if fmt == "usda":
        m = np.asarray(wm.walls[0]["asset_to_scene"]).reshape(4, 4)
        placed = np.asarray(corners[:4], float) @ m[:3, :3].T + m[:3, 3]
        np.testing.assert_allclose(np.sort(placed, axis=0), np.sort(wm.vertices, axis=0), atol=1e-12)


def test_a_tiny_part_far_from_the_rest_of_a_wall_is_said_and_kept_in_the_report(tmp_path, caplog):
    """A 1 mm triangle left 50 m from a 1 m tank widened the wall's box (and the SDF grid: 1254 x 83 x 54 instead
    of 83 x 83 x 54) without a word. It is said now, with its box, triangle count and how much it widens the
    wall's box, and kept in the report (for a refusal of the grid's size to name it); a small part near the rest
    (a baffle in the tank) or a big one far away (a second tank) is no stray."""
    import logging

    tank = trimesh.creation.box(extents=(1.0, 1.0, 0.6))
    stray = trimesh.Trimesh([[50, 0, 0], [50.001, 0, 0], [50, 0.001, 0]], [[0, 1, 2]])
    baffle = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    baffle.apply_translation((0.3, 0.3, 0.2))
    other = tank.copy()
    other.apply_translation((50, 0, 0))
    trimesh.util.concatenate([tank, stray, baffle]).export(tmp_path / "stray.obj")
    trimesh.util.concatenate([tank, baffle]).export(tmp_path / "baffle.obj")
    trimesh.util.concatenate([tank, other]).export(tmp_path / "two.obj")
    with caplog.at_level(logging.WARNING):
        wm = _import(tmp_path, [{"file": "stray.obj", "fluid": "inside"}])
    found = wm.walls[0]["report"]["stray_part"]
    assert found["triangles"] == 1 and found["axis"] == "x" and found["widens"] == pytest.approx(50.501)
    np.testing.assert_allclose(found["min"], [50, 0, 0]) and np.testing.assert_allclose(found["max"], [50.001, 0.001, 0])
    np.testing.assert_allclose(found["rest_min"], [-0.5, -0.5, -0.3]) and np.testing.assert_allclose(found["rest_max"], [0.5, 0.5, 0.3])
    said = [r.getMessage() for r in caplog.records if "stray part" in r.getMessage()]
    assert len(said) == 1 and "stray.obj: a stray part of 1 triangle (under 0.01 % of the area)" in said[0], caplog.text
    assert "at x 50..50, y 0..0.001, z 0..0" in said[0] and "widening the wall's box 50.5x along x" in said[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        for name in ("baffle.obj", "two.obj"):
            wm = _import(tmp_path, [{"file": name, "fluid": "inside"}])
            assert "stray_part" not in wm.walls[0]["report"]
    assert "stray" not in caplog.text


def test_a_grid_too_large_for_a_stray_part_names_the_part_not_the_units(tmp_path):
    """A 1 mm triangle 2 km from a 1 m tank made the SDF grid too large, and the refusal advised checking
    meters_per_unit; it names the stray part and where it lies."""
    from pipeline.stage import StageError
    from stages.sdf_bake.open3d_bake import Open3dBake

    tank = trimesh.creation.box(extents=(1.0, 1.0, 0.6))
    stray = trimesh.Trimesh([[2000, 0, 0], [2000.001, 0, 0], [2000, 0.001, 0]], [[0, 1, 2]])
    trimesh.util.concatenate([tank, stray]).export(tmp_path / "stray.obj")
    walls = [{"file": "stray.obj", "fluid": "inside"}]
    out = run_stage(TrimeshImport, tmp_path / "walls", scene={"scene": SCENE, "walls": walls}, config_dir=tmp_path)
    scene = {"scene": SCENE, "walls": walls, "fluid": {"spacing": 0.02, "emitters": [{"box": {
        "min": [-0.4, -0.4, -0.2], "max": [0.4, 0.4, 0.2]}}]}}
    with pytest.raises(StageError, match=r"; wall 0 \(.*stray\.obj\) has a stray part of 1 triangle .* at x "
                                         r"2000\.\.2000.*: delete it from the file, or give a scene\.domain") as e:
        run_stage(Open3dBake, tmp_path / "sdf", scene=scene, inputs={"walls": out})
    assert "meters_per_unit" not in str(e.value)


def test_an_ascii_stl_with_a_long_solid_line_is_not_taken_for_a_binary_one(tmp_path):
    """An ASCII STL was told from a binary one by 'facet' in its first 1024 bytes: one whose 'solid' line holds a
    long name was read as binary, its text as triangles (or refused as cut off). No NUL byte there (a binary's
    records hold some) says ASCII too."""
    from stages.mesh_import.trimesh_import import read_mesh_file

    text = trimesh.creation.box(extents=(0.4, 0.4, 0.3)).export(file_type="stl_ascii")
    first, rest = text.split("\n", 1)
    (tmp_path / "long.stl").write_text(f"{first} {'tank_' * 300}\n{rest}")
    v, f = read_mesh_file(tmp_path / "long.stl")
    assert len(f) == 12
    np.testing.assert_allclose(np.ptp(v, axis=0), [0.4, 0.4, 0.3], atol=1e-6)
