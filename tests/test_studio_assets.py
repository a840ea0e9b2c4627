"""mesh_import: assets as studios and DCCs write them (shots from code 1001, point instancers, polygon
soups welded by distance, OBJ relative indices and free layout)."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.stage import StageError
from pipeline.testing import run_stage
from stages.common.formats import WallMesh
from stages.common.motion import RigidMotion
from stages.mesh_import.trimesh_import import TrimeshImport

SCENE = {"name": "t", "units": {"meters_per_unit": 1.0, "up_axis": "Z"}}
CUBE_COUNTS = [4] * 6
CUBE_INDICES = [0, 3, 2, 1, 4, 5, 6, 7, 0, 1, 5, 4, 1, 2, 6, 5, 2, 3, 7, 6, 3, 0, 4, 7]


def _import(tmp_path, walls, **params):
    out = run_stage(TrimeshImport, tmp_path / "out", scene={"scene": SCENE, "walls": walls}, params=params,
                    config_dir=tmp_path)
    return WallMesh.load(out)


def _cube_points(h):
    return [(x, y, z) for z in (-h, h) for x, y in ((-h, -h), (h, -h), (h, h), (-h, h))]


def _define_cube(stage, path, h=0.05):
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(_cube_points(h))
    mesh.CreateFaceVertexCountsAttr(CUBE_COUNTS)
    mesh.CreateFaceVertexIndicesAttr(CUBE_INDICES)
    return mesh


def _new_stage(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    return stage


def test_usd_animation_from_code_1001_moves_as_from_code_0(tmp_path):
    """A shot authored from startTimeCode 1001 starts at time 0: the wall keyed 0.1 m over 30 codes at
    30 codes/s is at 0.05 m after 0.5 s, as the same wall keyed from code 0 (it stood still for 33 s)."""
    from pxr import Gf, UsdGeom

    poses = {}
    for start in (0, 1001):
        stage = _new_stage(tmp_path / f"anim{start}.usda")
        stage.SetStartTimeCode(start)
        stage.SetEndTimeCode(start + 30)
        stage.SetTimeCodesPerSecond(30)
        op = UsdGeom.Xform.Define(stage, "/World/Mover").AddTranslateOp()
        op.Set(Gf.Vec3d(0, 0, 0), start)
        op.Set(Gf.Vec3d(0.1, 0, 0), start + 30)
        _define_cube(stage, "/World/Mover/Cube")
        stage.GetRootLayer().Save()
        motion = RigidMotion.from_json(_import(tmp_path, [{"usd": f"anim{start}.usda"}]).walls[0]["motion"])
        poses[start] = [motion.pose(t) for t in (0.0, 0.5, 1.0)]
    np.testing.assert_allclose(poses[1001][1][1], [0.05, 0, 0], atol=1e-9)
    for a, b in zip(poses[0], poses[1001]):
        np.testing.assert_allclose(a[0], b[0], atol=1e-12)
        np.testing.assert_allclose(a[1], b[1], atol=1e-12)


def test_a_polygon_soup_with_float_noise_across_a_rounding_boundary_welds_closed(tmp_path):
    """A cube exported as a triangle soup, each corner written once per triangle with noise of a few 1e-9
    (under the weld tolerance, 1e-7 of the 0.17 diagonal) around 0.05000005, where rounding to 7 digits
    splits it: every copy is welded, the cube is closed (8 vertices) and a solid, not an open shell."""
    h = 0.05000005  # half-way between 0.0500000 and 0.0500001
    v = np.array(_cube_points(h))
    tris = np.array(CUBE_INDICES).reshape(-1, 4)[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3)
    lines = []
    for k, t in enumerate(tris):
        jitter = 2e-9 if k % 2 else -2e-9  # neighbouring triangles' copies on either side of the boundary
        lines += [f"v {x + jitter:.12f} {y + jitter:.12f} {z + jitter:.12f}" for x, y, z in v[t]]
    lines += [f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}" for k in range(len(tris))]
    (tmp_path / "soup.obj").write_text("\n".join(lines) + "\n")
    wall = _import(tmp_path, [{"file": "soup.obj"}]).walls[0]
    assert wall["report"]["vertices"] == 8 and wall["report"]["welded_vertices"] == 28
    assert wall["report"]["watertight"] and wall["fluid"] == "outside"


def _cube_obj(face_vertex, sep=" ", indent="", comment=""):
    v = [f"{indent}v{sep}{sep.join(f'{c:g}' for c in p)}{comment}" for p in _cube_points(0.1)]
    extra = [f"{indent}vt 0 0", f"{indent}vn 0 0 1"]
    quads = np.array(CUBE_INDICES).reshape(-1, 4)
    f = [f"{indent}f{sep}{sep.join(face_vertex(i) for i in q)}{comment}" for q in quads]
    return "\n".join(v + extra + f) + "\n"


@pytest.mark.parametrize("name, text", [
    ("negidx_vn", _cube_obj(lambda i: f"{i - 8}//-1")),
    ("negidx_vtvn", _cube_obj(lambda i: f"{i - 8}/-1/-1")),
    ("tabs", _cube_obj(lambda i: str(i + 1), sep="\t")),
    ("indent", _cube_obj(lambda i: str(i + 1), indent="  ")),
    ("comment", _cube_obj(lambda i: str(i + 1), comment="  # corner")),
])
def test_valid_obj_layouts_import_as_the_plain_file(tmp_path, name, text):
    """Relative indices with /vt or /vn, tabs, indented lines and trailing comments are valid OBJ (trimesh
    refused or misread them): the cube comes in as the plain-index file's does."""
    (tmp_path / "plain.obj").write_text(_cube_obj(lambda i: str(i + 1)))
    (tmp_path / f"{name}.obj").write_text(text)
    plain = _import(tmp_path, [{"file": "plain.obj"}])
    wm = _import(tmp_path, [{"file": f"{name}.obj"}])
    assert wm.walls[0]["report"]["watertight"] and wm.walls[0]["report"]["faces"] == 12
    np.testing.assert_array_equal(wm.vertices, plain.vertices)
    np.testing.assert_array_equal(_triangles(wm.faces), _triangles(plain.faces))  # trimesh orders them otherwise


def _triangles(f):
    """The triangles as a set: each rotated to start at its smallest index (winding kept), rows sorted."""
    f = np.array([np.roll(t, -int(np.argmin(t))) for t in f])
    return f[np.lexsort(f.T[::-1])]


def test_obj_relative_index_out_of_range_names_the_file(tmp_path):
    (tmp_path / "bad.obj").write_text(_cube_obj(lambda i: f"{i - 9}//-1"))
    with pytest.raises(StageError, match=r"bad\.obj: .*out of range"):
        _import(tmp_path, [{"file": "bad.obj"}])


def _streamed_cube_obj(triangles=False):
    """The cube as streaming exporters write it: each face's own vertices, then the face by relative
    indices (``f -4 -3 -2 -1``), repeated."""
    p = _cube_points(0.1)
    quads = np.array(CUBE_INDICES).reshape(-1, 4)
    faces = quads[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3) if triangles else quads
    out = []
    for q in faces:
        out += [f"v {p[i][0]:g} {p[i][1]:g} {p[i][2]:g}" for i in q]
        out.append("f " + " ".join(str(k - len(q)) for k in range(len(q))))
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("triangles", [False, True])
def test_plain_relative_indices_count_back_from_the_vertices_read_so_far(tmp_path, triangles):
    """``f -4 -3 -2 -1`` after each quad's vertices (no slashes): trimesh counted back from the file's last
    vertex, every face landed on the last quad and the tank vanished without a word; each face is its own
    quad now and the cube is closed, as the plain-index file."""
    (tmp_path / "plain.obj").write_text(_cube_obj(lambda i: str(i + 1)))
    (tmp_path / "streamed.obj").write_text(_streamed_cube_obj(triangles))
    plain = _import(tmp_path, [{"file": "plain.obj", "fluid": "inside"}])
    wm = _import(tmp_path, [{"file": "streamed.obj", "fluid": "inside"}])
    report = wm.walls[0]["report"]
    assert report["watertight"] and report["faces"] == 12 and report["vertices"] == 8
    corners = lambda m: sorted(sorted(map(tuple, m.vertices[t])) for t in m.faces)  # noqa: E731 - the triangles' corners
    assert corners(wm) == corners(plain)


@pytest.mark.parametrize("face", ["f 0 4 3 2", "f 0 3 2"])
def test_obj_index_0_is_refused_naming_its_line(tmp_path, face):
    """Index 0 is no OBJ index (they start at 1): trimesh took it for the last vertex (a triangle file) or the
    message said only "out of range"; now one line names the file and the line."""
    lines = _cube_obj(lambda i: str(i + 1)).splitlines()
    n = next(k for k, line in enumerate(lines) if line.startswith("f "))
    lines[n] = face
    (tmp_path / "zero.obj").write_text("\n".join(lines) + "\n")
    with pytest.raises(StageError, match=rf"zero\.obj: line {n + 1}: face index 0 is not valid in OBJ "
                                         r"\(indices start at 1\)$"):
        _import(tmp_path, [{"file": "zero.obj"}])


def _instancer_and_meshes(tmp_path, animated=False):
    """A Y-up centimetre stage with a PointInstancer (under a moved Xform; its cube prototype has its own
    offset) of two instances, one turned and scaled; and the same two cubes as plain meshes placed by
    xformOps (an instance: scale, then turn, then move, after the prototype root's own transform)."""
    from pxr import Gf, UsdGeom, Vt

    pos = [Gf.Vec3f(0, 10, 0), Gf.Vec3f(50, 10, 0)]
    rot = [Gf.Quatf(1, 0, 0, 0), Gf.Quatf(Gf.Rotation(Gf.Vec3d(0, 1, 0), 90).GetQuat())]
    scale = [Gf.Vec3f(1, 1, 1), Gf.Vec3f(2, 1, 1)]
    for name in ("inst", "meshes"):
        stage = _new_stage(tmp_path / f"{name}.usda")
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.Xform.Define(stage, "/World").AddTranslateOp().Set(Gf.Vec3d(0, 0, -20))
        if name == "inst":
            pi = UsdGeom.PointInstancer.Define(stage, "/World/PI")
            proto = _define_cube(stage, "/World/PI/Protos/Cube", h=10)
            proto.AddTranslateOp().Set(Gf.Vec3d(300, 0, 0))  # part of each instance's transform
            pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
            pi.CreateProtoIndicesAttr([0, 0])
            pi.CreateOrientationsfAttr(Vt.QuatfArray(rot))
            pi.CreateScalesAttr(Vt.Vec3fArray(scale))
            pi.CreatePositionsAttr(Vt.Vec3fArray(pos))
            if animated:
                pi.GetPositionsAttr().Set(Vt.Vec3fArray(pos), 0)
                pi.GetPositionsAttr().Set(Vt.Vec3fArray([p + Gf.Vec3f(0, 5, 0) for p in pos]), 10)
        else:
            for k in range(2):
                cube = _define_cube(stage, f"/World/C{k}", h=10)
                cube.AddTranslateOp().Set(Gf.Vec3d(pos[k]))
                cube.AddOrientOp().Set(rot[k])
                cube.AddScaleOp().Set(scale[k])
                cube.AddTranslateOp(opSuffix="proto").Set(Gf.Vec3d(300, 0, 0))
        stage.GetRootLayer().Save()


def test_point_instancer_instances_are_walls_placed_as_meshes_would_be(tmp_path):
    """Each instance of a PointInstancer is a wall mesh where the instancer puts it (units and up axis
    converted as for other meshes); the prototype itself is no wall (it came in alone, at its own place)."""
    _instancer_and_meshes(tmp_path)
    inst = _import(tmp_path, [{"usd": "inst.usda"}])
    meshes = _import(tmp_path, [{"usd": "meshes.usda"}])
    assert inst.walls[0]["report"]["prims"] == ["/World/PI[0]", "/World/PI[1]"]
    assert len(inst.faces) == len(meshes.faces) == 24 and inst.walls[0]["report"]["watertight"]
    gap = np.linalg.norm(inst.vertices[:, None] - meshes.vertices[None], axis=2)  # the same corners (float32 noise)
    assert gap.min(axis=0).max() < 1e-5 and gap.min(axis=1).max() < 1e-5
    # metres, Z up: instance 0 at x 2.9..3.1 m, instance 1 (the prototype's 3 m offset doubled, turned) at y 6..6.4 m
    np.testing.assert_allclose(inst.vertices.min(axis=0), [0.4, 0.1, 0.0], atol=1e-6)
    np.testing.assert_allclose(inst.vertices.max(axis=0), [3.1, 6.4, 0.2], atol=1e-6)


def test_an_animated_point_instancer_is_refused_in_one_line(tmp_path):
    _instancer_and_meshes(tmp_path, animated=True)
    with pytest.raises(StageError, match=r"inst\.usda:/World/PI: a PointInstancer with animated positions") as e:
        _import(tmp_path, [{"usd": "inst.usda"}])
    assert "\n" not in str(e.value)


def test_a_usd_file_without_units_or_up_axis_is_warned_about(tmp_path, caplog):
    """USD's fallbacks are centimetres and Y up: a cube written in metres by a tool that states neither came
    in as a 1 mm cube lying on its side, without a word (a user's sweep). Imported by the fallbacks, as USD
    says, but warned about; a file stating both is not."""
    import logging

    from pxr import Usd

    bare = Usd.Stage.CreateNew(str(tmp_path / "bare.usda"))
    _define_cube(bare, "/Cube")
    bare.GetRootLayer().Save()
    stated = _new_stage(tmp_path / "stated.usda")
    _define_cube(stated, "/Cube")
    stated.GetRootLayer().Save()
    with caplog.at_level(logging.WARNING):
        mesh = _import(tmp_path, [{"usd": "bare.usda"}])
    assert np.allclose(np.ptp(mesh.vertices, axis=0), 0.001)  # 0.1 cm: the fallback, as USD reads it
    assert any("states no metersPerUnit and no upAxis" in r.getMessage() for r in caplog.records), caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _import(tmp_path, [{"usd": "stated.usda"}])
    assert not any("states no" in r.getMessage() for r in caplog.records)


def test_a_quad_obj_with_an_inf_coordinate_is_one_line_without_numpy_warnings(tmp_path):
    """The n-gon triangulation ran on the non-finite points before the check that refuses them, and numpy's
    RuntimeWarnings were printed above the one-line error."""
    import warnings

    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 inf\nv 0 1 0\nv 0 0 1\nf 1 2 3 4\nf 1 2 5\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(StageError, match="bad.obj: vertex coordinates contain NaN or Inf"):
            _import(tmp_path, [{"file": "bad.obj"}])
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in caught]


# (type, attributes in cm, closed volume in cm^3 or the Plane's area in cm^2, local half-extents in cm)
SHAPES = {
    "Cube": ({"size": 40.0}, 40.0 ** 3, (20, 20, 20)),
    "Sphere": ({"radius": 15.0}, 4 / 3 * np.pi * 15 ** 3, (15, 15, 15)),
    "Cylinder": ({"radius": 10.0, "height": 30.0, "axis": "X"}, np.pi * 100 * 30, (15, 10, 10)),
    "Cone": ({"radius": 10.0, "height": 30.0, "axis": "Y"}, np.pi * 100 * 30 / 3, (10, 15, 10)),
    "Capsule": ({"radius": 5.0, "height": 20.0, "axis": "Z"}, np.pi * 25 * 20 + 4 / 3 * np.pi * 125, (5, 5, 15)),
    "Cylinder_1": ({"radiusBottom": 10.0, "radiusTop": 5.0, "height": 20.0, "axis": "Z"},
                   np.pi * 20 / 3 * (100 + 50 + 25), (10, 10, 10)),
    "Plane": ({"width": 40.0, "length": 20.0, "axis": "X"}, 40.0 * 20.0, (0, 10, 20)),
    # USD's capsule of unequal ends is the hull of the two spheres (centres 10 apart): two caps and the
    # tangent frustum between them (it was a cone from equator to equator, 1.8 l0 inside the drawn one)
    "Capsule_1": ({"radiusBottom": 10.0, "radiusTop": 3.0, "height": 10.0, "axis": "Z"}, None, (10, 10, 15)),
}


def _capsule_hull_volume(r1: float, r2: float, spine: float) -> float:
    s = (r1 - r2) / spine  # sin of the tangent latitude
    c1, c2 = r1 * (1 + s), r2 * (1 - s)  # the caps' heights
    frustum = spine + (r2 - r1) * s
    return (np.pi * c1 ** 2 * (3 * r1 - c1) / 3 + np.pi * c2 ** 2 * (3 * r2 - c2) / 3
            + np.pi * frustum / 3 * (1 - s * s) * (r1 * r1 + r1 * r2 + r2 * r2))


@pytest.mark.parametrize("kind", list(SHAPES))
def test_usd_shapes_are_walls_of_their_own_size_and_place(tmp_path, kind):
    """A layout's implicit shapes (a Cube floor, a Sphere rock) are walls: tessellated at their schema's
    size, axis and place (a Y-up centimetre stage under a moved parent, into a metre Z-up scene), closed
    and outward except the Plane (an open sheet); they were left out without a word."""
    from pxr import Gf, Usd, UsdGeom

    attrs, measure, half = SHAPES[kind]
    measure = _capsule_hull_volume(10.0, 3.0, 10.0) if measure is None else measure
    stage = _new_stage(tmp_path / "set.usda")
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.Xform.Define(stage, "/World").AddTranslateOp().Set(Gf.Vec3d(100, 200, 300))
    prim = stage.DefinePrim("/World/Shape", kind)
    UsdGeom.Xformable(prim).AddTranslateOp().Set(Gf.Vec3d(0, 50, 0))
    for name, value in attrs.items():
        prim.GetAttribute(name).Set(value)
    stage.GetRootLayer().Save()
    mesh = _import(tmp_path, [{"usd": "set.usda"}])
    assert mesh.walls[0]["report"]["prims"] == ["/World/Shape"]
    # back to the stage's own frame (cm, Y up: z_scene = y_usd, y_scene = -z_usd), relative to the shape's centre
    v = mesh.vertices.astype(np.float64) * 100.0
    local = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1) - [100, 250, 300]
    np.testing.assert_allclose(np.abs(local).max(axis=0), half, atol=1e-3)
    tri = local[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if kind == "Plane":
        assert not mesh.walls[0]["report"]["watertight"]
        assert 0.5 * np.linalg.norm(cross, axis=1).sum() == pytest.approx(measure, rel=1e-9)
        assert np.allclose(cross[:, 1:], 0) and (cross[:, 0] > 0).all()  # the normal along +X, the plane's axis
        return
    assert mesh.walls[0]["report"]["watertight"]
    volume = float(np.einsum("ij,ij->i", tri[:, 0], cross).sum() / 6.0)
    assert volume == pytest.approx(measure, rel=2e-3)  # outward (> 0), the tessellation within 0.2 %
    if kind == "Sphere":
        np.testing.assert_allclose(np.linalg.norm(local, axis=1), 15.0, rtol=1e-6)
    if kind == "Cone":  # the apex is at +height/2 along the axis
        top = local[:, 1] > 15 - 1e-3
        assert top.any() and np.abs(local[top][:, [0, 2]]).max() < 1e-3


def test_a_shape_with_a_negative_radius_is_refused_in_one_line(tmp_path):
    from pxr import UsdGeom

    stage = _new_stage(tmp_path / "bad.usda")
    UsdGeom.Sphere.Define(stage, "/World/Rock").GetRadiusAttr().Set(-1.0)
    stage.GetRootLayer().Save()
    with pytest.raises(StageError, match=r"bad\.usda:/World/Rock: Sphere radius -1\.0 must be a positive number") as e:
        _import(tmp_path, [{"usd": "bad.usda"}])
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("axis", ["X", "invalid"])
def test_an_up_axis_usd_does_not_allow_is_refused_in_one_line(tmp_path, axis):
    """usd-wg's upAxis_X and upAxis_invalid: USD allows Y or Z; these were turned as if Z up were Y."""
    (tmp_path / "x.usda").write_text(f'#usda 1.0\n(\n    upAxis = "{axis}"\n    metersPerUnit = 0.01\n)\n'
                                     'def Cube "C"\n{\n}\n')
    with pytest.raises(StageError, match=rf"x\.usda: upAxis '{axis}' is not Y or Z") as e:
        _import(tmp_path, [{"usd": "x.usda"}])
    assert "\n" not in str(e.value)


def test_a_sublayer_in_other_units_is_read_as_usd_reads_it_and_warned_about(tmp_path, caplog):
    """usd-wg's metersPerUnit_mix: USD composes with the root layer's metersPerUnit only, so a sublayered
    metre cube in a centimetre stage is 2 cm wide (as usdview shows it); that trap is said, not hidden."""
    import logging

    (tmp_path / "metre.usda").write_text('#usda 1.0\n(\n    upAxis = "Z"\n    metersPerUnit = 1\n)\n'
                                         'def Cube "C"\n{\n}\n')
    (tmp_path / "shot.usda").write_text('#usda 1.0\n(\n    upAxis = "Z"\n    metersPerUnit = 0.01\n'
                                        '    subLayers = [@metre.usda@]\n)\n')
    with caplog.at_level(logging.WARNING):
        mesh = _import(tmp_path, [{"usd": "shot.usda"}])
    assert np.allclose(np.ptp(mesh.vertices, axis=0), 0.02)
    assert any("1 layer(s) state other units" in r.getMessage() and "metre.usda (metersPerUnit 1.0)" in r.getMessage()
               for r in caplog.records), caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _import(tmp_path, [{"usd": "metre.usda"}])
    assert not any("other units" in r.getMessage() for r in caplog.records)


def test_a_mesh_without_a_subdivision_scheme_is_said_to_be_usds_fallback_cage(tmp_path, caplog):
    """No subdivisionScheme authored is USD's fallback, catmullClark: Karma or RenderMan draws the limit surface,
    up to a third of a spacing off the cage the water met (a user's bowl), and nothing said so. One authored
    none stays silent."""
    import logging

    from pxr import UsdGeom

    stage = _new_stage(tmp_path / "plain.usda")
    _define_cube(stage, "/World/Plain", h=1.0)
    flat = _define_cube(stage, "/World/Flat", h=0.5)
    flat.AddTranslateOp().Set((3.0, 0.0, 0.0))
    flat.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    stage.GetRootLayer().Save()
    with caplog.at_level(logging.INFO):
        mesh = _import(tmp_path, [{"usd": "plain.usda"}])
    assert mesh.walls[0]["report"]["subdivision"] == {
        "/World/Plain": "catmullClark cage as-is (no subdivisionScheme authored: USD's fallback)"}
    assert "/World/Plain catmullClark subdivision cage(s), taken as-is" in caplog.text


def test_a_subdivision_cage_is_recorded_as_is_or_refined_to_its_limit_surface(tmp_path, caplog):
    """A catmullClark cage (the usd-wg teapot's kind) is the wall as authored unless the wall asks for
    ``subdivide``; either way the walls report says which. Refined, a cube cage (+-1) approaches
    Catmull-Clark's limit surface: the face centre's limit is x = (16 + 4 * 3 + 20/9) / 36 = 0.8395
    (the valence-4 limit mask on the first level's points), reached from above (0.878, 0.849, 0.842)."""
    import logging

    from pxr import UsdGeom

    stage = _new_stage(tmp_path / "cage.usda")
    cube = _define_cube(stage, "/World/Cage", h=1.0)
    cube.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.catmullClark)
    stage.GetRootLayer().Save()
    with caplog.at_level(logging.INFO):
        as_is = _import(tmp_path, [{"usd": "cage.usda"}])
    assert as_is.walls[0]["report"]["subdivision"] == {"/World/Cage": "catmullClark cage as-is"}
    assert "subdivision cage(s), taken as-is" in caplog.text
    np.testing.assert_allclose(np.abs(as_is.vertices).max(axis=0), 1.0)
    centre = []
    for levels in (2, 3, 4):
        mesh = _import(tmp_path, [{"usd": "cage.usda", "subdivide": levels}])
        assert mesh.walls[0]["report"]["subdivision"] == {"/World/Cage": f"catmullClark cage refined {levels} levels"}
        assert mesh.walls[0]["report"]["watertight"] and len(mesh.faces) == 12 * 4 ** levels
        centre.append(float(mesh.vertices[:, 0].max()))
    np.testing.assert_allclose(centre, [0.87847, 0.84918, 0.84192], atol=1e-5)
    assert 0.8395 < centre[-1] < centre[-2] < centre[-3]


def test_catmull_clark_keeps_a_flat_open_patch_flat_with_its_corners():
    """USD's boundary rule edgeAndCorner: boundary edges are creases and a vertex of one face stays put,
    so a flat quad patch keeps its outline and plane (its area within the boundary curves' rounding)."""
    from stages.mesh_import.subdivision import catmull_clark

    grid = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    quads = [[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]]
    p, c, i = catmull_clark(grid, [4] * 4, np.ravel(quads), 3)
    assert len(c) == 4 * 4 ** 3 and (c == 4).all()
    assert np.abs(p[:, 2]).max() == 0.0
    np.testing.assert_allclose(p[:, :2].min(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(p[:, :2].max(axis=0), 2.0, atol=1e-12)
    for corner in ([0, 0], [2, 0], [2, 2], [0, 2]):
        assert np.isclose(np.linalg.norm(p[:, :2] - corner, axis=1).min(), 0.0)


def test_a_malformed_usd_wall_or_camera_names_the_line_it_breaks_on(tmp_path):
    """A broken .usda said "cannot open as USD (')": the last of pxr's stacked messages, cut. Now the
    parser's first complaint, with the file's line and column; a camera file too (it was a traceback)."""
    from stages.common.camera import usd_camera_moves

    bad = tmp_path / "bad.usda"
    bad.write_text('#usda 1.0\ndef Mesh "M" {\n  point3f[] points = [(0,0,0), (1,0\n}\n')
    with pytest.raises(StageError, match=r"bad\.usda: cannot open as USD \(.*bad\.usda:4:1: parse error") as e:
        _import(tmp_path, [{"usd": "bad.usda"}])
    assert "\n" not in str(e.value) and "pxrInternal" not in str(e.value)
    with pytest.raises(StageError, match=r"camera: camera\.usd: .*bad\.usda: cannot open as USD \(.*4:1: parse error"):
        usd_camera_moves(bad, None)


def test_instancer_prototypes_leave_out_guides_and_proxies_and_nested_instancers_are_refused(tmp_path):
    """Inside an instancer's prototype a guide Cube (a rig helper 51 x the rock) and a proxy beside the
    render Sphere became walls at every instance; an instancer inside a prototype came in at its own
    place without its instances (a user's sweep). Guides and proxies are left out as outside instancers;
    a nested instancer is refused in one line."""
    from pxr import Gf, UsdGeom, Vt

    stage = _new_stage(tmp_path / "rocks.usda")
    pi = UsdGeom.PointInstancer.Define(stage, "/World/Inst")
    UsdGeom.Sphere.Define(stage, "/World/Inst/Protos/Rock/Render").GetRadiusAttr().Set(0.1)
    for name, purpose, size in (("Helper", UsdGeom.Tokens.guide, 0.6), ("Proxy", UsdGeom.Tokens.proxy, 0.25)):
        cube = UsdGeom.Cube.Define(stage, f"/World/Inst/Protos/Rock/{name}")
        cube.GetSizeAttr().Set(size)
        cube.CreatePurposeAttr(purpose)
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/Inst/Protos/Rock/Render")).CreatePurposeAttr(UsdGeom.Tokens.render)
    pi.CreatePrototypesRel().SetTargets(["/World/Inst/Protos/Rock"])
    pi.CreateProtoIndicesAttr([0, 0])
    pi.CreatePositionsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0)]))
    stage.GetRootLayer().Save()
    mesh = _import(tmp_path, [{"usd": "rocks.usda"}])
    assert mesh.walls[0]["report"]["prims"] == ["/World/Inst[0]/Render", "/World/Inst[1]/Render"]
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-0.1, -0.1, -0.1], atol=1e-9)

    inner = UsdGeom.PointInstancer.Define(stage, "/World/Inst/Protos/Rock/Pebbles")
    inner.CreatePrototypesRel().SetTargets(["/World/Inst/Protos/Rock/Render"])
    inner.CreateProtoIndicesAttr([0])
    inner.CreatePositionsAttr(Vt.Vec3fArray([Gf.Vec3f(0.2, 0, 0)]))
    stage.GetRootLayer().Save()
    with pytest.raises(StageError, match=r"rocks\.usda:/World/Inst: prototype /World/Inst/Protos/Rock holds another "
                                         r"PointInstancer") as e:
        _import(tmp_path, [{"usd": "rocks.usda"}])
    assert "\n" not in str(e.value)


def test_a_usd_camera_in_an_up_axis_usd_does_not_allow_is_refused_as_walls_are(tmp_path):
    """A camera file with upAxis X was turned as if it were Z up, and one with metersPerUnit 0 sat at the
    origin, without a word (walls refuse both)."""
    from stages.common.camera import usd_camera

    for name, head in (("x", 'upAxis = "X"\n    metersPerUnit = 0.01'), ("zero", 'upAxis = "Z"\n    metersPerUnit = 0')):
        (tmp_path / f"{name}.usda").write_text(f'#usda 1.0\n(\n    {head}\n)\ndef Camera "Cam"\n{{\n}}\n')
        with pytest.raises(StageError, match=rf"camera: camera\.usd: .*{name}\.usda: (upAxis 'X' is not Y or Z|"
                                             r"metersPerUnit 0\.0 must be a positive number)"):
            usd_camera(tmp_path / f"{name}.usda", None, "Z", 1.0)


def test_a_hole_in_a_subdivision_cage_leaves_its_neighbours_on_the_closed_cages_limit(tmp_path):
    """A hole face refines with the cage and only its children are left out (OpenSubdiv draws the hole's
    neighbours as on the closed cage: the cube's faces reach 0.842 at 4 levels); removed first, it made
    the rim a boundary crease and the sides bulged to 0.918, 8 % outside what a renderer draws."""
    from pxr import UsdGeom

    stage = _new_stage(tmp_path / "holed.usda")
    cube = _define_cube(stage, "/World/Cage", h=1.0)
    cube.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.catmullClark)
    cube.CreateHoleIndicesAttr([1])  # the top face (z = +1)
    stage.GetRootLayer().Save()
    closed_stage = _new_stage(tmp_path / "closed.usda")
    _define_cube(closed_stage, "/World/Cage", h=1.0).CreateSubdivisionSchemeAttr(UsdGeom.Tokens.catmullClark)
    closed_stage.GetRootLayer().Save()
    holed = _import(tmp_path, [{"usd": "holed.usda", "subdivide": 4, "shell": {"thickness": 0.01}}])
    closed = _import(tmp_path, [{"usd": "closed.usda", "subdivide": 4}])
    assert len(holed.faces) == len(closed.faces) * 5 // 6  # one face's children of six
    assert holed.vertices[:, 0].max() == pytest.approx(closed.vertices[:, 0].max(), abs=1e-9)  # 0.8419, not 0.918
    assert holed.vertices[:, 0].max() == pytest.approx(0.84192, abs=1e-4)


def test_a_usd_emitter_without_units_is_warned_about_as_a_wall_is(tmp_path, caplog):
    """A USD emitter stating no metersPerUnit was read as centimetres without a word (the same file as a
    wall is warned about)."""
    import logging

    from pxr import Usd

    from pipeline.scene import MeshEmitter
    from stages.simulate.emitters import emit

    bare = Usd.Stage.CreateNew(str(tmp_path / "water.usda"))
    _define_cube(bare, "/Water", h=10.0)
    bare.GetRootLayer().Save()
    with caplog.at_level(logging.WARNING):
        x, _ = emit([MeshEmitter(mesh="water.usda")], 0.02, lambda p: tmp_path / p, 1.0,
                    logging.getLogger("t"))
    assert len(x) == 1000  # a 20 cm cube at 2 cm, as USD's centimetre fallback reads it
    assert "states no metersPerUnit and no upAxis" in caplog.text


def test_visibility_keyed_only_in_time_samples_is_read_at_the_shots_start_as_the_geometry(tmp_path, caplog):
    """A shot from code 1001 hides a plate with ``visibility.timeSamples = {1001: invisible}`` only: read at
    the default time (no value: visible) it was a wall while its points came from the first sample; a lid
    invisible at code 0 and visible from 100 was a wall too. Both are left out now, as they are at the shot's
    start, and the animated one is warned about once, naming the prim."""
    import logging

    from pxr import UsdGeom

    stage = _new_stage(tmp_path / "keyed.usda")
    stage.SetStartTimeCode(1001)
    stage.SetEndTimeCode(1100)
    _define_cube(stage, "/World/Tank", h=0.2)
    plate = _define_cube(stage, "/World/Plate", h=0.05)
    plate.CreateVisibilityAttr().Set(UsdGeom.Tokens.invisible, 1001)
    lid = _define_cube(stage, "/World/Lid", h=0.1)
    lid.CreateVisibilityAttr().Set(UsdGeom.Tokens.invisible, 0)
    lid.GetVisibilityAttr().Set(UsdGeom.Tokens.inherited, 1100)
    stage.GetRootLayer().Save()
    with caplog.at_level(logging.WARNING):
        wm = _import(tmp_path, [{"usd": "keyed.usda", "fluid": "inside"}])
    assert wm.walls[0]["report"]["prims"] == ["/World/Tank"]
    warned = [r.getMessage() for r in caplog.records if "visibility is animated" in r.getMessage()]
    assert len(warned) == 1 and "keyed.usda:/World/Lid: " in warned[0], caplog.text
    wm = _import(tmp_path, [{"usd": "keyed.usda", "fluid": "inside", "include_invisible": True}])
    assert len(wm.walls[0]["report"]["prims"]) == 3


@pytest.mark.parametrize("arc", ["reference", "payload"])
def test_a_reference_or_payload_to_a_missing_file_is_one_line_naming_layer_asset_and_prim(tmp_path, capfd, arc):
    """A set whose tank references a file moved away: USD composed on without it, printed C++ warnings and the
    tank was no wall (exit 0). Refused now in one line naming the layer, the asset and the prim, with nothing
    of USD's on stderr; a wall selecting only prims the missing file does not touch still imports."""
    from pxr import UsdGeom

    rock = _new_stage(tmp_path / "rock.usda")
    rock.SetDefaultPrim(UsdGeom.Xform.Define(rock, "/Rock").GetPrim())
    _define_cube(rock, "/Rock/Geo")
    rock.GetRootLayer().Save()
    stage = _new_stage(tmp_path / "set.usda")
    for name, asset in (("Tank", "./gone/tank.usda"), ("Rock", "./rock.usda")):
        prim = UsdGeom.Xform.Define(stage, f"/World/{name}").GetPrim()
        (prim.GetReferences().AddReference if arc == "reference" or name == "Rock" else prim.GetPayloads().AddPayload)(asset)
    stage.GetRootLayer().Save()
    capfd.readouterr()
    with pytest.raises(StageError) as e:
        _import(tmp_path, [{"usd": "set.usda"}])
    assert "\n" not in str(e.value)
    assert f"set.usda: layer {tmp_path / 'set.usda'}: the {arc} of </World/Tank>, {tmp_path / 'gone' / 'tank.usda'}, " \
        "cannot be opened" in str(e.value), str(e.value)
    assert "Could not open" not in capfd.readouterr().err
    wm = _import(tmp_path, [{"usd": "set.usda", "prims": ["/World/Rock"]}])
    assert wm.walls[0]["report"]["prims"] == ["/World/Rock/Geo"]
