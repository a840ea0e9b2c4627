"""Units end to end: the same small scene (a box tank with a block of water, SPH, a few frames) in
metres, centimetres and millimetres, Z-up and Y-up, through the real stages mesh_import -> sdf_bake ->
simulate -> surface_extract -> wall_snap -> render. Everything a stage writes is in scene units, so
each variant, scaled back by its unit (and turned back to Z-up), must agree with the metre Z-up scene:
particles, surface (vertex count, area, enclosed volume), snap error, rendered frame. And a studio set
in centimetres, Y-up, comes back from export in centimetres, Y-up."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from pipeline.testing import run_stage
from stages.common.formats import ParticleMeta, WallMesh, load_particle_frame, load_surface
from stages.common.meshes import signed_volume, tidy
from stages.common.sdf import SDFGrid
from stages.export.usd_export import UsdExport
from stages.mesh_import.trimesh_import import TrimeshImport
from stages.render.pyvista_render import PyvistaRender
from stages.sdf_bake.open3d_bake import Open3dBake
from stages.simulate.sph import SPHSimulate
from stages.surface_extract.marching_cubes import MarchingCubes
from stages.wall_snap.distance import DistanceSnap, DistanceSnapParams, closest_points_on, snap_mesh

L0 = 0.01  # metres
FRAMES = 4
LAST = FRAMES - 1
# Z-up, metres: tank x in [-0.05, 0.05], y in [-0.04, 0.04], z in [0, 0.1]; water (4 x 8 x 6 particles)
# in its -x end
TANK = (0.10, 0.08, 0.10)
WATER = ((-0.05, -0.04, 0.0), (-0.01, 0.04, 0.06))
VARIANTS = [(1.0, "Z"), (0.01, "Z"), (0.001, "Z"), (0.01, "Y")]
RESOLUTION = (160, 120)


def z_to_y(p) -> np.ndarray:
    """Z-up coordinates to the Y-up frame the scenes use ((x, y, z) -> (x, z, -y), right-handed)."""
    p = np.asarray(p, np.float64)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def y_to_z(p) -> np.ndarray:
    p = np.asarray(p, np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


def scene(mpu: float, up: str) -> dict:
    s = 1.0 / mpu  # metres -> scene units
    lo, hi = (np.array(c) * s for c in WATER)
    size = np.array(TANK) * s
    if up == "Y":
        lo, hi = np.minimum(z_to_y(lo), z_to_y(hi)), np.maximum(z_to_y(lo), z_to_y(hi))
        size = size[[0, 2, 1]]
    return {"scene": {"name": "units", "frames": {"fps": 50, "count": FRAMES},
                      "units": {"up_axis": up, "meters_per_unit": mpu}},
            "walls": [{"builtin": "box_tank", "size": size.tolist(), "fluid": "inside"}],
            "fluid": {"spacing": L0 * s, "emitters": [{"box": {"min": lo.tolist(), "max": hi.tolist()}}]},
            "effects": {"gravity": {}, "viscosity": {"mu": 0.001}}}


def write_cm_y_up_set(path) -> None:
    """The tank as a studio hands it over: Y-up, centimetres, a mesh under a transformed parent."""
    import trimesh

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Set").GetPrim())
    UsdGeom.Xform.Define(stage, "/Set/Props").AddTranslateOp().Set(Gf.Vec3d(1.0, 5.0, 0.0))
    box = trimesh.creation.box(extents=np.abs(z_to_y(np.array(TANK) * 100)))  # centred; lifted by Props
    box.apply_translation((-1.0, 0.0, 0.0))
    tank = UsdGeom.Mesh.Define(stage, "/Set/Props/Tank")
    tank.GetPointsAttr().Set([Gf.Vec3f(*map(float, v)) for v in box.vertices])
    tank.GetFaceVertexCountsAttr().Set([3] * len(box.faces))
    tank.GetFaceVertexIndicesAttr().Set([int(i) for i in box.faces.ravel()])
    stage.GetRootLayer().Save()


STUDIO = (0.001, "Z")  # this variant takes its tank from the centimetre Y-up set and exports back into it


def run_pipeline(root, mpu: float, up: str, offset=None) -> dict:
    sc = scene(mpu, up)
    if offset is not None:  # the scene moved away from the world's origin (metres, Z up)
        sc["walls"][0]["center"] = list(map(float, offset))
        box = sc["fluid"]["emitters"][0]["box"]
        box["min"], box["max"] = (np.add(box["min"], offset).tolist(), np.add(box["max"], offset).tolist())
    d = {k: root / k for k in ("walls", "sdf", "particles", "raw", "surface", "frames", "usd")}
    if (mpu, up) == STUDIO:
        write_cm_y_up_set(root / "set.usda")
        sc["walls"] = [{"usd": "set.usda", "prims": ["/Set/Props/Tank"], "fluid": "inside"}]
    run_stage(TrimeshImport, d["walls"], scene=sc, config_dir=root)
    run_stage(Open3dBake, d["sdf"], scene=sc, inputs={"walls": d["walls"]})
    run_stage(SPHSimulate, d["particles"], scene=sc, params={"threads": 2}, inputs={"sdf": d["sdf"]})
    run_stage(MarchingCubes, d["raw"], scene=sc, inputs={"particles": d["particles"], "sdf": d["sdf"]},
              frames=(0, LAST))
    run_stage(DistanceSnap, d["surface"], scene=sc, frames=(0, LAST),
              inputs={"raw_surface": d["raw"], "sdf": d["sdf"], "particles": d["particles"], "walls": d["walls"]})
    run_stage(PyvistaRender, d["frames"], scene=sc, frames=(LAST,),
              params={"resolution": list(RESOLUTION), "label": False},
              inputs={"walls": d["walls"], "surface": d["surface"], "particles": d["particles"]})
    if (mpu, up) == STUDIO or offset is not None:
        run_stage(UsdExport, d["usd"], scene=sc, frames=(0, LAST), config_dir=root,
                  inputs={"walls": d["walls"], "particles": d["particles"], "surface": d["surface"]})
    return d


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return {(mpu, up): run_pipeline(tmp_path_factory.mktemp(f"{up}{mpu}"), mpu, up) for mpu, up in VARIANTS}


def to_metres_z_up(p, mpu: float, up: str) -> np.ndarray:
    p = np.asarray(p, np.float64) * mpu
    return y_to_z(p) if up == "Y" else p


def snapped_like_raw(r, frame: int):
    """The frame's snapped surface vertex for vertex with its raw one: wall_snap's result before the stage
    tidies it (which drops unreferenced vertices), checked to be what the stage published."""
    raw = load_surface(r["raw"], frame)
    same, _ = snap_mesh(raw, SDFGrid.load(r["sdf"]), ParticleMeta.load(r["particles"]).spacing, DistanceSnapParams(),
                        WallMesh.load(r["walls"]), particles=load_particle_frame(r["particles"], frame).x)
    published = load_surface(r["surface"], frame)
    v, f = tidy(same.vertices, same.faces)
    np.testing.assert_array_equal(v, published.vertices)
    np.testing.assert_array_equal(f, published.faces)
    return raw, same


def area(v, f) -> float:
    return float(0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())


def matched(a, b):
    """Indices putting the particles of frame 0 of ``b`` in the order of ``a`` (by position: the emitter
    lattice is listed in another order in a Y-up scene), then valid for every frame through the ids."""
    ka = np.lexsort(np.round(a / (0.1 * L0)).T)
    kb = np.lexsort(np.round(b / (0.1 * L0)).T)
    np.testing.assert_allclose(a[ka], b[kb], atol=1e-6 * L0)
    order = np.empty(len(a), np.int64)
    order[ka] = kb
    return order


@pytest.mark.parametrize("variant", VARIANTS[1:], ids=lambda v: f"{v[1]}-up_{v[0]}")
def test_every_stage_agrees_with_the_metre_z_up_scene(runs, variant):
    mpu, up = variant
    ref, run = runs[(1.0, "Z")], runs[variant]
    meta = ParticleMeta.load(run["particles"])
    assert meta.meters_per_unit == mpu and meta.up_axis == up
    assert meta.spacing * mpu == pytest.approx(L0)
    np.testing.assert_allclose(meta.volume(1000.0), ParticleMeta.load(ref["particles"]).volume(1000.0) / mpu ** 3,
                               rtol=1e-12)

    # particles: the same motion, scaled (and turned) back
    a0, b0 = load_particle_frame(ref["particles"], 0), load_particle_frame(run["particles"], 0)
    a, b = load_particle_frame(ref["particles"], LAST), load_particle_frame(run["particles"], LAST)
    order = matched(a0.x.astype(np.float64), to_metres_z_up(b0.x, mpu, up))
    b_id_of = dict(zip(a0.id.tolist(), b0.id[order].tolist()))  # a's particle id -> b's
    where_b = {int(i): k for k, i in enumerate(b.id)}
    ib = np.array([where_b[b_id_of[int(i)]] for i in a.id])
    fall = np.abs(a.x[:, 2].max() - a0.x[:, 2].max())
    assert fall > 0.3 * L0  # the block has started to collapse: agreement means something
    np.testing.assert_allclose(to_metres_z_up(b.x[ib], mpu, up), a.x, atol=1e-3 * L0)  # measured: 1e-6 l0
    np.testing.assert_allclose(to_metres_z_up(b.v[ib], mpu, up), a.v, atol=1e-3 * L0 * 50)  # l0 per frame
    np.testing.assert_allclose(b.rho[ib], a.rho, rtol=1e-4)  # kg/m^3 in every unit

    # surface: not empty, the same mesh scaled (area by unit^2, volume by unit^3)
    for stage in ("raw", "surface"):
        for f in (0, LAST):
            sa, sb = load_surface(ref[stage], f), load_surface(run[stage], f)
            assert len(sa.faces) > 500
            vb = to_metres_z_up(sb.vertices, mpu, up)
            va = sa.vertices.astype(np.float64)
            assert len(sb.vertices) == len(sa.vertices)
            assert area(vb, sb.faces) == pytest.approx(area(va, sa.faces), rel=0.01)
            assert signed_volume(vb, sb.faces) == pytest.approx(signed_volume(va, sa.faces), rel=0.01)
            # the same arithmetic in other units, and in the Y-up scene too for the raw surface (extracted in the
            # Z-up frame: the same vertices in the same order); wall_snap works in the scene's own frame
            if up == "Z" or stage == "raw":
                # to 3e-4 l0: where the field is flat across a cell, marching cubes' interpolation turns the
                # particles' 3e-7 l0 of rounding into up to 6e-5 l0, and the snap into 1.2e-4 l0 (measured, mm);
                # an edge whose two ends both lie within rounding of the iso level amplifies it without bound
                # (the spline's frame 3: 2 raw vertices of 938 at 3.7e-4 and 7.4e-4 l0), so a few may sit further
                dev = np.abs(vb - va).max(axis=1)
                off = dev > 3e-4 * L0
                if stage == "surface" and f == 0:
                    # frame 0 is an axis-aligned block: its top face meets the side walls at a right
                    # angle, so whether a vertex of that edge passes wall_snap's contact test (surface
                    # normal . wall normal < 0) is decided by rounding, in any units
                    assert off.mean() < 0.02
                else:
                    assert off.mean() < 0.005 and dev.max() < 0.01 * L0, (off.sum(), dev.max() / L0)

    # the surface's volume is the water's (no Phi ~ 1e-6 of an empty grid)
    water = np.prod(np.subtract(WATER[1], WATER[0]))
    sb = load_surface(run["surface"], 0)
    assert signed_volume(to_metres_z_up(sb.vertices, mpu, up), sb.faces) == pytest.approx(water, rel=0.1)

    # wall_snap: the contact region (raw vertices within l0/4 of a wall) ends on the exact walls, to the
    # same fraction of l0 (float32 rounding) in every unit, and as many vertices end on the walls
    found = []
    for r, m in ((ref, 1.0), (run, mpu)):
        walls = WallMesh.load(r["walls"])
        raw, snapped = snapped_like_raw(r, LAST)
        used = np.unique(snapped.faces)

        def gap(v):
            v = v[used].astype(np.float64)
            return np.linalg.norm(closest_points_on(walls, v) - v, axis=1) * m / L0

        contact, after = gap(raw.vertices) < 0.25, gap(snapped.vertices)
        assert contact.sum() > 100 and after[contact].max() < 1e-5
        found.append((contact.sum(), (after < 1e-3).sum()))
    np.testing.assert_allclose(found[1], found[0], rtol=0.01)

    # render: the same picture (the automatic camera frames the walls in any units and up axis)
    import imageio.v3 as iio

    pa = iio.imread(ref["frames"] / f"frame_{LAST:05d}.png").astype(np.float64)
    pb = iio.imread(run["frames"] / f"frame_{LAST:05d}.png").astype(np.float64)
    water_px = (pa[..., 2] > pa[..., 0] + 40).sum()
    assert water_px > 200  # the water is in the picture
    diff = np.abs(pa - pb).max(axis=-1)
    assert (diff > 40).mean() < 0.01 and diff.mean() < 2.0  # measured: identical Z-up; Y-up 0.5 %, 0.6


def test_a_centimetre_y_up_studio_set_comes_back_in_centimetres_y_up(runs):
    """The millimetre Z-up scene's tank came from a cm Y-up USD set: export writes every layer in the
    set's own frame, where the fluid is the metre scene's fluid times 100, turned to Y-up."""
    ref, run = runs[(1.0, "Z")], runs[STUDIO]
    stage = Usd.Stage.Open(str(run["usd"] / "scene.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    box = cache.ComputeWorldBound(stage.GetPrimAtPath("/Set/Props/Tank")).ComputeAlignedRange()
    np.testing.assert_allclose([box.GetMin(), box.GetMax()], [[-5, 0, -4], [5, 10, 4]], atol=1e-4)

    camera = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    assert camera.GetHorizontalApertureAttr().Get() == pytest.approx(36.0)  # tenths of a cm: a 36 mm film back
    assert camera.GetCamera(0).GetFieldOfView(Gf.Camera.FOVVertical) == pytest.approx(30.0)

    surface = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Fluid/Surface"))
    for f in (0, LAST):
        pts = np.array(surface.GetPointsAttr().Get(f), np.float64)
        faces = np.array(surface.GetFaceVertexIndicesAttr().Get(f)).reshape(-1, 3)
        expected = load_surface(ref["surface"], f)
        if f == LAST:  # (frame 0: see the axis-aligned contact above)
            np.testing.assert_allclose(pts, z_to_y(expected.vertices) * 100, atol=1e-3 * L0 * 100)
        assert signed_volume(pts, faces) == pytest.approx(signed_volume(
            expected.vertices.astype(np.float64), expected.faces) * 1e6, rel=0.01)  # cm^3

    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    a = load_particle_frame(ref["particles"], LAST)  # the same emitter order: the same ids
    ids = np.array(points.GetIdsAttr().Get(LAST))
    order = np.argsort(ids)[np.argsort(np.argsort(a.id))]
    x = np.array(points.GetPointsAttr().Get(LAST), np.float64)[order]
    v = np.array(points.GetVelocitiesAttr().Get(LAST), np.float64)[order]
    np.testing.assert_allclose(x, z_to_y(a.x) * 100, atol=1e-3 * L0 * 100)  # cm
    np.testing.assert_allclose(v, z_to_y(a.v) * 100, atol=50e-3 * L0 * 100)  # cm/s
    np.testing.assert_allclose(np.array(points.GetWidthsAttr().Get(LAST)), L0 * 100, rtol=1e-6)  # diameters, cm


FAR = np.array([1e5, 2e5, 50.0])  # a survey or CAD scene's coordinates, metres


@pytest.fixture(scope="module")
def far(tmp_path_factory):
    return run_pipeline(tmp_path_factory.mktemp("far"), 1.0, "Z", FAR)


def test_a_scene_far_from_the_origin_comes_out_as_at_the_origin(runs, far):
    """1e5 m out, float32's step is 8 mm (0.8 l0 here): the particle frames, the surfaces and USD's point3f
    stored there quantised the particles by up to 0.4 l0, bent the surface (-12 % volume), put snapped vertices
    0.16 l0 outside the walls and stacked half the USD's particles on each other. Positions are now kept in
    float64 where float32 would lose 1e-4 l0, and USD points are written about a local origin under a
    double-precision translate: everything agrees with the scene at the origin, moved."""
    from stages.common.formats import position_dtype

    ref = runs[(1.0, "Z")]
    for f in (0, LAST):
        a, b = load_particle_frame(ref["particles"], f), load_particle_frame(far["particles"], f)
        assert b.x.dtype == np.float64 and a.x.dtype == np.float32  # only where float32 would lose digits
        np.testing.assert_array_equal(a.id, b.id)
        np.testing.assert_allclose(b.x - FAR, a.x, atol=1e-3 * L0)
        for stage in ("raw", "surface"):
            sa, sb = load_surface(ref[stage], f), load_surface(far[stage], f)
            assert len(sb.vertices) == len(sa.vertices) and len(sa.faces) > 500
            vb = sb.vertices.astype(np.float64) - FAR
            np.testing.assert_allclose(vb, sa.vertices, atol=1e-3 * L0)
            assert signed_volume(vb, sb.faces) == pytest.approx(signed_volume(sa.vertices.astype(np.float64), sa.faces),
                                                                 rel=1e-3)
    walls = WallMesh.load(far["walls"])
    raw, snapped = snapped_like_raw(far, LAST)
    used = np.unique(snapped.faces)
    gap = lambda v: np.linalg.norm(closest_points_on(walls, v[used]) - v[used], axis=1) / L0  # noqa: E731
    contact = gap(raw.vertices.astype(np.float64)) < 0.25
    assert contact.sum() > 100 and gap(snapped.vertices.astype(np.float64))[contact].max() < 1e-4

    # USD: every point where the npz has it, in world space (points + the prim's translate)
    stage = Usd.Stage.Open(str(far["usd"] / "scene.usda"))
    cache = UsdGeom.XformCache(Usd.TimeCode(LAST))

    def world(path):
        prim = stage.GetPrimAtPath(path)
        m = np.array(cache.GetLocalToWorldTransform(prim), np.float64)
        pts = np.array(UsdGeom.PointBased(prim).GetPointsAttr().Get(Usd.TimeCode(LAST)), np.float64)
        return pts @ m[:3, :3] + m[3, :3]

    np.testing.assert_allclose(world("/World/Fluid/Surface"), load_surface(far["surface"], LAST).vertices,
                               atol=1e-3 * L0)
    np.testing.assert_allclose(world("/World/Particles"), load_particle_frame(far["particles"], LAST).x,
                               atol=1e-3 * L0)
    tank = world(next(str(p.GetPath()) for p in stage.Traverse() if str(p.GetPath()).startswith("/World/Walls/")
                      and p.IsA(UsdGeom.Mesh)))
    np.testing.assert_allclose(tank.min(axis=0), FAR - [0.05, 0.04, 0.0], atol=1e-3 * L0)
    assert position_dtype(tank, L0) is np.float64  # (the check above is not float32's luck)

    # the picture: the same frame as at the origin (the surface was faceted there, 5-6 % of the pixels off)
    import imageio.v3 as iio

    pa = iio.imread(ref["frames"] / f"frame_{LAST:05d}.png").astype(np.float64)
    pb = iio.imread(far["frames"] / f"frame_{LAST:05d}.png").astype(np.float64)
    diff = np.abs(pa - pb).max(axis=-1)
    assert (diff > 40).mean() < 0.005 and diff.mean() < 1.0, ((diff > 40).mean(), diff.mean())
