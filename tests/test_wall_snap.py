"""wall_snap.distance: fluid surfaces end on the exact walls (flat tank walls, a concave cylinder and a
convex sphere), with no triangle flipped and the surface still closed."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.testing import run_stage
from stages.common.formats import SurfaceMesh, WallMesh, load_surface
from stages.common.meshes import boundary_edge_count, face_normals, signed_volume, tidy, vertex_normals
from stages.common.sdf import SDFGrid, box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.surface_extract.marching_cubes import MarchingCubes
from stages.wall_snap.distance import DistanceSnap, DistanceSnapParams, closest_points_on, snap_mesh

from test_surface_extract import L0, SCENE, particles

LO, HI = np.zeros(3), np.array([0.2, 0.2, 0.2])


def save_walls(folder, *meshes):
    """Trimesh meshes as one wall mesh (the exact geometry the SDF stands for)."""
    import trimesh

    folder.mkdir()
    m = trimesh.util.concatenate(list(meshes))
    wall_id = np.concatenate([np.full(len(x.faces), i, np.int32) for i, x in enumerate(meshes)])
    WallMesh(np.asarray(m.vertices), np.asarray(m.faces, np.int32), wall_id,
             [{"name": f"wall{i}", "fluid": "inside"} for i in range(len(meshes))]).save(folder)
    return folder


def tank_walls(folder):
    import trimesh

    box = trimesh.creation.box(bounds=[LO, HI])
    box.invert()  # a container: normals into the fluid
    return save_walls(folder, box)


def assert_on_the_walls(raw: SurfaceMesh, snapped: SurfaceMesh, report: dict, walls: WallMesh, band: np.ndarray,
                        inside_fluid, facets: float) -> None:
    """Every ``band`` vertex within 1e-3 l0 of the exact wall mesh, none inside a wall, no triangle
    flipped against the raw one it comes from, closed if the raw surface was, the rest unmoved."""
    v0, v1 = raw.vertices.astype(np.float64), snapped.vertices.astype(np.float64)
    gap = np.linalg.norm(closest_points_on(walls, v1) - v1, axis=1)
    assert gap[band].max() < 1e-3 * L0
    # nothing inside a wall (judged by the analytic distance; ``facets``: how far the wall mesh's flat
    # facets lie off the analytic wall, where the raw contact line already sits)
    assert inside_fluid(v1).min() > -facets
    kept = report["kept_faces"]
    assert len(kept) == len(snapped.faces) and len(kept) >= len(raw.faces) - 2 * report["collapsed"]
    flips = np.einsum("ij,ij->i", face_normals(v0, raw.faces[kept]), face_normals(v1, snapped.faces)) < 0
    assert not flips.any()
    assert boundary_edge_count(raw.faces) == 0 and boundary_edge_count(snapped.faces) == 0
    d0 = np.linalg.norm(closest_points_on(walls, v0) - v0, axis=1)
    far = d0 > 1.5 * L0
    assert np.allclose(v0[far], v1[far])


def assert_tidy(mesh: SurfaceMesh) -> None:
    """No unreferenced vertex, no triangle of zero area, no zero normal (what wall_snap published)."""
    used = np.zeros(len(mesh.vertices), np.bool_)
    used[mesh.faces.ravel()] = True
    assert used.all()
    v = mesh.vertices.astype(np.float64)
    p = v[mesh.faces]
    longest = np.max([np.linalg.norm(p[:, k] - p[:, (k + 1) % 3], axis=1) for k in range(3)], axis=0)
    height = np.linalg.norm(face_normals(v, mesh.faces), axis=1) / longest
    assert (height > 1e-5 * longest).all()
    assert (np.linalg.norm(mesh.normals, axis=1) > 0.99).all()


def test_tidy_takes_out_slivers_pillows_and_stray_vertices_and_keeps_the_surface():
    """wall_snap left, where vertices landed on one wall edge or corner, triangles of zero area (50 with
    collinear corners, 6 with coincident ones in a 6,050-face frame by a moving box's edge), a vertex whose only
    triangles were those (normal (0, 0, 0): black in a render) and up to 90 unreferenced vertices a frame
    (stray points in Houdini). tidy takes them out and keeps the surface: closed, the same volume, oriented."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=2)
    v, f = ball.vertices.copy(), ball.faces.copy()
    # a T-junction closed by a sliver: face 0 (a, b, c) split at the midpoint m of a -> b, the crack closed by
    # the zero-area (a, b, m)
    a, b, c = f[0]
    m = len(v)
    v = np.vstack([v, 0.5 * (v[a] + v[b])])
    f[0] = (a, m, c)
    f = np.vstack([f, [m, b, c], [a, b, m]])
    # a zero-length edge: face 10's corner x duplicated as x2, the two flat triangles (x, y, x2), (x, x2, z)
    x, y, z = f[10]
    x2 = len(v)
    v = np.vstack([v, v[x]])
    f[10] = (x2, y, z)
    f = np.vstack([f, [x, y, x2], [x, x2, z]])
    # a flat pillow hanging off vertex 5, and two stray vertices
    p1, p2 = len(v), len(v) + 1
    v = np.vstack([v, v[5] + [0.01, 0, 0], v[5] + [0, 0.01, 0], [9, 9, 9], [8, 8, 8]])
    f = np.vstack([f, [5, p1, p2], [5, p2, p1]])
    assert boundary_edge_count(f) == 0
    v2, f2 = tidy(v.astype(np.float32), f.astype(np.int32))
    assert v2.dtype == np.float32 and f2.dtype == np.int32
    assert_tidy(SurfaceMesh(v2, f2, vertex_normals(v2, f2).astype(np.float32)))
    assert boundary_edge_count(f2) == 0
    assert len(v2) == len(ball.vertices) + 1  # m stays (the split keeps it); x2, the pillow and the strays go
    assert signed_volume(v2, f2) == pytest.approx(signed_volume(ball.vertices, ball.faces), rel=1e-6)
    assert signed_volume(v2, f2) > 0
    # a clean mesh is returned as it is
    v3, f3 = tidy(ball.vertices, ball.faces)
    assert np.array_equal(v3, ball.vertices) and np.array_equal(f3, ball.faces)


def test_box_in_tank_snaps_flat_onto_the_walls(tmp_path):
    x = lattice([0, 0, 0], [0.2, 0.2, 0.1], L0)  # fills the tank's floor, half its height
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    exact = box_interior_sdf(LO, HI)
    sdf = grid_from_function(exact, LO, HI, L0 / 2, band=4 * L0)
    (tmp_path / "sdf").mkdir()
    sdf.save(tmp_path / "sdf")
    raw_dir = run_stage(MarchingCubes, tmp_path / "raw", scene=SCENE, inputs={"particles": src}, frames=(0,))
    raw = load_surface(raw_dir, 0)
    v0 = raw.vertices.astype(np.float64)
    d0 = exact(v0)
    band = d0 < 0.9 * L0  # strictly inside the snap band (1 l0): its edge is a tie
    assert band.sum() > 500 and (np.abs(d0[band]) > 0.05 * L0).any()  # the raw surface floats off the wall

    # from the SDF alone (no wall mesh): away from the tank's edges every vertex lies on the wall
    sdf_only, _ = snap_mesh(raw, sdf, L0, DistanceSnapParams())
    v1 = sdf_only.vertices.astype(np.float64)
    d1 = exact(v1)
    walls_near = (np.minimum(v1 - LO, HI - v1) < L0).sum(axis=1)
    flat = band & (walls_near == 1)
    assert flat.sum() > 200 and np.abs(d1[flat]).max() < 1e-3 * L0
    assert d1.min() > -1e-3 * L0
    assert (np.einsum("ij,ij->i", face_normals(v0, raw.faces), face_normals(v1, sdf_only.faces)) >= 0).all()

    # with the wall mesh (the stage's default when the walls are upstream): every band vertex, in the
    # concave edges and corners too, ends on the exact tank
    walls_dir = tank_walls(tmp_path / "walls")
    snap_dir = run_stage(DistanceSnap, tmp_path / "snap", scene=SCENE, frames=(0,),
                         inputs={"raw_surface": raw_dir, "sdf": tmp_path / "sdf", "particles": src,
                                 "walls": walls_dir})
    snapped = load_surface(snap_dir, 0)
    walls = WallMesh.load(walls_dir)
    same, report = snap_mesh(raw, SDFGrid.load(tmp_path / "sdf"), L0, DistanceSnapParams(), walls, particles=x)
    # the stage publishes it tidied: the collapses' unreferenced vertices and any sliver taken out
    v, f = tidy(same.vertices, same.faces)
    assert np.array_equal(v, snapped.vertices) and np.array_equal(f, snapped.faces)
    assert_tidy(snapped)
    snapped = same  # (vertex for vertex with the raw surface)
    assert_on_the_walls(raw, snapped, report, walls, band, exact, 1e-3 * L0)
    assert np.abs(exact(snapped.vertices.astype(np.float64))[band]).max() < 1e-3 * L0
    # the floor is flat: every band vertex nearer the floor than the side walls at z = 0
    side = np.minimum(v0[:, :2] - LO[:2], HI[:2] - v0[:, :2]).min(axis=1)
    floor = band & (v0[:, 2] < 0.5 * side)
    assert floor.sum() > 100 and np.abs(snapped.vertices[floor, 2]).max() < 1e-3 * L0


R, H, CENTRE, RS = 0.1, 0.2, np.array([0.0, 0.0, 0.05]), 0.05


def cylinder_with_sphere(p: np.ndarray) -> np.ndarray:
    """Signed distance, positive in the fluid: inside a cylinder tank (radius R, height H, axis z),
    outside a sphere (radius RS) standing in it."""
    r = np.hypot(p[:, 0], p[:, 1])
    tank = np.minimum(np.minimum(R - r, p[:, 2]), H - p[:, 2])
    return np.minimum(tank, np.linalg.norm(p - CENTRE, axis=1) - RS)


@pytest.mark.parametrize("wall_term", [False, True])
def test_fluid_in_a_cylinder_around_a_sphere_ends_on_both(tmp_path, wall_term):
    """Curved walls, concave (the cylinder, its crease with the floor) and convex (the sphere), with
    the raw surface floating off the walls (no wall term) or already cut at them (the default)."""
    import trimesh

    x = lattice([-R, -R, 0], [R, R, 0.08], L0)
    x = x[cylinder_with_sphere(x) > 0]
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    sdf = grid_from_function(cylinder_with_sphere, [-R, -R, 0], [R, R, H], L0 / 2, band=4 * L0)
    (tmp_path / "sdf").mkdir()
    sdf.save(tmp_path / "sdf")
    raw_dir = run_stage(MarchingCubes, tmp_path / "raw", scene=SCENE, frames=(0,),
                        inputs={"particles": src, **({"sdf": tmp_path / "sdf"} if wall_term else {})})
    raw = load_surface(raw_dir, 0)
    tank = trimesh.creation.cylinder(radius=R, height=H, sections=96)
    tank.apply_translation([0, 0, H / 2])
    tank.invert()
    ball = trimesh.creation.icosphere(subdivisions=4, radius=RS)
    ball.apply_translation(CENTRE)
    walls = WallMesh.load(save_walls(tmp_path / "walls", tank, ball))
    snapped, report = snap_mesh(raw, sdf, L0, DistanceSnapParams(), walls)
    # the contact region: within the band of a wall, surface normal facing it (the free surface near
    # the sphere's top faces up and stays)
    v0 = raw.vertices.astype(np.float64)
    wall_point = closest_points_on(walls, v0)
    d0 = np.linalg.norm(wall_point - v0, axis=1)
    _, n_wall = sdf.sample(v0)
    band = (d0 < 0.9 * L0) & (np.einsum("ij,ij->i", raw.normals, n_wall) < 0)
    assert band.sum() > 500 and (d0[band] > 0.05 * L0).any()
    on_ball = band & (np.linalg.norm(v0 - CENTRE, axis=1) < RS + L0)
    on_side = band & (np.hypot(v0[:, 0], v0[:, 1]) > R - L0)
    assert on_ball.sum() > 50 and on_side.sum() > 100
    # a 96-gon is off its circle by R (1 - cos(pi / 96)) = 0.0027 l0, the icosphere by less
    assert_on_the_walls(raw, snapped, report, walls, band, cylinder_with_sphere, 4e-3 * L0)


def test_closest_points_agree_with_open3d_near_and_far():
    """stages.common.closest (wall_snap's exact finish) against open3d's RaycastingScene: the same
    distance to a sphere standing in a tank, for points near the walls (where the grid answers from the
    point's own cell) and anywhere in and around the tank (where the search widens or checks every
    triangle); a degenerate triangle (a sliver with a repeated vertex) is only its edges."""
    import open3d as o3d
    import trimesh

    from stages.common.closest import ClosestPoints

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    ball.apply_translation([0.1, 0.1, 0.06])
    tank = trimesh.creation.box(bounds=[LO, HI])
    m = trimesh.util.concatenate([tank, ball])
    v = np.asarray(m.vertices)
    f = np.vstack([m.faces, [[0, 0, 1]]])  # a degenerate triangle: the tank's edge 0-1
    rng = np.random.default_rng(0)
    on = trimesh.sample.sample_surface(m, 3000, seed=1)[0]
    points = np.vstack([on + rng.normal(scale=0.002, size=on.shape),  # near: within a cell
                        rng.uniform(-0.1, 0.3, (1000, 3))])  # anywhere, also outside the tank's box
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    ref = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))["points"].numpy()
    for reach in (0.005, 0.05):
        near, normals, ids = ClosestPoints(v, f, reach)(points)
        d = np.linalg.norm(near - points, axis=1)
        assert np.abs(d - np.linalg.norm(ref - points, axis=1)).max() < 1e-6  # open3d rounds to float32
        sliver = ids == len(f) - 1  # the sliver's points lie on the edge, as do its neighbour's
        assert not normals[sliver].any()
        tri = v[f[ids[~sliver]]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert np.allclose(normals[~sliver], n / np.linalg.norm(n, axis=1)[:, None])  # the triangle it lies on
        assert np.abs(np.einsum("ij,ij->i", near[~sliver] - tri[:, 0], normals[~sliver])).max() < 1e-12


@pytest.mark.parametrize("thickness", [0.05, 0.06], ids=["0.5_l0", "0.6_l0"])
def test_water_in_a_thin_walled_glass_ends_on_the_glass_inside_not_its_outside(tmp_path, thickness):
    """A glass whose walls are about a grid cell thick (the shipped pour's: 0.6 l0): the baked field inside
    them is flat or shallow, the raw surface ends inside the wall, and the exact finish took the nearer face: at
    0.5 l0 517 vertices stayed inside the wall, at 0.6-0.65 l0 about 500 went onto its outside, the water drawn down the
    outside of the glass and under its floor (1.29 N l0^3 of it at 0.6 l0). Every contact vertex now ends on
    the glass's inside faces, none inside the wall or on its outside, the volume the water's."""
    from stages.mesh_import.trimesh_import import TrimeshImport
    from stages.sdf_bake.open3d_bake import Open3dBake

    sc = {"scene": {"name": "glass", "units": {"meters_per_unit": 1.0, "up_axis": "Z"},
                    "frames": {"fps": 10, "count": 1}, "domain": {"min": [-0.25, -0.25, -0.02], "max": [0.25, 0.25, 0.3]}},
          "walls": [{"builtin": "open_box", "size": [0.2, 0.2, 0.1]}],
          "fluid": {"spacing": L0, "emitters": [{"box": {"min": [-0.05, -0.05, 0.02], "max": [0.05, 0.05, 0.06]}}]}}
    walls_dir = run_stage(TrimeshImport, tmp_path / "walls", scene=sc, params={"open_box_thickness": thickness})
    sdf_dir = run_stage(Open3dBake, tmp_path / "sdf", scene=sc, inputs={"walls": walls_dir})
    t = thickness * 0.2
    # the glass's inside filled as the emitter does: the lattice, rows nearer the walls than l0 / 2 moved out to it
    x = lattice([-0.09, -0.09, 0.01], [0.09, 0.09, 0.09], L0)
    x[:, :2] = np.clip(x[:, :2], -(0.1 - t - L0 / 2), 0.1 - t - L0 / 2)
    x[:, 2] = np.maximum(x[:, 2], t + L0 / 2)
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    raw_dir = run_stage(MarchingCubes, tmp_path / "raw", scene=SCENE, inputs={"particles": src, "sdf": sdf_dir},
                        frames=(0,))
    snap_dir = run_stage(DistanceSnap, tmp_path / "snap", scene=SCENE, frames=(0,),
                         inputs={"raw_surface": raw_dir, "sdf": sdf_dir, "particles": src, "walls": walls_dir})

    def in_wall(p):  # how deep inside the glass's walls (> 0), or on its outside faces (== 0 there)
        ax, ay, z = np.abs(p[:, 0]), np.abs(p[:, 1]), p[:, 2]
        outer = np.minimum.reduce([0.1 - ax, 0.1 - ay, z, 0.1 - z])
        cavity = np.minimum.reduce([0.1 - t - ax, 0.1 - t - ay, z - t])
        return np.where((outer > -1e-6) & (cavity < 0), np.minimum(outer, -cavity), -1.0), outer

    raw = load_surface(raw_dir, 0)
    depth, _ = in_wall(raw.vertices.astype(np.float64))
    assert (depth > 0.05 * L0).sum() > 300  # the raw surface ends inside the thin wall (the case at hand)
    snapped = load_surface(snap_dir, 0)
    assert_tidy(snapped)
    v = snapped.vertices.astype(np.float64)
    depth, outer = in_wall(v)
    assert (depth > 1e-3 * L0).sum() == 0  # none inside the wall
    assert (np.abs(outer) < 1e-3 * L0).sum() == 0  # none on its outside faces
    on_inside = np.minimum.reduce([np.abs(0.1 - t - np.abs(v[:, 0])), np.abs(0.1 - t - np.abs(v[:, 1])),
                                   np.abs(v[:, 2] - t)]) < 1e-3 * L0
    assert on_inside.sum() > 300
    assert boundary_edge_count(snapped.faces) == 0
    assert signed_volume(v, snapped.faces) == pytest.approx(len(x) * L0 ** 3, rel=0.12)


def extract_and_snap_in_the_tank(tmp_path, x: np.ndarray):
    """(raw, snapped) surface folders of the particles ``x`` (one frame) in the box tank LO-HI, its exact field."""
    sdf = grid_from_function(box_interior_sdf(LO, HI), LO, HI, L0 / 2, band=4 * L0)
    (tmp_path / "sdf").mkdir()
    sdf.save(tmp_path / "sdf")
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    raw_dir = run_stage(MarchingCubes, tmp_path / "raw", scene=SCENE, inputs={"particles": src, "sdf": tmp_path / "sdf"},
                        frames=(0,))
    snap_dir = run_stage(DistanceSnap, tmp_path / "snap", scene=SCENE, frames=(0,),
                         inputs={"raw_surface": raw_dir, "sdf": tmp_path / "sdf", "particles": src,
                                 "walls": tank_walls(tmp_path / "walls")})
    return raw_dir, snap_dir


def test_a_drop_hanging_over_the_floor_keeps_its_shape_and_a_drop_on_it_meets_it(tmp_path):
    """A lone particle 1.0 or 1.4 l0 above the floor is a drop that does not touch it (a resting first layer is
    0.5 l0 off), but its underside faces the floor within the snap band: it was pulled down onto the floor (at
    1.4 l0 four vertices went 0.84 l0 straight down, +72 % volume; a splash's droplets grew 20-65 %). It now keeps
    its extracted shape; a drop resting on the floor (0.5 l0) still meets it."""
    import trimesh

    heights = {"resting": 0.5, "hanging": 1.0, "higher": 1.4}
    x = np.array([[0.05 + 0.05 * k, 0.1, h * L0] for k, h in enumerate(heights.values())])
    raw_dir, snap_dir = extract_and_snap_in_the_tank(tmp_path, x)

    def drops(folder):  # per particle: (lowest point, volume) of the piece around it, in l0 and l0^3
        m = load_surface(folder, 0)
        pieces = trimesh.Trimesh(m.vertices.astype(np.float64), m.faces, process=False).split(only_watertight=True)
        assert len(pieces) == len(x)
        got = {}
        for name, p in zip(heights, x):
            piece = min(pieces, key=lambda q: np.linalg.norm(q.centroid[:2] - p[:2]))
            got[name] = (piece.vertices[:, 2].min() / L0, piece.volume / L0 ** 3)
        return got

    raw, snapped = drops(raw_dir), drops(snap_dir)
    assert raw["hanging"][0] > 0.2 and raw["higher"][0] > 0.6  # the raw drops clear the floor
    for name in ("hanging", "higher"):
        assert snapped[name][0] == pytest.approx(raw[name][0], abs=1e-6)
        assert snapped[name][1] == pytest.approx(raw[name][1], rel=1e-6)
    assert snapped["resting"][0] < 1e-3  # on the floor
    assert_tidy(load_surface(snap_dir, 0))


@pytest.mark.parametrize("layers", [1, 2])
@pytest.mark.parametrize("gap", [0.8, 1.0, 1.2])
def test_a_film_on_the_floor_short_of_a_side_wall_stays_inside_the_surface(tmp_path, gap, layers):
    """Water a layer or two deep on the floor, ending ``gap`` l0 short of a side wall (the pour's film in the corner
    of its tipped glass): the raw surface's end faces the side wall within the band, no water touches the wall
    there, and the thin-wall probe (WET_PROBE l0 back into the water) found the floor nearer and pulled those
    vertices down under the film: 3-11 of 48 particles ended outside the snapped surface (18 of 1,000 in the pour).
    A probe still in front of the face first found is no thin wall's dry side: the vertex stays as extracted."""
    import igl

    i, j, k = np.meshgrid(np.arange(6), np.arange(8), np.arange(layers), indexing="ij")
    x = np.stack([(gap + i.ravel()) * L0, (2 + j.ravel()) * L0, (0.5 + k.ravel()) * L0], axis=1)
    raw_dir, snap_dir = extract_and_snap_in_the_tank(tmp_path, x)
    for folder in (raw_dir, snap_dir):
        m = load_surface(folder, 0)
        inside = igl.winding_number(m.vertices.astype(np.float64), m.faces.astype(np.int64), x) > 0.5
        assert inside.all(), (folder.name, int((~inside).sum()))
    snapped = load_surface(snap_dir, 0)
    assert_tidy(snapped)
    assert snapped.vertices[:, 2].min() > -1e-6 and np.abs(snapped.vertices[:, 2]).min() < 1e-6 * L0  # on the floor


@pytest.mark.parametrize("dense", [True, False])
def test_touching_finds_every_particle_in_front_of_a_wall_point_whatever_the_spread(monkeypatch, dense):
    """The touch test (keep_contacts) bins a frame's particles in cells of l0: a dense table over their box, or, for
    spray kilometres apart (a box of too many cells), the sorted cell keys. Either way it answers what the definition
    says for every point (brute force over all particles): a particle within l0 of the point half a spacing out,
    between -0.1 and TOUCH l0 in front of it; points far outside the particles' box touch nothing."""
    from stages.wall_snap.distance import TOUCH, Water, touching

    rng = np.random.default_rng(7)
    l0 = 0.02
    x = np.vstack([rng.uniform(0, 0.3, (3000, 3)), rng.uniform(500, 500.05, (50, 3))])  # a block and far spray
    if dense:
        x = x[:3000]
    else:
        monkeypatch.setattr(Water, "DENSE_CELLS", 1000)
    points = np.vstack([rng.uniform(-0.05, 0.35, (4000, 3)), rng.uniform(499.95, 500.1, (500, 3)), [[-1e9, 0, 0]]])
    normals = rng.normal(size=points.shape)
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    water = Water(x, l0)
    assert (len(water.starts) > 0) == dense
    got = touching(water, points, normals, l0)
    q = points + 0.5 * l0 * normals
    want = np.zeros(len(points), np.bool_)
    for i in range(len(points)):
        near = np.linalg.norm(x - q[i], axis=1) < l0
        ahead = (x[near] - points[i]) @ normals[i]
        want[i] = ((ahead > -0.1 * l0) & (ahead < TOUCH * l0)).any()
    assert want.sum() > 200 and (want[4000:4500].any() or dense)
    np.testing.assert_array_equal(got, want)


def test_touching_bins_spray_light_years_apart_without_overflow():
    """Cells of l0 over a box 1e15 spacings wide would overflow the cell keys: the bins grow there, and the answer
    is still the definition's (a point beside each of two particles 1e13 m apart touches, one between them not)."""
    from stages.wall_snap.distance import Water, touching

    l0 = 0.01
    x = np.array([[0.0, 0.0, 0.0], [1e13, 1e13, 1e13]])
    water = Water(x, l0)
    assert water.cell > l0 and np.prod(water.dims.astype(float)) < 2.0 ** 62
    up = np.array([[0.0, 0.0, 1.0]] * 3)
    points = np.array([[0.0, 0.0, -0.5 * l0], [1e13, 1e13, 1e13 - 0.5 * l0], [5e12, 5e12, 5e12]])
    np.testing.assert_array_equal(touching(water, points, up, l0), [True, True, False])
