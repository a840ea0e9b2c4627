"""Open and single-sided walls (shells) and thin walls: no leak through the trilinear SDF grid, water
held by an open bowl, a single-sided USD trough in centimetres and a tilted sheet, and a 10 m/s jet
against a wall 0.2 l0 thick and against a shell of the default thickness (issue 16)."""
from __future__ import annotations

import logging
from pathlib import Path

import numba as nb
import numpy as np
import pytest
import trimesh
import yaml

import pipeline
from conftest import no_wall_terms
from pipeline import Registry
from stages.common.formats import ParticleMeta, WallMesh, load_particle_frame
from stages.common.sdf import DEFAULT_SHELL_THICKNESS, SHELL_R_REP, SHELL_STEP, SDFGrid, min_shell_thickness
from stages.simulate.walls.maps import push_out
from stages.wall_snap.distance import DistanceSnapParams


# -- the bound: a particle left at d >= r_rep and moved by one step never ends across the wall ------
@nb.njit(cache=True)
def _step_and_push(p, step, walls, r_rep, out):
    for i in range(p.shape[0]):
        x, y, z, _, _, _ = push_out(walls, None, -1, p[i, 0] + step[i, 0], p[i, 1] + step[i, 1], p[i, 2] + step[i, 2],
                                    0.0, 0.0, 0.0, r_rep, 0.5, True)
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z


def _crossings(thickness: float, step: float, cell: float = 0.5, seed: int = 1) -> int:
    """Particles (l0 = 1) that end on the far side of a planar shell |d| - thickness/2 baked on a grid
    of ``cell``: each starts on one side where the eq. 16 push-out leaves it (d = r_rep, after a push),
    then moves ``step`` straight at the wall (the worst direction) and is pushed out again. Planes: along
    an axis, the diagonal, (1, 2, 0) and six random normals, each at 16 offsets across a cell, from
    both sides."""
    rng = np.random.default_rng(seed)
    k = int(round(4.0 / cell)) + 1
    axis = -2.0 + cell * np.arange(k)
    nodes = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    normals = [np.array([0.0, 0.0, 1.0]), np.ones(3), np.array([1.0, 2.0, 0.0])] + list(rng.normal(size=(6, 3)))
    crossed = 0
    for n in normals:
        n = n / np.linalg.norm(n)
        for s in (np.arange(16) + 0.5) * cell / 16:
            grid = SDFGrid(np.full(3, -2.0), cell, (np.abs(nodes @ n - s) - thickness / 2).reshape(k, k, k).astype(np.float32), 10.0)
            for side in (-1.0, 1.0):
                p = rng.uniform(-0.8, 0.8, (300, 3))
                p += ((s + side * (SHELL_R_REP + thickness / 2 + 0.3)) - p @ n)[:, None] * n
                settled = np.empty_like(p)
                walls = no_wall_terms(grid, 2.0)
                _step_and_push(p, np.tile(-side * 0.3 * n, (len(p), 1)), walls, SHELL_R_REP, settled)
                moved = np.empty_like(p)
                _step_and_push(settled, np.tile(-side * step * n, (len(p), 1)), walls, SHELL_R_REP, moved)
                crossed += int(np.sum(np.sign(settled @ n - s) != side) + np.sum(np.sign(moved @ n - s) != side))
    return crossed


def test_least_shell_thickness_is_leak_free_and_tight():
    """At the default cell (0.5 l0) and r_rep 0.5 l0, a shell of min_shell_thickness (0.55 l0) is never
    crossed by a particle stepping SHELL_STEP (0.525 l0: CFL 0.4 + the force limit's 0.125), nor is the
    default thickness; a thinner shell is (the bound is tight), and at CFL 0.4 alone 0.3 l0 suffices."""
    t_min = min_shell_thickness(0.5)
    assert t_min == pytest.approx(0.55) and DEFAULT_SHELL_THICKNESS >= t_min
    assert _crossings(t_min, SHELL_STEP) == 0
    assert _crossings(DEFAULT_SHELL_THICKNESS, SHELL_STEP) == 0
    assert _crossings(t_min - 0.1, SHELL_STEP) > 0
    assert _crossings(min_shell_thickness(0.5, step=0.4), 0.4) == 0
    assert _crossings(0.2, 0.4) > 0


# -- scenes --------------------------------------------------------------------------------------
def _run(tmp: Path, cfg: dict, outputs=("walls", "particles"), sets: tuple[str, ...] = ()) -> tuple[WallMesh, list, dict]:
    """Run the scene ``cfg`` (WCSPH) into ``tmp``: its walls, particle frames and simulate stats."""
    cfg = {"config_version": 1, "stages": {"simulate": {"use": "sph"}}, "outputs": list(outputs), **cfg}
    (tmp / "scene.yaml").write_text(yaml.safe_dump(cfg))
    report = pipeline.run(tmp / "scene.yaml", registry=Registry.from_entry_points(), cache_dir=tmp / "cache",
                          out_dir=tmp / "out", overrides=sets)
    folder = Path(report.outputs["particles"])
    meta = ParticleMeta.load(folder)
    frames = [load_particle_frame(folder, f) for f in range(meta.frame_count)]
    return WallMesh.load(Path(report.outputs["walls"])), frames, meta.stats


def test_water_poured_into_an_open_bowl_stays_in_it(tmp_path):
    """An open hemispherical bowl (boundary edges at its rim, so a shell by the automatic choice): the
    water poured from above its rim fills it instead of landing on a lid at the rim's height."""
    radius, centre = 0.2, np.array([0.0, 0.0, 0.25])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    trimesh.Trimesh(sphere.vertices + centre, sphere.faces[sphere.triangles_center[:, 2] < 0]).export(tmp_path / "bowl.obj")
    walls, frames, _ = _run(tmp_path, {
        "scene": {"name": "bowl", "frames": {"fps": 10, "count": 13}},
        "walls": [{"builtin": "box_tank", "size": [0.6, 0.6, 0.5]}, {"file": "bowl.obj"}],
        "fluid": {"spacing": 0.02, "emitters": [{"box": {"min": [-0.12, -0.12, 0.26], "max": [0.12, 0.12, 0.30]}}]},
        "effects": {"gravity": {"g": 9.81}, "viscosity": {"mu": 0.001}}})
    assert walls.walls[1]["fluid"] == "both" and walls.walls[1]["shell"] == pytest.approx(DEFAULT_SHELL_THICKNESS * 0.02)
    assert len(frames[0]) > 250
    in_bowl = [np.mean((np.linalg.norm(f.x - centre, axis=1) < radius) & (f.x[:, 2] < centre[2])) for f in frames]
    assert in_bowl[0] == 0 and in_bowl[-1] >= 0.95, in_bowl


# a single-sided trough, open at the top: floor, two slanted and two upright sides (quads) and two
# hexagonal ends (n-gons); centimetres, local frame Y-up, under two nested transforms
TROUGH_SECTION = [(-10, 0), (10, 0), (15, 10), (15, 20), (-15, 20), (-15, 10)]  # (x, y) cm, an end's outline
TROUGH_LENGTH = 60.0


def write_trough_usda(path: Path) -> np.ndarray:
    """The trough as a .usda (metersPerUnit 0.01, Y-up); returns the 4x4 local-to-world matrix."""
    from pxr import Gf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    outer = UsdGeom.Xform.Define(stage, "/Set")
    outer.AddTranslateOp().Set(Gf.Vec3d(5.0, 0.0, -4.0))
    inner = UsdGeom.Xform.Define(stage, "/Set/Props")
    inner.AddRotateYOp().Set(90.0)
    inner.AddScaleOp().Set(Gf.Vec3f(1.0, 1.0, 1.0))
    mesh = UsdGeom.Mesh.Define(stage, "/Set/Props/Trough")
    mesh.AddTranslateOp().Set(Gf.Vec3d(0.0, 2.0, 0.0))
    n = len(TROUGH_SECTION)
    z0, z1 = -TROUGH_LENGTH / 2, TROUGH_LENGTH / 2
    pts = [(x, y, z0) for x, y in TROUGH_SECTION] + [(x, y, z1) for x, y in TROUGH_SECTION]
    sides = [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n) if i != 3]  # edge 3-4 is the open top
    faces = sides + [tuple(range(n))[::-1], tuple(range(n, 2 * n))]
    mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*p) for p in pts]))
    mesh.CreateFaceVertexCountsAttr([len(f) for f in faces])
    mesh.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    stage.GetRootLayer().Save()
    return np.asarray(UsdGeom.Xformable(mesh.GetPrim()).ComputeLocalToWorldTransform(Usd.TimeCode.Default()),
                      np.float64)


def test_water_poured_into_a_single_sided_usd_trough_in_centimetres_stays_in_it(tmp_path):
    """The trough's faces have no thickness and no inside: a shell. Poured from above, >= 95 % of the
    water is in the trough when it settles (a scene in centimetres, Y-up, like the asset)."""
    to_world = write_trough_usda(tmp_path / "trough.usda")
    walls, frames, stats = _run(tmp_path, {
        "scene": {"name": "trough", "units": {"meters_per_unit": 0.01, "up_axis": "Y"}, "frames": {"fps": 10, "count": 9}},
        "walls": [{"builtin": "box_tank", "size": [80, 40, 60], "center": [5, 0, -4]}, {"usd": "trough.usda"}],
        "fluid": {"spacing": 2.0, "emitters": [{"box": {"min": [-18, 25, -14], "max": [28, 29, 6]}}]},
        "effects": {"gravity": {"g": 9.81}, "viscosity": {"mu": 0.001}}})
    assert walls.walls[1]["fluid"] == "both" and walls.walls[1]["report"]["boundary_edges"] > 0
    # the trough's inside: the convex hull of its outline (the section prism), in the scene's frame
    local = np.array([(x, y, z) for z in (-TROUGH_LENGTH / 2, TROUGH_LENGTH / 2) for x, y in TROUGH_SECTION], float)
    world = local @ to_world[:3, :3] + to_world[3, :3]  # USD matrices act on row vectors
    trough = walls.vertices[np.unique(walls.faces[walls.wall_id == 1])]
    assert np.allclose(trough.min(axis=0), world.min(axis=0), atol=1e-4) and np.allclose(trough.max(axis=0), world.max(axis=0), atol=1e-4)
    from scipy.spatial import Delaunay

    hull = Delaunay(world)
    inside = [np.mean(hull.find_simplex(f.x) >= 0) for f in frames]
    assert len(frames[0]) > 250 and inside[0] == 0
    assert inside[-1] >= 0.95, inside
    assert stats["left_domain"] == 0


def _sheet(path: Path, centre, normal, size: float, n: int = 6) -> None:
    """A single plane of triangles (n x n quads, two triangles each) through ``centre`` across ``normal``."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 1.0, 0.0] if abs(normal[1]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    a = np.linspace(-size / 2, size / 2, n + 1)
    A, B = np.meshgrid(a, a, indexing="ij")
    v = np.asarray(centre, float) + A.reshape(-1, 1) * u + B.reshape(-1, 1) * w
    q = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    faces = np.concatenate([np.stack([q, q + n + 1, q + n + 2], 1), np.stack([q, q + n + 2, q + 1], 1)])
    trimesh.Trimesh(v, faces, process=False).export(path)


def test_a_sheet_tilted_30_degrees_stops_a_falling_block(tmp_path):
    """A single sheet of triangles tilted 30 degrees, larger than the tank (it splits it in two): a block
    of water falling onto it slides down it; no particle is ever below it."""
    c, n = np.array([0.0, 0.0, 0.18]), np.array([0.0, -np.sin(np.radians(30)), np.cos(np.radians(30))])
    _sheet(tmp_path / "sheet.obj", c, n, 1.0)
    walls, frames, stats = _run(tmp_path, {
        "scene": {"name": "sheet", "frames": {"fps": 20, "count": 9}},
        "walls": [{"builtin": "box_tank", "size": [0.3, 0.4, 0.5]}, {"file": "sheet.obj"}],
        "fluid": {"spacing": 0.02, "emitters": [{"box": {"min": [-0.06, -0.06, 0.3], "max": [0.06, 0.06, 0.4]}}]},
        "effects": {"gravity": {"g": 9.81}, "viscosity": {"mu": 0.001}}})
    assert walls.walls[1]["fluid"] == "both"
    side = [(f.x - c) @ n for f in frames]
    assert len(frames[0]) > 150
    assert min(s.min() for s in side) > 0  # nothing ever below the sheet
    assert np.median(side[-1]) < 0.05 < side[0].min()  # the block came down onto it
    assert frames[-1].x[:, 1].mean() < frames[0].x[:, 1].mean() - 0.03  # and slid down its slope (-y)
    assert stats["left_domain"] == 0


@pytest.mark.parametrize("solver", ["sph", "dfsph", "mps"])
@pytest.mark.parametrize("wall", ["thin_solid", "shell"])
def test_a_10_m_s_jet_does_not_cross_a_thin_wall(wall, solver, tmp_path):
    """A wall across the whole tank at x = 0.25 (so nothing can go round it): a closed, watertight slab
    0.2 l0 thick (sdf_bake thickens it to the least leak-free thickness) or a single sheet (a shell of
    the default thickness). A 10 m/s jet hits it; no particle is ever beyond it, with every solver at
    its default settings (DFSPH steps up to 0.8 l0 and pushes out to 0.2 l0 only: its moves near walls
    are sub-stepped to sdf.wall_move_limit)."""
    l0, x_wall = 0.01, 0.2523  # 0.23 l0 past a grid node: where a thin wall's trilinear field is worst
    if wall == "thin_solid":
        slab = trimesh.creation.box(extents=[0.2 * l0, 0.5, 0.5])
        slab.apply_translation([x_wall, 0.1, 0.1])
        slab.export(tmp_path / "wall.obj")
    else:
        _sheet(tmp_path / "wall.obj", [x_wall, 0.1, 0.1], [1.0, 0.0, 0.0], 0.5, n=3)
    walls, frames, stats = _run(tmp_path, {
        "scene": {"name": "jet", "frames": {"fps": 200, "count": 9}},
        "walls": [{"builtin": "box_tank", "size": [0.4, 0.2, 0.2], "center": [0.2, 0.1, 0.0]}, {"file": "wall.obj"}],
        "fluid": {"spacing": l0, "emitters": [{"box": {"min": [0.08, 0.07, 0.07], "max": [0.18, 0.13, 0.13]},
                                               "velocity": [10.0, 0.0, 0.0]}]},
        "effects": {"gravity": {"g": 9.81}, "viscosity": {"mu": 0.001}}}, sets=(f"simulate.use={solver}",))
    assert walls.walls[1]["fluid"] == ("outside" if wall == "thin_solid" else "both")
    assert len(frames[0]) > 300
    assert max(f.x[:, 0].max() for f in frames) < x_wall
    assert frames[3].x[:, 0].max() > x_wall - 0.02  # the jet reached the wall
    assert stats["left_domain"] == 0


def test_wall_snap_puts_the_surface_on_the_face_of_a_shell_the_fluid_touches():
    """A drop resting on a horizontal sheet (a shell): its contact vertices end on the shell's upper
    face, thickness/2 above the mesh, not on the mesh inside the shell; from below, on the lower face."""
    from stages.common.formats import SurfaceMesh
    from stages.sdf_bake.open3d_bake import bake
    from stages.wall_snap.distance import snap_mesh

    l0, z_sheet = 0.02, 0.1
    t = DEFAULT_SHELL_THICKNESS * l0
    sheet = trimesh.creation.box(extents=[0.4, 0.4, 1e-9])  # its top face: a single plane of two triangles
    top = sheet.faces[sheet.triangles_center[:, 2] > 0]
    walls = WallMesh(np.asarray(sheet.vertices) + [0, 0, z_sheet], np.asarray(top, np.int32), np.zeros(len(top), np.int32),
                     [{"name": "sheet", "fluid": "both", "shell": t, "report": {"watertight": False}}])
    grid, _ = bake(walls, np.array([-0.25, -0.25, -0.1]), np.array([0.25, 0.25, 0.3]), 0.5 * l0, 4 * l0)
    for side in (1.0, -1.0):
        drop = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
        drop.apply_translation([0.0, 0.0, z_sheet + side * (t / 2 + 0.05 + 0.3 * l0)])
        mesh = SurfaceMesh(np.asarray(drop.vertices, np.float32), np.asarray(drop.faces, np.int32),
                           np.asarray(drop.vertex_normals, np.float32))
        snapped, report = snap_mesh(mesh, grid, l0, DistanceSnapParams(), walls)
        z = snapped.vertices[:, 2].astype(np.float64) - z_sheet
        contact = np.abs(z - side * t / 2) < 0.05 * l0
        assert contact.sum() >= 10 and report["snapped"] >= contact.sum()
        assert np.abs(z[contact] - side * t / 2).max() < 1e-3 * l0
        assert (side * z).min() > t / 2 - 1e-3 * l0  # nothing inside the shell


def test_a_wall_is_a_solid_or_a_shell_not_both(tmp_path):
    from pipeline.config import ConfigError, load_config

    (tmp_path / "c.yaml").write_text(yaml.safe_dump({
        "config_version": 1, "scene": {"name": "x"}, "fluid": {"spacing": 0.1, "emitters": [{"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}]},
        "walls": [{"file": "bowl.obj", "fluid": "inside", "shell": {"thickness": 0.01}}], "outputs": ["sdf"]}))
    with pytest.raises(ConfigError, match="either a solid"):
        load_config(tmp_path / "c.yaml", Registry.from_entry_points())


@pytest.mark.parametrize("cap, expected", [(0.9999, "outside"), (0.6, "both")])
def test_a_mesh_with_small_holes_stays_a_solid_and_one_with_an_opening_becomes_a_shell(cap, expected, tmp_path, caplog):
    """The automatic choice: a sphere (radius 0.2, l0 0.02) with a scan hole at its top narrower than
    2 l0 (the faces round its pole, 1.9 l0 wide) is closed but messy, a solid with its inside/outside;
    with a cap cut off (an opening 23 l0 wide) it is an open vessel, a shell. The log says which and why."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
    keep = sphere.vertices[sphere.faces].max(axis=1)[:, 2] < cap * 0.2
    trimesh.Trimesh(sphere.vertices + [0, 0, 0.25], sphere.faces[keep]).export(tmp_path / "vessel.obj")
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump({
        "config_version": 1, "scene": {"name": "vessel", "frames": {"fps": 10, "count": 1}},
        "walls": [{"builtin": "box_tank", "size": [0.6, 0.6, 0.6]}, {"file": "vessel.obj"}],
        "fluid": {"spacing": 0.02, "emitters": [{"box": {"min": [-0.25, -0.25, 0.0], "max": [-0.21, -0.21, 0.04]}}]},
        "outputs": ["walls"]}))
    with caplog.at_level(logging.INFO, logger="stage.mesh_import.trimesh"):
        report = pipeline.run(tmp_path / "scene.yaml", registry=Registry.from_entry_points(), cache_dir=tmp_path / "cache",
                              out_dir=tmp_path / "out")
    walls = WallMesh.load(Path(report.outputs["walls"]))
    assert walls.walls[1]["report"]["boundary_edges"] > 0
    assert walls.walls[1]["fluid"] == expected, walls.walls[1]["report"]["largest_hole"]
    edges = walls.walls[1]["report"]["boundary_edges"]
    why = (f"wall 1 (vessel): closed but for small holes ({edges} boundary edges, widest" if expected == "outside"
           else f"wall 1 (vessel): open mesh ({edges} boundary edges) -> shell 0.012 (0.6 l0) thick; set fluid: inside/outside")
    assert why in caplog.text, caplog.text


@pytest.mark.parametrize("solver", ["sph", "dfsph"])
def test_a_10_m_s_jet_does_not_cross_the_wall_of_a_cup_0_2_l0_thick(solver, tmp_path):
    """Issue 16's cup: a closed, watertight cup (a revolved profile, radius 6 l0, side and floor 0.2 l0
    thick) on the tank floor with its rim against the tank's lid, so its inside is sealed (the
    jet's splash reaches the lid within 0.03 s); a 10 m/s jet hits its curved side from outside. No
    particle is ever inside the cup."""
    l0, r_in, lift, tank_h = 0.01, 0.06, 0.0, 0.32
    r_out, axis = r_in + 0.2 * l0, np.array([0.28, 0.0])
    profile = np.array([[0, lift], [r_out, lift], [r_out, tank_h], [r_in, tank_h],
                        [r_in, lift + 0.2 * l0], [0, lift + 0.2 * l0], [0, lift]])  # (r, z), counter-clockwise
    cup = trimesh.creation.revolve(profile, sections=64)
    assert cup.is_watertight and cup.volume > 0
    cup.apply_translation([axis[0], axis[1], 0.0])
    cup.export(tmp_path / "cup.obj")
    walls, frames, stats = _run(tmp_path, {
        "scene": {"name": "cup", "frames": {"fps": 200, "count": 7}},
        "walls": [{"builtin": "box_tank", "size": [0.4, 0.24, tank_h], "center": [0.2, 0.0, 0.0]}, {"file": "cup.obj"}],
        "fluid": {"spacing": l0, "emitters": [{"box": {"min": [0.08, -0.03, 0.04], "max": [0.18, 0.03, 0.10]},
                                               "velocity": [10.0, 0.0, 0.0]}]},
        "effects": {"gravity": {"g": 9.81}, "viscosity": {"mu": 0.001}}}, sets=(f"simulate.use={solver}",))
    assert walls.walls[1]["fluid"] == "outside" and walls.walls[1]["report"]["watertight"]
    assert len(frames[0]) > 300
    gap = [np.linalg.norm(f.x[:, :2] - axis, axis=1) for f in frames]  # distance from the cup's axis
    assert min(g.min() for g in gap) > r_out, [g.min() for g in gap]  # nobody inside the cup's side
    assert min(g.min() for g in gap[2:]) < r_out + 1.5 * l0  # the jet reached the cup
    assert stats["left_domain"] == 0


def _tank_and_rock_obj(path: Path, k: float, up: str) -> None:
    """One OBJ of two objects, as a set exports them: an open tank of 5 quads (1 x 1 x 0.6 m, no lid) and a
    closed rock (a 0.3 m cube on its floor), ``k`` file units a metre, ``up`` its up axis."""
    tank = np.array([[x, y, z] for z in (0, 0.6) for x, y in ((-.5, -.5), (.5, -.5), (.5, .5), (-.5, .5))])
    quads = [[1, 4, 3, 2], [1, 2, 6, 5], [2, 3, 7, 6], [3, 4, 8, 7], [4, 1, 5, 8]]
    rock = trimesh.creation.box(extents=[0.3, 0.3, 0.3]).apply_translation([0, 0, 0.15])
    to_file = (lambda v: v) if up == "Z" else (lambda v: v[:, [0, 2, 1]] * [1, 1, -1])
    lines = ["o Tank"] + [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in to_file(tank * k)]
    lines += [f"f {' '.join(map(str, q))}" for q in quads] + ["o Rock"]
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in to_file(rock.vertices * k)]
    lines += [f"f {' '.join(str(i + 9) for i in f)}" for f in rock.faces]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("mpu, up, config", [(1.0, "Z", {}), (0.01, "Y", {}), (0.001, "Z", {}),
                                             (1.0, "Z", {"motion": {"keyframes": [{"time": 0.0}, {"time": 1.0}]}}),
                                             (1.0, "Z", {"shell": {"thickness": 0.06}}), (1.0, "Z", {"fluid": "outside"})])
def test_a_closed_rock_in_the_file_of_an_open_tank_stays_solid(mpu, up, config, tmp_path, caplog):
    """An open tank and a closed rock in one wall file: the wall was one open mesh (4 boundary edges), all a
    shell, so the rock was hollow and an emitter over the tank filled it (16 particles). Chosen per part now:
    the tank a shell, the rock a solid (its middle 0.15 m deep in it), said per part; in cm Y-up and mm as in m,
    and for a moving wall. A config's shell: or fluid: is the whole wall's (the rock hollow in an explicit shell)."""
    from stages.common.sdf import load_bodies, posed_field

    k = 1.0 / mpu
    _tank_and_rock_obj(tmp_path / "tank_rock.obj", k, up)
    config = {key: ({"thickness": 0.06 * k} if key == "shell" else v) for key, v in config.items()}
    z = (lambda p: np.asarray(p, float)) if up == "Z" else (lambda p: np.asarray(p, float)[..., [0, 2, 1]] * [1, 1, -1])
    box = z([-.4, -.4, .05]), z([.4, .4, .55])  # an emitter over the tank
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump({
        "config_version": 1, "scene": {"name": "rock", "units": {"meters_per_unit": mpu, "up_axis": up},
                                       "frames": {"fps": 10, "count": 1}},
        "walls": [{"file": "tank_rock.obj", **config}],
        "fluid": {"spacing": 0.1 * k, "emitters": [{"box": {"min": (np.minimum(*box) * k).tolist(),
                                                            "max": (np.maximum(*box) * k).tolist()}}]},
        "outputs": ["sdf"]}))
    with caplog.at_level(logging.INFO):
        report = pipeline.run(tmp_path / "scene.yaml", registry=Registry.from_entry_points(),
                              cache_dir=tmp_path / "cache", out_dir=tmp_path / "out")
    folder = Path(report.outputs["sdf"])
    grid = posed_field(SDFGrid.load(folder), load_bodies(folder), 0.0)
    probes = z([[0.08, 0, 0.15],  # in the rock, 0.07 m from its nearest face
                [0.1, 0.05, 0.2],  # in the rock, 0.05 m from its nearest face
                [0.3, 0.3, 0.45],  # the tank's water, above the rock's side
                [0.49, 0.0, 0.3]]) * k  # by the tank's side: in the shell
    d = grid.sample(probes)[0] / k
    if "shell" in config:  # the config's shell is the whole wall's: the rock is a shell too
        assert d[0] == pytest.approx(0.07 - 0.03, abs=2e-3) and d[3] < 0, d
        assert "1 closed part" not in caplog.text
        return
    if "fluid" in config:  # a solid, as said: the open tank's inside too (closed as by a lid)
        assert "1 closed part" not in caplog.text and d[2] < 0, d
        return
    assert d[0] == pytest.approx(-0.07, abs=2e-3), d  # solid, its exact depth (was +0.04: a hollow shell)
    assert d[1] < -0.03 and d[2] > 0.1 and d[3] < 0, d
    assert f"wall 0 (tank_rock): 1 open part (4 boundary edges) -> shell {0.06 * k:.4g} (0.6 l0) thick" in caplog.text, \
        caplog.text
    assert ", 1 closed part -> solid, fluid outside" in caplog.text, caplog.text
    # wall_snap puts the surface on the rock's faces, not half a shell's thickness off them (and on the tank's
    # shell face as before)
    from stages.common.formats import WallMesh
    from stages.wall_snap.distance import WallProjector

    walls = WallMesh.load(Path(report.outputs["walls"]) if "walls" in report.outputs else
                          next((tmp_path / "cache" / "mesh_import").glob("*/*/walls.json")).parent)
    near = WallProjector(walls.posed(0.0), SDFGrid.load(folder).shell_thickness)(
        z([[0.2, 0.0, 0.15], [0.35, 0.0, 0.1]]) * k)[0] / k
    np.testing.assert_allclose(near[0], z([0.15, 0.0, 0.15]), atol=1e-9)  # the rock's face at x = 0.15
    np.testing.assert_allclose(near[1], z([0.35, 0.0, 0.03]), atol=1e-9)  # the tank floor's shell face, 0.03 up
