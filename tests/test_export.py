"""export.usd on synthetic walls, particles and surfaces: round trip, compliance, studio assets."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from pxr import Gf, Usd, UsdGeom, UsdShade

from pipeline.testing import run_stage
from stages.common.formats import (ParticleFrame, ParticleMeta, SurfaceMesh, WallMesh, save_particle_frame,
                                   save_surface)
from stages.export.usd_export import UsdExport
from stages.export.usd_layers import compliance_problems

FRAMES = 4
FPS = 24.0


def surfaces(folder, centre, frames=FRAMES):
    """A sphere whose tessellation (so its topology) changes every frame."""
    made = []
    for f in range(frames):
        ball = trimesh.creation.icosphere(subdivisions=1 + f % 3, radius=0.2 + 0.02 * f)
        ball.apply_translation(centre)
        m = SurfaceMesh(ball.vertices.astype(np.float32), ball.faces.astype(np.int32),
                        ball.vertex_normals.astype(np.float32))
        save_surface(folder, f, m)
        made.append(m)
    return made


def particles(folder, centre, frames=FRAMES, spacing=0.05):
    rng = np.random.default_rng(3)
    ParticleMeta(spacing=spacing, mass=0.125, density=1000.0, support=2 * spacing, fps=FPS, frame_count=frames,
                 up_axis="Z", meters_per_unit=1.0, solver="synthetic").save(folder)
    made = []
    for f in range(frames):
        n = 100 + 7 * f
        p = ParticleFrame(np.asarray(centre) + rng.uniform(-0.2, 0.2, (n, 3)), rng.normal(size=(n, 3)),
                          rng.uniform(990, 1010, n), rng.uniform(0, 3000, n), np.arange(n) + 5)
        save_particle_frame(folder, f, p)
        made.append(p)
    return made


def tank_walls(folder, translate=(0.0, 0.0, 0.0), extra=None):
    box = trimesh.creation.box(extents=(2.0, 1.0, 1.0))
    box.apply_translation(np.array([0.0, 0.0, 0.5]) + translate)
    WallMesh(box.vertices, box.faces, np.zeros(len(box.faces), np.int32),
             [dict({"name": "tank", "fluid": "inside", "source": "builtin:box_tank"}, **(extra or {}))]).save(folder)
    return box


def folders(tmp_path):
    out = {}
    for name in ("walls", "surface", "particles"):
        out[name] = tmp_path / name
        out[name].mkdir()
    return out


def scene(up="Z", mpu=1.0, walls=()):
    return {"scene": {"name": "t", "units": {"up_axis": up, "meters_per_unit": mpu},
                      "frames": {"fps": FPS, "count": FRAMES}}, "walls": list(walls)}


def test_round_trip_points_topology_time_and_metrics(tmp_path):
    inputs = folders(tmp_path)
    tank_walls(inputs["walls"])
    surf = surfaces(inputs["surface"], (-0.5, 0.0, 0.4))
    parts = particles(inputs["particles"], (-0.5, 0.0, 0.4))
    out = run_stage(UsdExport, tmp_path / "usd", scene=scene(mpu=0.5), params={"usdz": True}, inputs=inputs)

    for name in ("scene.usda", "scene.usdz"):
        errors, _ = compliance_problems(out / name)
        assert errors == [], name
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 0.5
    assert stage.GetTimeCodesPerSecond() == FPS
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, FRAMES - 1)
    assert stage.GetDefaultPrim().GetPath() == "/World"

    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
    assert mesh.GetPointsAttr().GetTimeSamples() == list(range(FRAMES))
    for f, m in enumerate(surf):
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(f)), m.vertices, atol=1e-6)
        np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get(f)), m.faces.ravel())
        np.testing.assert_array_equal(np.array(mesh.GetFaceVertexCountsAttr().Get(f)), 3)
        np.testing.assert_allclose(np.array(mesh.GetNormalsAttr().Get(f)), m.normals, atol=1e-5)
        ext = np.array(mesh.GetExtentAttr().Get(f))
        np.testing.assert_allclose(ext, [m.vertices.min(0), m.vertices.max(0)], atol=1e-6)
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    shader = UsdShade.Shader(stage.GetPrimAtPath(material.GetPath().AppendChild("PreviewSurface")))
    assert shader.GetInput("ior").Get() == pytest.approx(1.33) and shader.GetInput("opacity").Get() < 1

    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    for f, p in enumerate(parts):
        np.testing.assert_allclose(np.array(points.GetPointsAttr().Get(f)), p.x, atol=1e-6)
        np.testing.assert_allclose(np.array(points.GetVelocitiesAttr().Get(f)), p.v, atol=1e-6)
        np.testing.assert_array_equal(np.array(points.GetIdsAttr().Get(f)), p.id)
        np.testing.assert_allclose(np.array(points.GetWidthsAttr().Get(f)), 0.05, rtol=1e-6)  # diameters
    walls = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Walls/tank"))
    assert len(walls.GetFaceVertexCountsAttr().Get()) == 12
    camera = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    # lens and film back are in tenths of a scene unit: a 36 mm film back is 0.72 tenths of half a metre
    assert camera.GetHorizontalApertureAttr().Get() == pytest.approx(0.72)

    # the published folder is self-contained: moved elsewhere, every sample still reads
    moved = tmp_path / "published" / "usd"
    moved.parent.mkdir()
    (out).rename(moved)
    stage = Usd.Stage.Open(str(moved / "scene.usda"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
    assert len(mesh.GetPointsAttr().Get(FRAMES - 1)) == len(surf[-1].vertices)


def write_cm_y_up_asset(path, root_translate=None):
    """A studio set: Y-up, centimetres, tank 200 x 100 (height) x 100 cm under a transformed parent (and,
    with ``root_translate``, its default prim moved too)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = UsdGeom.Xform.Define(stage, "/Set")
    if root_translate is not None:
        root.AddTranslateOp().Set(Gf.Vec3d(*root_translate))
    stage.SetDefaultPrim(root.GetPrim())
    props = UsdGeom.Xform.Define(stage, "/Set/Props")
    props.AddTranslateOp().Set(Gf.Vec3d(0, 50, 0))
    box = trimesh.creation.box(extents=(200.0, 100.0, 100.0))  # centred: y in [-50, 50] -> [0, 100]
    tank = UsdGeom.Mesh.Define(stage, "/Set/Props/Tank")
    tank.GetPointsAttr().Set([Gf.Vec3f(*map(float, v)) for v in box.vertices])
    tank.GetFaceVertexCountsAttr().Set([3] * len(box.faces))
    tank.GetFaceVertexIndicesAttr().Set([int(i) for i in box.faces.ravel()])
    stage.GetRootLayer().Save()


def world_bounds(stage, path):
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    r = cache.ComputeWorldBound(stage.GetPrimAtPath(path)).ComputeAlignedRange()
    return np.array(r.GetMin()), np.array(r.GetMax())


@pytest.fixture
def studio(tmp_path):
    """The asset placed in a Z-up metre scene moved 1 m along x, as mesh_import would deliver it."""
    write_cm_y_up_asset(tmp_path / "set.usda")
    inputs = folders(tmp_path)
    translate = (1.0, 0.0, 0.0)
    # cm Y-up -> m Z-up ((x, y, z) -> (x, -z, y) / 100), then the translation
    to_scene = [[0.01, 0, 0, 1.0], [0, 0, -0.01, 0], [0, 0.01, 0, 0], [0, 0, 0, 1]]
    tank_walls(inputs["walls"], translate, {"source": "set.usda", "usd": "set.usda", "prims": ["/Set/Props/Tank"],
                                            "asset_to_scene": np.ravel(to_scene).tolist()})
    centre = np.array([0.4, 0.1, 0.3])  # scene metres: inside the moved tank
    surf = surfaces(inputs["surface"], centre)
    particles(inputs["particles"], centre)
    sc = scene(walls=[{"usd": "set.usda", "prims": ["/Set/Props/Tank"], "fluid": "inside", "translate": translate}])
    return tmp_path, inputs, sc, surf


def scene_to_asset(p_scene):
    """The expected inverse of the placement: undo translate, metres -> cm, Z-up -> Y-up."""
    q = (np.asarray(p_scene, float) - [1.0, 0.0, 0.0]) * 100.0
    return np.stack([q[:, 0], q[:, 2], -q[:, 1]], axis=1)


def test_y_up_cm_asset_gives_a_y_up_cm_fluid_layer_that_lines_up(studio):
    tmp_path, inputs, sc, surf = studio
    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, inputs=inputs, config_dir=tmp_path,
                    params={"fluid_layer_path": "shot/fluid.usdc"})
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert compliance_problems(out / "scene.usda")[0] == []
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    # the original asset is composed in with its prim paths, not a copy of the wall mesh
    assert stage.GetPrimAtPath("/Set/Props/Tank").IsA(UsdGeom.Mesh)
    assert not stage.GetPrimAtPath("/World/Walls")
    lo, hi = world_bounds(stage, "/Set/Props/Tank")
    np.testing.assert_allclose(lo, [-100, 0, -50], atol=1e-4)
    np.testing.assert_allclose(hi, [100, 100, 50], atol=1e-4)

    fluid = Usd.Stage.Open(str(out / "shot" / "fluid.usdc"))  # the fluid layer alone, inside the usd folder
    assert UsdGeom.GetStageUpAxis(fluid) == "Y" and UsdGeom.GetStageMetersPerUnit(fluid) == 0.01
    for s in (stage, fluid):
        mesh = UsdGeom.Mesh(s.GetPrimAtPath("/World/Fluid/Surface"))
        for f, m in enumerate(surf):
            pts = np.array(mesh.GetPointsAttr().Get(f))
            np.testing.assert_allclose(pts, scene_to_asset(m.vertices), atol=1e-3)
            assert (pts.min(0) > lo).all() and (pts.max(0) < hi).all()  # inside the asset's tank
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    np.testing.assert_allclose(np.array(points.GetWidthsAttr().Get(0)), 5.0, rtol=1e-6)  # 0.05 m in cm


def test_asset_in_scene_units_is_referenced_under_its_placement(studio):
    tmp_path, inputs, sc, surf = studio
    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, inputs=inputs, config_dir=tmp_path,
                    params={"fluid_units": "scene", "particles": False})
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert compliance_problems(out / "scene.usda")[0] == []
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    lo, hi = world_bounds(stage, "/World/Asset_0")
    walls = WallMesh.load(inputs["walls"])
    np.testing.assert_allclose(lo, walls.vertices.min(0), atol=1e-6)
    np.testing.assert_allclose(hi, walls.vertices.max(0), atol=1e-6)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
    np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(2)), surf[2].vertices, atol=1e-6)


@pytest.mark.parametrize("placement, root_translate", [
    ({"rotate": [0, 0, 90], "translate": [0.5, -0.25, 0.0], "scale": 2.0}, None),
    ({"rotate": [0, 0, 90], "fit": {"min": [-0.3, -0.5, 0.0], "max": [0.3, 0.5, 0.4]}, "translate": [0.1, 0, 0]}, None),
    ({"translate": [0.5, -0.25, 0.0]}, (0.0, 3.0, 0.0)),
], ids=["scale_rotate_translate", "fit", "translated_default_prim"])
def test_asset_placed_by_the_real_mesh_import_lines_up(tmp_path, placement, root_translate):
    """End to end with mesh_import.trimesh: a Y-up cm asset rotated and moved (or fitted) into a Z-up
    metre scene; the export's inverse placement must put the asset back exactly where mesh_import's
    walls are, also when the asset's default prim carries a transform of its own (it was dropped: 3 cm off)."""
    from stages.mesh_import import trimesh_import

    write_cm_y_up_asset(tmp_path / "set.usda", root_translate)
    inputs = folders(tmp_path)
    wall = {"usd": "set.usda", "prims": ["/Set/Props/Tank"], "fluid": "inside", **placement}
    sc = scene(walls=[wall])
    run_stage(trimesh_import.TrimeshImport, inputs["walls"], scene=sc, config_dir=tmp_path)
    walls = WallMesh.load(inputs["walls"])
    lo_w, hi_w = walls.vertices.min(0), walls.vertices.max(0)
    surfaces(inputs["surface"], 0.5 * (lo_w + hi_w))
    particles(inputs["particles"], 0.5 * (lo_w + hi_w))

    out = run_stage(UsdExport, tmp_path / "scene_units", scene=sc, inputs=inputs, config_dir=tmp_path,
                    params={"fluid_units": "scene"})
    lo, hi = world_bounds(Usd.Stage.Open(str(out / "scene.usda")), "/World/Asset_0")
    np.testing.assert_allclose(lo, lo_w, atol=1e-6)
    np.testing.assert_allclose(hi, hi_w, atol=1e-6)

    out = run_stage(UsdExport, tmp_path / "asset_units", scene=sc, inputs=inputs, config_dir=tmp_path)
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    lo, hi = world_bounds(stage, "/Set/Props/Tank")
    pts = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface")).GetPointsAttr().Get(0))
    # the fluid sits at the tank's centre in the asset's own frame, scaled with it (r = 0.2 m / s)
    scale = (hi_w - lo_w).max() / 2.0  # the tank is 2 m long in the asset (200 cm)
    np.testing.assert_allclose(0.5 * (pts.min(0) + pts.max(0)), 0.5 * (lo + hi), atol=1e-3)
    np.testing.assert_allclose(pts.max(0) - pts.min(0), 2 * 0.2 * 100 / scale, rtol=0.02)


def test_empty_frames_export_and_read_back_empty(tmp_path):
    """No fluid yet (an emitter that starts later, or everything drained): empty samples, not errors."""
    inputs = folders(tmp_path)
    tank_walls(inputs["walls"])
    ParticleMeta(spacing=0.05, mass=0.1, density=1000.0, support=0.1, fps=FPS, frame_count=FRAMES, up_axis="Z",
                 meters_per_unit=1.0, solver="synthetic").save(inputs["particles"])
    for f in range(FRAMES):
        save_surface(inputs["surface"], f, SurfaceMesh.empty())
        z = np.zeros((0, 3))
        save_particle_frame(inputs["particles"], f, ParticleFrame(z, z, z[:, 0], z[:, 0], z[:, 0].astype(int)))
    out = run_stage(UsdExport, tmp_path / "usd", scene=scene(), inputs=inputs)
    assert compliance_problems(out / "scene.usda")[0] == []
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert len(UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface")).GetPointsAttr().Get(1)) == 0
    assert len(UsdGeom.Points(stage.GetPrimAtPath("/World/Particles")).GetPointsAttr().Get(1)) == 0


def write_world_rooted_asset(path, default_prim=True):
    """A set rooted at /World like ours, its root moved: Y-up, centimetres, /World translated 1 cm along
    x, a pillar 3 x 20 x 3 cm under /World/Props; its default prim /World, or none."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = UsdGeom.Xform.Define(stage, "/World")
    root.AddTranslateOp().Set(Gf.Vec3d(1, 0, 0))
    if default_prim:
        stage.SetDefaultPrim(root.GetPrim())
    box = trimesh.creation.box(extents=(3.0, 20.0, 3.0))
    box.apply_translation((11.5, 10.0, -5.5))  # Y-up cm: x 10..13, height 0..20, z -7..-4
    pillar = UsdGeom.Mesh.Define(stage, "/World/Props/Pillar")
    pillar.GetPointsAttr().Set([Gf.Vec3f(*map(float, v)) for v in box.vertices])
    pillar.GetFaceVertexCountsAttr().Set([3] * len(box.faces))
    pillar.GetFaceVertexIndicesAttr().Set([int(i) for i in box.faces.ravel()])
    stage.GetRootLayer().Save()


def world_points_in_scene_metres(stage, path, points, time=Usd.TimeCode.Default()):
    """``points`` of the prim at ``path`` in the stage's world, in metres, Z-up (the scene's frame)."""
    m = np.array(UsdGeom.XformCache(time).GetLocalToWorldTransform(stage.GetPrimAtPath(path)))  # row vectors
    p = (np.c_[np.asarray(points, float), np.ones(len(points))] @ m)[:, :3] * UsdGeom.GetStageMetersPerUnit(stage)
    return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1) if UsdGeom.GetStageUpAxis(stage) == "Y" else p


@pytest.mark.parametrize("fluid_units, default_prim", [("auto", True), ("auto", False), ("scene", True)],
                         ids=["asset_units", "asset_units_no_default_prim", "scene_units"])
def test_asset_rooted_at_world_moves_none_of_our_prims(tmp_path, fluid_units, default_prim):
    """An asset whose root prim is /World, with a transform, must not compose over the export's own /World:
    sublayered (its frame is the written one under fluid_units: asset), its translate moved the fluid,
    particles, walls and camera 1 cm with it. Everything must stay where it was simulated, in metres, and
    the asset's pillar where mesh_import put the pillar wall (also with no default prim to reference)."""
    from stages.mesh_import import trimesh_import

    write_world_rooted_asset(tmp_path / "pillar_cm.usda", default_prim)
    inputs = folders(tmp_path)
    eye, look = [0.5, -0.6, 0.4], [0.0, 0.0, 0.1]
    sc = scene(walls=[{"builtin": "box_tank", "size": [0.3, 0.2, 0.3]},
                      {"usd": "pillar_cm.usda", "fluid": "outside"}])
    sc["camera"] = {"position": eye, "focal_point": look}
    run_stage(trimesh_import.TrimeshImport, inputs["walls"], scene=sc, config_dir=tmp_path)
    walls = WallMesh.load(inputs["walls"])
    tank, pillar = (walls.vertices[np.unique(walls.faces[walls.wall_id == i])] for i in (0, 1))
    # the pillar where the asset has it: x 11..14 cm (1 cm of root translate), y 4..7 cm, z 0..20 cm
    np.testing.assert_allclose([pillar.min(0), pillar.max(0)], [[0.11, 0.04, 0.0], [0.14, 0.07, 0.2]], atol=1e-9)
    surf = surfaces(inputs["surface"], (-0.07, 0.0, 0.08))
    parts = particles(inputs["particles"], (-0.07, 0.0, 0.08))

    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, inputs=inputs, config_dir=tmp_path,
                    params={"fluid_units": fluid_units})
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert compliance_problems(out / "scene.usda")[0] == []
    assert UsdGeom.GetStageMetersPerUnit(stage) == (0.01 if fluid_units == "auto" else 1.0)
    for f in (0, FRAMES - 1):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
        got = world_points_in_scene_metres(stage, mesh.GetPath(), mesh.GetPointsAttr().Get(f), f)
        np.testing.assert_allclose(got, surf[f].vertices, atol=1e-6)
        points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
        got = world_points_in_scene_metres(stage, points.GetPath(), points.GetPointsAttr().Get(f), f)
        np.testing.assert_allclose(got, parts[f].x, atol=1e-6)
    # the simulated tank is x -15..15 cm (it came out -14..16)
    wall = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Walls/wall0_box_tank"))
    got = world_points_in_scene_metres(stage, wall.GetPath(), wall.GetPointsAttr().Get())
    np.testing.assert_allclose([got.min(0), got.max(0)], [tank.min(0), tank.max(0)], atol=1e-6)
    np.testing.assert_allclose([got.min(0)[0], got.max(0)[0]], [-0.15, 0.15], atol=1e-6)
    camera = world_points_in_scene_metres(stage, "/World/Camera", [[0.0, 0.0, 0.0]])[0]
    np.testing.assert_allclose(camera, eye, atol=1e-6)

    # the asset is there once, with its own root transform, on the simulated pillar wall
    found = [p for p in stage.Traverse() if p.GetName() == "Pillar" and p.IsA(UsdGeom.Mesh)]
    assert len(found) == 1
    got = world_points_in_scene_metres(stage, found[0].GetPath(), UsdGeom.Mesh(found[0]).GetPointsAttr().Get())
    np.testing.assert_allclose([got.min(0), got.max(0)], [pillar.min(0), pillar.max(0)], atol=1e-6)


@pytest.mark.parametrize("default_prim", [True, False], ids=["default_prim", "no_default_prim"])
def test_the_fx_layer_sublayered_beside_a_world_rooted_set_lines_up(tmp_path, default_prim):
    """export.fluid_layer_path is the layer a shot sublayers beside the set. Its water was under /World: beside a
    set whose /World is translated, the two merged and the water moved with the set's root (3 cm high in a
    user's bowl set). Sublayered with the set (either order), and opened alone, the water is where it was
    simulated; with a set not rooted at /World the layer keeps /World."""
    from stages.mesh_import import trimesh_import

    write_world_rooted_asset(tmp_path / "pillar_cm.usda", default_prim)
    inputs = folders(tmp_path)
    sc = scene(walls=[{"builtin": "box_tank", "size": [0.3, 0.2, 0.3]}, {"usd": "pillar_cm.usda", "fluid": "outside"}])
    run_stage(trimesh_import.TrimeshImport, inputs["walls"], scene=sc, config_dir=tmp_path)
    surf = surfaces(inputs["surface"], (-0.07, 0.0, 0.08))
    particles(inputs["particles"], (-0.07, 0.0, 0.08))
    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, inputs=inputs, config_dir=tmp_path,
                    params={"fluid_layer_path": "fx/water.usdc"})
    layer = Usd.Stage.Open(str(out / "fx" / "water.usdc"))
    assert layer.GetDefaultPrim().GetPath() == "/FX" and not layer.GetPrimAtPath("/World")
    bound = UsdShade.MaterialBindingAPI(layer.GetPrimAtPath("/FX/Fluid/Surface")).ComputeBoundMaterial()[0]
    assert bound.GetPath() == "/FX/Fluid/Looks/Water"  # the binding followed the copy
    for order in (["./fx/water.usdc", "./assets/pillar_cm.usda"], ["./assets/pillar_cm.usda", "./fx/water.usdc"],
                  ["./fx/water.usdc"]):
        shot = Usd.Stage.CreateNew(str(out / f"shot_{len(order)}_{order[0][2:4]}.usda"))
        UsdGeom.SetStageUpAxis(shot, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(shot, 0.01)
        shot.GetRootLayer().subLayerPaths = order
        mesh = UsdGeom.Mesh(shot.GetPrimAtPath("/FX/Fluid/Surface"))
        for f in (0, FRAMES - 1):
            got = world_points_in_scene_metres(shot, mesh.GetPath(), mesh.GetPointsAttr().Get(f), f)
            np.testing.assert_allclose(got, surf[f].vertices, atol=1e-6)
    # a set without a /World of its own: the layer is fluid_surface.usdc's, under /World
    other = tmp_path / "other"
    other.mkdir()
    inputs2 = folders(other)
    tank_walls(inputs2["walls"])
    surfaces(inputs2["surface"], (-0.5, 0.0, 0.4))
    particles(inputs2["particles"], (-0.5, 0.0, 0.4))
    out2 = run_stage(UsdExport, other / "usd", scene=scene(), inputs=inputs2, params={"fluid_layer_path": "fx.usdc"})
    assert Usd.Stage.Open(str(out2 / "fx.usdc")).GetPrimAtPath("/World/Fluid/Surface").IsA(UsdGeom.Mesh)


@pytest.mark.parametrize("name", ["scene.usda", "particles.usdc", "Walls.usdc", "fluid_surface.usdc",
                                  "assets/set.usda"])
def test_a_fluid_layer_path_the_export_writes_is_refused_with_the_config(name):
    """Refused only after every stage had run (the whole simulation lost); the names are known up front."""
    with pytest.raises(Exception, match="is a file the export itself writes"):
        UsdExport.Params(fluid_layer_path=name)


def test_a_usdz_export_leaves_the_published_layers_with_their_write_times(tmp_path):
    """The usdz's fixed zip times were stamped on the layers themselves (2000-01-01): a live session's reload,
    which goes by modification time, never saw a re-export and kept the old water."""
    import time

    inputs = folders(tmp_path)
    tank_walls(inputs["walls"])
    surfaces(inputs["surface"], (-0.5, 0.0, 0.4))
    particles(inputs["particles"], (-0.5, 0.0, 0.4))
    before = time.time() - 5
    out = run_stage(UsdExport, tmp_path / "usd", scene=scene(), inputs=inputs, params={"usdz": True})
    for f in out.rglob("*"):
        assert f.stat().st_mtime > before, f


def animated(stage):
    """{(prim, attribute): time samples} of every time-sampled attribute on the composed stage."""
    return {(str(p.GetPath()), a.GetName()): a.GetTimeSamples()
            for p in stage.Traverse() for a in p.GetAttributes() if a.GetNumTimeSamples()}


def test_frames_run_exports_only_the_selected_frames(tmp_path):
    """A --frames run: every layer holds the selected frames and nothing else, and the stage plays
    first..last selected. The simulation's own particles.usdc (every frame) was copied as it was, so the
    particles moved over 0..3 beside a surface held still outside 1..2, on a stage that said 0..3."""
    from stages.common.usd_points import write_points_layer

    inputs = folders(tmp_path)
    tank_walls(inputs["walls"])
    surfaces(inputs["surface"], (-0.5, 0.0, 0.4))
    parts = particles(inputs["particles"], (-0.5, 0.0, 0.4))
    sim_layer = write_points_layer(inputs["particles"] / "particles.usdc", enumerate(parts), spacing=0.05,
                                   up_axis="Z", meters_per_unit=1.0, fps=FPS, count=FRAMES)

    selected = [1, 2]
    out = run_stage(UsdExport, tmp_path / "part", scene=scene(), inputs=inputs, frames=tuple(selected))
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    samples = animated(stage)
    assert ("/World/Particles", "points") in samples and ("/World/Fluid/Surface", "points") in samples
    assert {k: v for k, v in samples.items() if v != selected} == {}
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1, 2)
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    for f in selected:
        np.testing.assert_allclose(np.array(points.GetPointsAttr().Get(f)), parts[f].x, atol=1e-6)

    # a whole run is as before: every frame, and the simulation's layer itself
    out = run_stage(UsdExport, tmp_path / "whole", scene=scene(), inputs=inputs)
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    assert animated(stage) == {k: list(range(FRAMES)) for k in samples}
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, FRAMES - 1)
    assert (out / "particles.usdc").read_bytes() == sim_layer.read_bytes()


def test_a_drained_frame_has_usds_empty_extent(tmp_path):
    """A frame with no particles (a sink drained the tank) gets USD's empty extent, which bounding boxes skip;
    a zero box at the origin pulled the shot's bounds there."""
    from pxr import Usd, UsdGeom

    from stages.common.formats import ParticleFrame
    from stages.common.usd_points import write_points_layer

    full = ParticleFrame(np.array([[2.0, 3.0, 4.0], [2.5, 3.5, 4.5]]), np.zeros((2, 3)), np.full(2, 1000.0),
                         np.zeros(2), np.arange(2))
    empty = ParticleFrame(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, np.int64))
    path = write_points_layer(tmp_path / "p.usdc", [(0, full), (1, empty)], spacing=0.1, up_axis="Z",
                              meters_per_unit=1.0, fps=10, count=2)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/World/Particles")
    lo, hi = (np.array(c) for c in UsdGeom.Points(prim).GetExtentAttr().Get(Usd.TimeCode(1)))
    assert (lo > hi).all()  # empty
    boxes = [UsdGeom.BBoxCache(Usd.TimeCode(t), ["default"]).ComputeWorldBound(prim).ComputeAlignedRange()
             for t in (0, 1)]
    assert boxes[1].IsEmpty() and np.allclose(boxes[0].GetMin(), [1.95, 2.95, 3.95], atol=1e-6)
    from stages.export.usd_layers import extent_of
    lo, hi = (np.array(c) for c in extent_of(np.zeros((0, 3), np.float32)))
    assert (lo > hi).all()


@pytest.mark.parametrize("translate", [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], ids=["sublayered", "referenced"])
def test_an_asset_animated_from_code_1001_moves_in_step_with_the_shot(tmp_path, translate):
    """Studios start a shot at code 1001; mesh_import simulates an animated asset from its startTimeCode, so
    the exported scene must play the asset from there at our code 0 (a layer offset), or the composed wall
    stands still for 1001 codes and moves 42 s late, away from the fluid it pushed."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "set.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1001)
    stage.SetEndTimeCode(1031)
    stage.SetTimeCodesPerSecond(48)  # not ours (24): USD scales the codes itself
    root = UsdGeom.Xform.Define(stage, "/Set")
    stage.SetDefaultPrim(root.GetPrim())
    box = UsdGeom.Xform.Define(stage, "/Set/Box")
    op = box.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 1001)
    op.Set(Gf.Vec3d(0.3, 0, 0), 1031)
    stage.GetRootLayer().Save()
    inputs = folders(tmp_path)
    to_scene = np.eye(4)
    to_scene[0, 3] = translate[0]
    tank_walls(inputs["walls"], (0.0, 0.0, 0.0), {"source": "set.usda", "usd": "set.usda", "prims": ["/Set/Box"],
                                                   "asset_to_scene": to_scene.ravel().tolist()})
    surfaces(inputs["surface"], np.array([0.0, 0.0, 0.3]))
    particles(inputs["particles"], np.array([0.0, 0.0, 0.3]))
    sc = scene(walls=[{"usd": "set.usda", "prims": ["/Set/Box"], "fluid": "inside", "translate": list(translate)}])
    # in the asset's frame (the default) the asset is sublayered; in the scene's, moved, it is referenced
    params = {"fluid_units": "scene"} if any(translate) else {}
    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, inputs=inputs, config_dir=tmp_path, params=params)
    composed = Usd.Stage.Open(str(out / "scene.usda"))
    prim = next(p for p in composed.Traverse() if p.GetName() == "Box")
    assert (str(prim.GetPath()) == "/Set/Box") == (not any(translate)), prim.GetPath()
    for code, seconds in ((0, 0.0), (2, 2 / FPS), (3, 3 / FPS)):
        x = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(code).ExtractTranslation()[0]
        # the asset's own pose at its start + seconds: 0.3 m over 30 codes at 48 codes a second
        assert abs(x - (translate[0] + 0.3 * min(seconds * 48 / 30, 1.0))) < 1e-9, (code, x)


@pytest.mark.parametrize("mpu", [1.0, 0.01])
def test_the_usd_cameras_clipping_range_holds_the_whole_scene(tmp_path, mpu):
    """A camera beside the tank aimed at a point far past it: the near plane was 1 % of the distance to that
    point, 1.5 m, and cut 71 % of the water a user's frames showed. Near and far now hold the walls' box
    (padded) from the eye, in any units."""
    inputs = folders(tmp_path)
    box = tank_walls(inputs["walls"])
    surfaces(inputs["surface"], (-0.5, 0.0, 0.4))
    particles(inputs["particles"], (-0.5, 0.0, 0.4))
    sc = scene(mpu=mpu)  # the walls and surfaces are in the config's units as given
    sc["camera"] = {"position": [1.2, -0.5, 0.6], "focal_point": [-150.0, -0.5, 0.5]}
    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, params={"particles": False}, inputs=inputs)
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    camera = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    near, far = camera.GetClippingRangeAttr().Get()
    eye = np.array([1.2, -0.5, 0.6])
    reach = np.linalg.norm(box.vertices - eye, axis=1)  # every corner of the tank, and the water inside it
    assert 0 < near < 0.2 and far >= reach.max(), (near, far)  # the tank's nearest face is 0.2 from the eye
    assert far / near < 1e6


def test_a_set_referencing_geometry_outside_its_folder_comes_along(tmp_path):
    """sets/set.usda references ../geo/tank.usda (a studio's sets/ + geo/ layout): the export copied only the
    set's own folder, the reference pointed at a usd/geo/ that did not exist, and the tank came in empty (in
    scene.usda and the usdz), exit 0. Both files are copied with their layout now, and the copy composes."""
    from pxr import Sdf, UsdUtils

    from stages.mesh_import import trimesh_import

    (tmp_path / "geo").mkdir()
    (tmp_path / "sets").mkdir()
    write_cm_y_up_asset(tmp_path / "geo" / "tank.usda")
    stage = Usd.Stage.CreateNew(str(tmp_path / "sets" / "set.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = UsdGeom.Xform.Define(stage, "/Set")
    stage.SetDefaultPrim(root.GetPrim())
    stage.DefinePrim("/Set/Geo").GetReferences().AddReference("../geo/tank.usda")
    stage.GetRootLayer().Save()
    inputs = folders(tmp_path)
    sc = scene(walls=[{"usd": "sets/set.usda", "fluid": "inside"}])
    run_stage(trimesh_import.TrimeshImport, inputs["walls"], scene=sc, config_dir=tmp_path)
    walls = WallMesh.load(inputs["walls"])
    centre = 0.5 * (walls.vertices.min(0) + walls.vertices.max(0))
    surfaces(inputs["surface"], centre)
    particles(inputs["particles"], centre)
    out = run_stage(UsdExport, tmp_path / "usd", scene=sc, inputs=inputs, config_dir=tmp_path, params={"usdz": True})
    for name in ("scene.usda", "scene.usdz"):
        stage = Usd.Stage.Open(str(out / name))
        tanks = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.GetName() == "Tank"]
        assert len(tanks) == 1 and len(tanks[0].GetPointsAttr().Get() or []) == 8, name
        _, _, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(out / name)))
        assert unresolved == [], (name, unresolved)


def test_the_surface_carries_the_waters_velocities_for_motion_blur(tmp_path):
    """The surface's topology changes every frame, so a renderer can blur it only from authored velocities
    (UsdGeomPointBased): a ball of particles spinning about z at 2 rad/s and drifting at 0.5 m/s along x gives
    its surface vertices v = (0.5, 0, 0) + w x r within w l0 (the neighbourhood of a vertex at the free surface
    is one-sided: its particles' mean lies up to a spacing inside), in units per second."""
    inputs = folders(tmp_path)
    tank_walls(inputs["walls"])
    centre = np.array([-0.5, 0.0, 0.4])
    surf = surfaces(inputs["surface"], centre)
    g = np.arange(-0.3, 0.3001, 0.025)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) <= 0.3]  # the surfaces (radius 0.2-0.26) inside it
    omega, drift = np.array([0.0, 0.0, 2.0]), np.array([0.5, 0.0, 0.0])
    ParticleMeta(spacing=0.025, mass=0.0156, density=1000.0, support=0.05, fps=FPS, frame_count=FRAMES,
                 up_axis="Z", meters_per_unit=1.0, solver="synthetic").save(inputs["particles"])
    for f in range(FRAMES):
        n = len(x)
        save_particle_frame(inputs["particles"], f, ParticleFrame(centre + x, drift + np.cross(omega, x),
                                                                  np.full(n, 1000.0), np.zeros(n), np.arange(n)))
    out = run_stage(UsdExport, tmp_path / "usd", scene=scene(), inputs=inputs, params={"particles": False})
    stage = Usd.Stage.Open(str(out / "scene.usda"))  # held: a prim of a dropped stage is invalid
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
    assert mesh.GetVelocitiesAttr().GetTimeSamples() == list(range(FRAMES))
    for f, m in enumerate(surf):
        v = np.array(mesh.GetVelocitiesAttr().Get(f))
        expected = drift + np.cross(omega, m.vertices - centre)
        assert v.shape == m.vertices.shape
        assert np.abs(v - expected).max() < 2.0 * 0.025, f
    out = run_stage(UsdExport, tmp_path / "off", scene=scene(), inputs=inputs,
                    params={"particles": False, "surface_velocities": False})
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
    assert not mesh.GetVelocitiesAttr().HasAuthoredValue()


def test_a_fast_turning_wall_stays_rigid_between_frames_and_colliders_are_guides(tmp_path):
    """A wall turning 13 degrees a frame: its matrix op was interpolated entry by entry, so at mid-frame it
    shrank by 1.2 % (determinant 0.988). Translate + orient ops interpolate rigidly: the determinant is 1 at
    every half frame and the poses at the frames are the simulated ones. A built-in tank is a collider drawn
    as a guide (it hid the water in viewers that draw back faces), the particles beside a surface too, and
    the scene has a model hierarchy (/World an assembly, the fluid a component)."""
    from pxr import Kind

    from stages.common.motion import RigidMotion

    inputs = folders(tmp_path)
    tank = trimesh.creation.box(extents=(2.0, 1.0, 1.0)).apply_translation([0.0, 0.0, 0.5])
    paddle = trimesh.creation.box(extents=(0.1, 0.6, 0.4)).apply_translation([0.3, 0.0, 0.4])
    motion = RigidMotion.from_keyframes([{"time": 0.0}, {"time": FRAMES / FPS, "rotate": [0, 0, 13.0 * FRAMES]}],
                                        [0.3, 0.0, 0.4])
    WallMesh(np.vstack([tank.vertices, paddle.vertices]), np.vstack([tank.faces, paddle.faces + 8]),
             np.repeat(np.arange(2, dtype=np.int32), 12),
             [{"name": "tank", "fluid": "inside", "source": "builtin:box_tank"},
              {"name": "paddle", "fluid": "outside", "source": "paddle.obj", "motion": motion.to_json()}]
             ).save(inputs["walls"])
    surfaces(inputs["surface"], (-0.5, 0.0, 0.4))
    particles(inputs["particles"], (-0.5, 0.0, 0.4))
    out = run_stage(UsdExport, tmp_path / "usd", scene=scene(), inputs=inputs)
    stage = Usd.Stage.Open(str(out / "scene.usda"))
    prim = stage.GetPrimAtPath("/World/Walls/paddle")
    xf = UsdGeom.Xformable(prim)
    for f in range(FRAMES - 1):
        at_frame = np.array(xf.ComputeLocalToWorldTransform(f)).T  # USD's row vectors -> column vectors
        np.testing.assert_allclose(at_frame, motion.matrix(f / FPS), atol=1e-6)
        between = np.array(xf.ComputeLocalToWorldTransform(f + 0.5)).T
        assert abs(np.linalg.det(between[:3, :3]) - 1.0) < 1e-9, f
        # turning about its pivot between frames too (a translate about the origin swung it off its path)
        np.testing.assert_allclose(between, motion.matrix((f + 0.5) / FPS), atol=1e-6)
    assert UsdGeom.Imageable(stage.GetPrimAtPath("/World/Walls/tank")).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    assert UsdGeom.Imageable(prim).GetPurposeAttr().Get() == UsdGeom.Tokens.default_  # the user's own model
    assert UsdGeom.Imageable(stage.GetPrimAtPath("/World/Particles")).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    assert Usd.ModelAPI(stage.GetPrimAtPath("/World")).GetKind() == Kind.Tokens.assembly
    assert Usd.ModelAPI(stage.GetPrimAtPath("/World/Fluid")).GetKind() == Kind.Tokens.component
    assert compliance_problems(out / "scene.usda")[0] == []


def test_the_same_export_gives_the_same_usdz_bytes(tmp_path):
    """The usdz's zip entries carried the files' write times: every re-export differed (a farm's checksum
    dedup saw a change each time). The layers were already identical; the package is now too."""
    import hashlib
    import time

    inputs = folders(tmp_path)
    tank_walls(inputs["walls"])
    surfaces(inputs["surface"], (-0.5, 0.0, 0.4))
    particles(inputs["particles"], (-0.5, 0.0, 0.4))
    digests = []
    for run in ("a", "b"):
        out = run_stage(UsdExport, tmp_path / run, scene=scene(), inputs=inputs, params={"usdz": True})
        digests.append(hashlib.sha256((out / "scene.usdz").read_bytes()).hexdigest())
        time.sleep(2.1)  # zip times have a 2 s resolution
    assert digests[0] == digests[1]
    with pytest.raises(Exception, match="fluid_layer_path is the surface's layer: it needs surface: true"):
        UsdExport.Params(fluid_layer_path="layers/fluid.usdc", surface=False)


def test_surface_velocities_are_the_kernel_mean_of_the_particles_within_reach_or_the_nearest(tmp_path):
    """surface_velocities against its definition, by brute force: at each vertex the (1 - r^2 / R^2)^3-weighted mean
    of the velocities of the particles within R = 2 l0, or, with none that near, the nearest particle's among
    those within the cells searched (a vertex 1.5 R off gets its nearest; one far off gets zero)."""
    from stages.common.formats import ParticleFrame, ParticleMeta, load_particle_frame, save_particle_frame
    from stages.export.surface_velocity import surface_velocities

    rng = np.random.default_rng(5)
    l0 = 0.02
    x = rng.uniform(0.0, 0.3, (4000, 3))
    v = rng.normal(size=x.shape)
    ParticleMeta(spacing=l0, mass=0.008, density=1000.0, support=2 * l0, fps=10, frame_count=1, up_axis="Z",
                 meters_per_unit=1.0, solver="test").save(tmp_path)
    save_particle_frame(tmp_path, 0, ParticleFrame(x=x, v=v, rho=np.full(len(x), 1000.0), p=np.zeros(len(x)),
                                                   id=np.arange(len(x))))
    stored = load_particle_frame(tmp_path, 0)  # as the frame keeps them (float32)
    x, v = stored.x.astype(np.float64), stored.v.astype(np.float64)
    reach = 2 * l0
    pts = np.vstack([rng.uniform(-0.02, 0.32, (3000, 3)), [[0.15, 0.15, 0.3 + 1.5 * reach], [5.0, 5.0, 5.0]]])
    got = surface_velocities(pts, tmp_path, 0)
    for q, p in enumerate(pts[:-2]):
        r2 = ((x - p) ** 2).sum(axis=1)
        w = np.where(r2 < reach ** 2, (1 - r2 / reach ** 2) ** 3, 0.0)
        want = (w[:, None] * v).sum(axis=0) / w.sum() if w.sum() > 0 else v[np.argmin(r2)]
        np.testing.assert_allclose(got[q], want, rtol=1e-9, atol=1e-12)
    far = ((x - pts[-2]) ** 2).sum(axis=1)
    assert far.min() > reach ** 2
    np.testing.assert_array_equal(got[-2], v[np.argmin(far)])
    np.testing.assert_array_equal(got[-1], 0.0)


def test_fluid_units_asset_without_a_usd_wall_is_refused_before_anything_runs(tmp_path):
    """It was refused only by run, after the whole simulation (the corpus's 111 checks the command line: exit 2,
    nothing in the cache); a USD wall in the config passes the check."""
    from pipeline.stage import StageError
    from pipeline.testing import stage_context
    from stages.export.usd_export import UsdParams

    fluid = {"spacing": 0.1, "emitters": [{"box": {"min": [0, 0, 0], "max": [0.5, 0.5, 0.5]}}]}
    asset = {"scene": {"name": "t"}, "walls": [{"usd": "set/tank.usda"}], "fluid": fluid}
    builtin = {**asset, "walls": [{"builtin": "box_tank", "size": [1, 1, 1]}]}
    check = UsdExport().check
    ctx = lambda scene: stage_context(UsdExport, tmp_path, scene=scene, extra_reads=UsdExport.estimate_reads)
    with pytest.raises(StageError, match="fluid_units: asset needs a wall from a USD asset"):
        check(ctx(builtin), UsdParams(fluid_units="asset"))
    check(ctx(asset), UsdParams(fluid_units="asset"))
    check(ctx(builtin), UsdParams())  # auto: the scene's frame
