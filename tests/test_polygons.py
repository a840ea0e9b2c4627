"""Polygon triangulation of mesh import: concave n-gons (USD, OBJ, PLY, OFF) are not fanned across their notch;
polygons whose fan is right keep it exactly."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.scene import UsdWall
from pipeline.stage import StageError
from pipeline.testing import run_stage
from stages.common.formats import WallMesh
from stages.mesh_import import polygons
from stages.mesh_import.polygons import newell_normals, triangulate
from stages.mesh_import.trimesh_import import TrimeshImport, read_mesh_file
from stages.mesh_import.usd_import import _triangulate, read_usd_wall

# L-shaped block, metres: 20 x 16 cm minus a 10 x 8 cm notch at x > 0, y > 0, 5 cm tall
L_XY = [(-0.1, -0.08), (0.1, -0.08), (0.1, 0.0), (0.0, 0.0), (0.0, 0.08), (-0.1, 0.08)]  # (0, 0) is reflex
H = 0.05
L_AREA = 2 * (0.2 * 0.16 - 0.1 * 0.08) + 0.72 * H  # 840 cm^2: two caps and the walls (perimeter 72 cm)
L_VOLUME = (0.2 * 0.16 - 0.1 * 0.08) * H


def _l_prism(start):
    """Points and polygons (0-based) of the L-prism, its caps starting at vertex ``start`` of the L."""
    pts = [(x, y, 0.0) for x, y in L_XY] + [(x, y, H) for x, y in L_XY]
    sides = [[i, (i + 1) % 6, (i + 1) % 6 + 6, i + 6] for i in range(6)]  # outward
    top = [6 + (start + k) % 6 for k in range(6)]  # counter-clockwise seen from above: outward
    bottom = [(start - k) % 6 for k in range(6)]  # clockwise seen from above: outward
    return np.array(pts), sides + [top, bottom]


def _obj(pts, faces, negative=False, extras=False):
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in pts]
    if extras:
        lines += ["vt 0 0", "vn 0 0 1", "o L", "g caps", "usemtl steel", "s off", "# comment"]
    for k, f in enumerate(faces):
        if extras and k == 3:
            lines.append("g sides")
        ids = [i - len(pts) if negative else i + 1 for i in f]
        lines.append("f " + " ".join(f"{i}/1/1" if extras else str(i) for i in ids))
    return "\n".join(lines) + "\n"


def _usda(pts, faces, orientation=None):
    counts = ", ".join(str(len(f)) for f in faces)
    idx = ", ".join(str(i) for f in faces for i in f)
    points = ", ".join(f"({x:.17g}, {y:.17g}, {z:.17g})" for x, y, z in pts)
    orient = f'\n        uniform token orientation = "{orientation}"' if orientation else ""
    return (f'#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n    upAxis = "Z"\n)\n\n'
            f'def Xform "World"\n{{\n    def Mesh "L"\n    {{\n        int[] faceVertexCounts = [{counts}]\n'
            f'        int[] faceVertexIndices = [{idx}]\n        point3f[] points = [{points}]{orient}\n'
            f'        uniform token subdivisionScheme = "none"\n    }}\n}}\n')


def _ply(pts, faces):
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    return head + "".join(f"{x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in pts) + \
        "".join(f"{len(f)} " + " ".join(map(str, f)) + "\n" for f in faces)


def _off(pts, faces):
    return (f"OFF\n# an L prism\n{len(pts)} {len(faces)} 0\n" + "".join(f"{x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in pts)
            + "".join(f"{len(f)} " + " ".join(map(str, f)) + " 200 200 200\n" for f in faces))


def _import(tmp_path, wall):
    out = run_stage(TrimeshImport, tmp_path / "out", scene={"scene": {"name": "t", "units": {"up_axis": "Z"}},
                                                              "walls": [wall]}, params={}, config_dir=tmp_path)
    return WallMesh.load(out)


def _old_fan(counts, indices):
    """The triangulation mesh_import used before: a fan from each polygon's first vertex."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tri = counts - 2
    face_of_tri = np.repeat(np.arange(len(counts)), n_tri)
    k = np.arange(len(face_of_tri)) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    s = starts[face_of_tri]
    return np.stack([indices[s], indices[s + k + 1], indices[s + k + 2]], axis=1)


def _usd_tris(pts, counts, idx):
    return _triangulate(np.asarray(counts), np.asarray(idx), np.zeros(0, np.int64), "t", pts)


def _flat(faces):
    return np.array([len(f) for f in faces]), np.array([i for f in faces for i in f])


@pytest.mark.parametrize("fmt", ["usda", "obj", "ply", "off"])
@pytest.mark.parametrize("start", range(6))
def test_l_prism_has_no_wall_across_its_notch_whatever_vertex_its_caps_start_at(tmp_path, fmt, start):
    pts, faces = _l_prism(start)
    text = {"usda": _usda, "obj": _obj, "ply": _ply, "off": _off}[fmt](pts, faces)
    (tmp_path / f"l.{fmt}").write_text(text)
    wm = _import(tmp_path, {"usd": "l.usda"} if fmt == "usda" else {"file": f"l.{fmt}"})
    m = trimesh.Trimesh(wm.vertices, wm.faces, process=False)
    assert m.area == pytest.approx(L_AREA, rel=1e-6)  # a fan from (0.1, 0) or (0, 0.08) gave 1000 cm^2
    assert m.volume == pytest.approx(L_VOLUME, rel=1e-6)  # solid, normals outward
    r = wm.walls[0]["report"]
    assert r["watertight"] and r["winding_consistent_in"] and r["boundary_edges"] == 0 and r["non_manifold_edges"] == 0
    c = m.triangles_center
    assert not ((c[:, 0] > 1e-9) & (c[:, 1] > 1e-9)).any()  # nothing in the notch x > 0, y > 0
    # as read, before the clean-up fixes any winding: the authored (outward) winding is kept
    path = tmp_path / f"l.{fmt}"
    v, f = read_usd_wall(path, UsdWall(usd=str(path)), 1.0, "Z")[:2] if fmt == "usda" else read_mesh_file(path)
    raw = trimesh.Trimesh(v, f, process=False)
    assert raw.is_winding_consistent and raw.volume == pytest.approx(L_VOLUME, rel=1e-6)


@pytest.mark.parametrize("start", range(6))
def test_concave_cap_triangles_cover_it_once_with_its_winding(start):
    pts, faces = _l_prism(start)
    counts, idx = _flat(faces)
    tris = _triangulate(counts, idx, np.zeros(0, np.int64), "t", pts)
    assert tris.shape == (6 * 2 + 2 * 4, 3)
    assert np.array_equal(tris[:12], _old_fan(counts[:6], idx[:24]))  # the side quads: their fans
    # both caps: four triangles, all facing as the polygon (top up, bottom down), areas adding up to it
    for cap, up in ((tris[12:16], 1.0), (tris[16:20], -1.0)):
        assert set(cap.ravel()) <= set(range(6, 12) if up > 0 else range(6))
        n = np.cross(pts[cap[:, 1]] - pts[cap[:, 0]], pts[cap[:, 2]] - pts[cap[:, 0]])
        assert (n[:, 2] * up > 0).all() and np.allclose(n[:, :2], 0)
        assert 0.5 * np.abs(n[:, 2]).sum() == pytest.approx(0.2 * 0.16 - 0.1 * 0.08)


def test_left_handed_usd_l_prism_is_closed_and_correct(tmp_path):
    pts, faces = _l_prism(2)
    (tmp_path / "l.usda").write_text(_usda(pts, [f[::-1] for f in faces], orientation="leftHanded"))
    v, f = read_usd_wall(tmp_path / "l.usda", UsdWall(usd="l.usda"), 1.0, "Z")[:2]
    m = trimesh.Trimesh(v, f, process=False)
    assert m.area == pytest.approx(L_AREA) and m.is_watertight and m.volume == pytest.approx(L_VOLUME)


@pytest.mark.parametrize("negative, extras", [(True, False), (False, True)])  # trimesh reads no "-1/1/1"
def test_obj_groups_negative_indices_and_texture_slashes(tmp_path, negative, extras):
    pts, faces = _l_prism(1)
    (tmp_path / "l.obj").write_text(_obj(pts, faces, negative=negative, extras=extras))
    v, f = read_mesh_file(tmp_path / "l.obj")
    m = trimesh.Trimesh(v, f, process=False)
    assert len(f) == 20 and m.area == pytest.approx(L_AREA) and m.is_watertight and m.is_winding_consistent
    assert m.volume == pytest.approx(L_VOLUME)


def test_concave_dart_quad_out_of_plane_is_split_at_its_reflex_corner():
    # an arrowhead seen from +z, corner 1 reflex, corner 3 lifted: the fan's diagonal 0-2 runs outside it
    pts = np.array([[0, 0, 0], [1, 0.3, 0], [2, 0, 0], [1, 1, 0.05]], float)
    for start in range(4):
        ring = np.roll(np.arange(4), -start)
        tris = _usd_tris(pts, [4], ring)
        assert sorted(map(sorted, tris.tolist())) == [[0, 1, 3], [1, 2, 3]]  # diagonal 1-3
        n = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
        assert (n @ newell_normals(pts, np.array([4]), ring)[0] > 0).all()


def test_convex_non_planar_quad_keeps_its_fan():
    pts = np.array([[0, 0, 0], [1, 0, 0.1], [1, 1, 0], [0, 1, 0.1]], float)
    counts, idx = np.array([4]), np.array([0, 1, 2, 3])
    assert np.array_equal(triangulate(pts, counts, idx)[0], _old_fan(counts, idx))


@pytest.mark.parametrize("start", range(8))
def test_collinear_vertices_give_no_sliver(start):
    # a 2 x 1 rectangle with a vertex in the middle of every side: a fan from a corner made a
    # zero-area triangle (corner, midpoint, next corner) that clean-up dropped, cracking the mesh
    ring = [(0, 0), (1, 0), (2, 0), (2, 0.5), (2, 1), (1, 1), (0, 1), (0, 0.5)]
    pts = np.array([(x, y, 0.0) for x, y in ring])
    idx = np.roll(np.arange(8), -start)
    tris = _usd_tris(pts, [8], idx)
    n = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])[:, 2]
    assert len(tris) == 6 and (n > 1e-9).all() and 0.5 * n.sum() == pytest.approx(2.0)
    # the outline is exactly the polygon's edges: no T-junction
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    e, c = np.unique(edges, axis=0, return_counts=True)
    assert {tuple(x) for x in e[c == 1]} == {tuple(sorted((i, (i + 1) % 8))) for i in range(8)}


def test_cube_with_a_split_edge_stays_watertight(tmp_path):
    # top and front faces share the midpoint 9 of their common edge; the top face starts at the corner
    # before it, so its fan began with the zero-area triangle (corner, midpoint, corner)
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1), (0.5, 0, 1)]
    faces = [[0, 3, 2, 1], [4, 8, 5, 6, 7], [0, 1, 5, 8, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    (tmp_path / "c.obj").write_text(_obj(pts, faces))
    wm = _import(tmp_path, {"file": "c.obj"})
    r = wm.walls[0]["report"]
    assert r["watertight"] and r["degenerate_faces_removed"] == 0
    assert trimesh.Trimesh(wm.vertices, wm.faces, process=False).volume == pytest.approx(1.0)


@pytest.mark.parametrize("face", [[0, 1, 2, 2], [0, 1, 1, 2, 3], [0, 2, 1, 2, 3], [0, 0, 0, 0], [0, 1, 4, 5]])
def test_degenerate_polygons_do_not_crash(face):
    # repeated vertices, a polygon touching itself, all vertices at one point, all on one line
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]], float)
    tris, f = triangulate(pts, np.array([len(face)]), np.array(face))
    assert tris.shape == (len(face) - 2, 3) and set(tris.ravel()) <= set(face) and (f == 0).all()


def test_repeated_vertex_in_an_obj_face_still_imports_closed(tmp_path):
    pts, faces = _l_prism(3)
    faces[6] = faces[6][:2] + [faces[6][1]] + faces[6][2:]  # the top cap repeats a vertex
    (tmp_path / "l.obj").write_text(_obj(pts, faces))
    wm = _import(tmp_path, {"file": "l.obj"})
    m = trimesh.Trimesh(wm.vertices, wm.faces, process=False)
    assert wm.walls[0]["report"]["watertight"] and m.area == pytest.approx(L_AREA)


def test_convex_polygons_keep_exactly_the_old_fan():
    rng = np.random.default_rng(1)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pts, counts, idx = [], [], []
    for n in [3, 4, 5, 6, 7, 12, 40, 3, 4]:
        a = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.3, 0.3, n) * np.pi / n
        p = np.stack([np.cos(a), np.sin(a), 0.01 * rng.normal(size=n)], 1) @ rot.T * 3 + [100, -7, 0.5]
        ring = np.roll(np.arange(n), -int(rng.integers(n))) + len(pts)  # a random first vertex
        pts += p.tolist()
        counts.append(n)
        idx += ring.tolist()
    pts, counts, idx = np.array(pts), np.array(counts), np.array(idx)
    holes = np.array([2])
    old = _old_fan(counts, idx)
    keep = np.repeat(np.arange(len(counts)), counts - 2) != 2
    assert np.array_equal(_triangulate(counts, idx, holes, "t", pts), old[keep])
    # the L's cap starting at its reflex corner fans correctly: kept as well
    lp, lf = _l_prism(3)
    lc, li = _flat(lf[6:7])
    assert np.array_equal(triangulate(lp, lc, li)[0], _old_fan(lc, li))


def test_obj_and_ply_of_convex_polygons_read_as_trimesh_reads_them(tmp_path):
    pts = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)], float)
    quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    # quads, then an object of triangles (the top), then quads again
    text = _obj(pts, [quads[0]]) + "o second\nf 5 6 7\nf 5 7 8\no third\n" + "".join(
        "f " + " ".join(str(i + 1) for i in q) + "\n" for q in quads[2:])
    for name, body in (("b.obj", text), ("b.ply", _ply(pts, quads)), ("b.off", _off(pts, quads))):
        (tmp_path / name).write_text(body)
        loaded = trimesh.load(str(tmp_path / name), force="mesh", process=False, maintain_order=True)
        v, f = read_mesh_file(tmp_path / name)
        assert np.array_equal(v, loaded.vertices)
        if name == "b.off":  # read by polygons.off_polygons: the same triangles, in polygon order
            assert _canonical(f) == _canonical(loaded.faces)
        else:
            assert np.array_equal(f, loaded.faces)


def _canonical(faces):
    """The triangles as a set, each rotated to start at its smallest index (the winding kept)."""
    return {tuple(np.roll(t, -int(np.argmin(t)))) for t in np.asarray(faces).tolist()}


def test_big_concave_polygon_compiled_and_python_ear_clipping_agree():
    # a comb: 60 teeth, 242 vertices, past the plain-Python limit
    # teeth over x in [2i, 2i + 1] up to y = 1, gaps between them down to y = 0.2
    ring = [(0.0, 0.0), (120.0, 0.0)] + [p for i in range(59, -1, -1)
                                        for p in ((2 * i + 2, 0.2), (2 * i + 1, 0.2), (2 * i + 1, 1.0), (2 * i, 1.0))]
    pts = np.array([(x, y, 0.0) for x, y in ring])
    n = len(pts)
    counts, idx = np.array([n]), np.roll(np.arange(n), -5)
    assert n * n > polygons.PYTHON_WORK
    tris, _ = triangulate(pts, counts, idx)
    area = 0.5 * np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])[:, 2]
    outline = 0.5 * np.cross(pts, np.roll(pts, -1, axis=0))[:, 2].sum()
    assert (area > 0).all() and area.sum() == pytest.approx(outline)
    xy = pts[idx, :2].copy()
    args = (xy, np.array([0]), counts)
    assert np.array_equal(polygons._ear_clip(*args), polygons._ear_clip_compiled()(*args))


def test_off_face_index_out_of_range_is_one_line(tmp_path):
    (tmp_path / "bad.off").write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 9\n")
    with pytest.raises(StageError, match=r"bad\.off: cannot read as OFF \(face index 9 out of range \(only 4 vertices\)\)"):
        read_mesh_file(tmp_path / "bad.off")


@pytest.mark.parametrize("eol", ["\n", "\r\n"])
def test_obj_faces_continued_by_a_backslash_are_read_and_a_stray_token_names_its_line(tmp_path, eol):
    """The OBJ spec continues a line ending in a backslash: `f 1 20 4 19 \\` then `3 18 2 17` gave exit 1 from an
    int() of the backslash. Joined, the L-prism reads as unwrapped; a token that is still no face vertex is
    refused in one line naming the file and the line it is on."""
    pts, faces = _l_prism(2)
    lines = _obj(pts, faces).splitlines()
    wrapped = [f"{line[:line.index(' ', 2)]} \\{eol}   {line[line.index(' ', 2) + 1:]}" if line.startswith("f ") else line
               for line in lines]
    (tmp_path / "l.obj").write_bytes((eol.join(wrapped) + eol).encode())
    assert b"\\" + eol.encode() + b"   " in (tmp_path / "l.obj").read_bytes()
    v, f = read_mesh_file(tmp_path / "l.obj")
    m = trimesh.Trimesh(v, f, process=False)
    assert len(f) == 20 and m.area == pytest.approx(L_AREA) and m.is_watertight and m.volume == pytest.approx(L_VOLUME)
    # a backslash inside a face (no continuation), and a word: named with the file and line (12 vertices first)
    for bad in ("f 1 2 \\ 3", "f 1 2 x"):
        (tmp_path / "bad.obj").write_text("\n".join(lines[:12] + ["f 1 2 3", bad, "f 4 5 6"]) + "\n")
        with pytest.raises(StageError, match=r"bad\.obj: line 14: '.' is not a face vertex") as err:
            read_mesh_file(tmp_path / "bad.obj")
        assert "\n" not in str(err.value)


_PLY_NP = {"uchar": "u1", "ushort": "u2", "int": "i4", "uint": "u4", "float": "f4", "double": "f8"}


def _ply_binary(pts, faces, endian, count="uchar", index="uint", xyz="float", before=(), after=(), face_flags=False):
    """A binary PLY of the polygons, with vertex properties ``before`` and ``after`` x y z (name, type) and,
    with ``face_flags``, a ushort per face around its index list (as some exporters write)."""
    e = "<" if endian == "little" else ">"
    props = list(before) + [(k, xyz) for k in "xyz"] + list(after)
    vert = np.zeros(len(pts), [(k, e + _PLY_NP[t]) for k, t in props])
    for k, c in zip("xyz", np.asarray(pts).T):
        vert[k] = c
    for k, _ in list(before) + list(after):
        vert[k] = 7
    head = (f"ply\nformat binary_{endian}_endian 1.0\ncomment made by a test\nelement vertex {len(pts)}\n"
            + "".join(f"property {t} {k}\n" for k, t in props) + f"element face {len(faces)}\n"
            + ("property ushort flags\n" if face_flags else "")
            + f"property list {count} {index} vertex_indices\n" + ("property uchar tag\n" if face_flags else "")
            + "end_header\n")
    body = b"".join((np.array([1], e + "u2").tobytes() if face_flags else b"")
                    + np.array([len(f)], e + _PLY_NP[count]).tobytes() + np.array(f, e + _PLY_NP[index]).tobytes()
                    + (b"\x05" if face_flags else b"") for f in faces)
    return head.encode() + vert.tobytes() + body


@pytest.mark.parametrize("endian, count, index, xyz, before, after, flags", [
    ("little", "uchar", "uint", "float", (), (), False),  # Blender's
    ("big", "uchar", "int", "float", (), (), False),
    ("little", "ushort", "int", "double", [("nx", "float"), ("ny", "float"), ("nz", "float")],
     [("red", "uchar"), ("green", "uchar"), ("blue", "uchar"), ("alpha", "uchar")], True),
    ("big", "int", "uint", "float", [("red", "uchar")], [("nx", "double"), ("s", "float")], True),
], ids=["blender", "big_endian", "normals_colours_flags", "big_endian_int_counts"])
def test_binary_ply_of_quads_and_hexagons_reads_as_the_ascii_one(tmp_path, endian, count, index, xyz, before, after,
                                                                flags):
    """trimesh's binary PLY reader takes every face list to be as long as the first: Blender's binary export of
    quads and triangles was refused as damaged ('PLY is unexpected length!'), though the ASCII file of the same
    mesh loaded. Mixed sizes are read here now, polygons triangulated as any others: the L-prism of quads and
    concave hexagons comes in closed, without a wall across its notch, as its ASCII PLY does; cut short, the
    file is refused in one line naming it."""
    pts, faces = _l_prism(1)
    data = _ply_binary(pts, faces, endian, count, index, xyz, before, after, flags)
    (tmp_path / "l.ply").write_bytes(data)
    (tmp_path / "ascii.ply").write_text(_ply(pts, faces))
    v, f = read_mesh_file(tmp_path / "l.ply")
    va, fa = read_mesh_file(tmp_path / "ascii.ply")
    np.testing.assert_allclose(v, va, atol=1e-7)  # float32 in the binary file
    assert _canonical(f) == _canonical(fa)
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume == pytest.approx(L_VOLUME, rel=1e-6)
    wm = _import(tmp_path, {"file": "l.ply"})
    c = trimesh.Trimesh(wm.vertices, wm.faces, process=False).triangles_center
    assert not ((c[:, 0] > 1e-9) & (c[:, 1] > 1e-9)).any()
    for cut in (len(data) - 3, len(data) - 40, len(data) - 200):  # in the faces, and in the vertices
        (tmp_path / "cut.ply").write_bytes(data[:cut])
        with pytest.raises(StageError, match=r"cut\.ply: cannot read as PLY \(binary PLY cut off") as err:
            read_mesh_file(tmp_path / "cut.ply")
        assert "\n" not in str(err.value)


@pytest.mark.parametrize("endian", ["little", "big"])
def test_a_binary_ply_of_triangles_with_bytes_after_its_data_is_read_and_said(tmp_path, caplog, endian):
    """A binary PLY of triangles with padding after its faces (an exporter's or a copy's) was refused by trimesh
    as 'PLY is unexpected length!'; its data is whole, so it is read, and the bytes after it said in one line."""
    import logging

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    data = _ply_binary(box.vertices, box.faces.tolist(), endian)
    (tmp_path / "plain.ply").write_bytes(data)
    (tmp_path / "padded.ply").write_bytes(data + b"\n\0\0\0junk")
    v0, f0 = read_mesh_file(tmp_path / "plain.ply")
    with caplog.at_level(logging.WARNING):
        v, f = read_mesh_file(tmp_path / "padded.ply")
    np.testing.assert_array_equal(v, v0)
    np.testing.assert_array_equal(f, f0)
    assert trimesh.Trimesh(v, f, process=False).volume == pytest.approx(6.0)
    assert [r.getMessage() for r in caplog.records] == [f"{tmp_path / 'padded.ply'}: 8 bytes after the data its PLY "
                                                        "header declares: ignored"]
