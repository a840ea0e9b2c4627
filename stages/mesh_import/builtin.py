"""Analytic built-in walls (box_tank, open_box, cylinder, plane) as triangle meshes.

Geometry is built with the scene's up axis: ``center`` is the centre of the footprint at the floor and
``size`` the extent along (x, y, z) (cylinder: the two horizontal diameters, then the height).
Meshes come out with outward normals of the solid they bound; the caller orients them for the fluid.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pipeline.scene import BuiltinWall

if TYPE_CHECKING:  # imported where used; here for the annotations only
    import trimesh


def _axes(up_axis: str) -> tuple[int, int, int]:
    """Indices of (horizontal 1, horizontal 2, up)."""
    return (0, 2, 1) if up_axis == "Y" else (0, 1, 2)


def _box(lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh:
    import trimesh  # imported where used: a cached run or `pipeline status` need not load it (~1 s)
    return trimesh.creation.box(bounds=np.stack([lo, hi]))


def _bounds(wall: BuiltinWall, up_axis: str) -> tuple[np.ndarray, np.ndarray]:
    a, b, u = _axes(up_axis)
    c = np.asarray(wall.center, np.float64)
    s = np.asarray(wall.size, np.float64)
    lo, hi = c - 0.5 * s, c + 0.5 * s
    lo[u], hi[u] = c[u], c[u] + s[u]
    return lo, hi


def builtin_mesh(wall: BuiltinWall, up_axis: str, open_box_thickness: float) -> tuple[trimesh.Trimesh, str]:
    """The wall's mesh and the side of it the fluid is on, as sdf_bake should treat it.

    box_tank / cylinder: closed surfaces, fluid on the wall's ``fluid`` side (default inside).
    open_box: a zero-thickness open box has no inside/outside, so it is built as a solid with walls
    ``open_box_thickness`` (fraction of the smallest horizontal size) thick; the fluid is everywhere
    outside that solid: in the box, above the rim and around it ("outside").
    plane: a thick slab below the floor level (solid ground), fluid above it.
    """
    import trimesh
    a, b, u = _axes(up_axis)
    lo, hi = _bounds(wall, up_axis)
    if wall.builtin == "box_tank":
        return _box(lo, hi), wall.fluid
    if wall.builtin == "cylinder":
        d = np.asarray(wall.size, np.float64)
        height = d[u] if up_axis == "Z" else d[2]
        radius = 0.5
        cyl = trimesh.creation.cylinder(radius=radius, height=1.0, sections=64)
        # unit cylinder along z centred at 0 -> floor at 0, then stretch to the two diameters
        cyl.apply_translation([0, 0, 0.5])
        scale = np.eye(4)
        scale[0, 0], scale[1, 1], scale[2, 2] = wall.size[0], wall.size[1], height
        cyl.apply_transform(scale)
        if up_axis == "Y":
            cyl.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
        cyl.apply_translation(np.asarray(wall.center, np.float64))
        return cyl, wall.fluid
    if wall.builtin == "open_box":
        t = open_box_thickness * min(hi[a] - lo[a], hi[b] - lo[b])
        return _open_box(lo, hi, t, (a, b, u)), "outside"
    if wall.builtin == "plane":
        # a slab as wide as ``size`` and as deep as the size along the up axis, top face at center
        lo2, hi2 = lo.copy(), hi.copy()
        lo2[u], hi2[u] = lo[u] - (hi[u] - lo[u]), lo[u]
        return _box(lo2, hi2), "outside"
    raise ValueError(f"unknown builtin wall {wall.builtin!r}")


def _open_box(lo: np.ndarray, hi: np.ndarray, t: float, axes: tuple[int, int, int]) -> trimesh.Trimesh:
    """A closed, manifold solid: the box [lo, hi] minus its interior shrunk by ``t`` on the sides and
    the floor and open at the top. Built from quads; the winding is made outward afterwards."""
    import trimesh
    a, b, u = axes

    def rect(x0, x1, y0, y1, z):
        out = np.zeros((4, 3))
        for i, (x, y) in enumerate(((x0, y0), (x1, y0), (x1, y1), (x0, y1))):
            out[i, a], out[i, b], out[i, u] = x, y, z
        return out

    outer = (lo[a], hi[a], lo[b], hi[b])
    inner = (lo[a] + t, hi[a] - t, lo[b] + t, hi[b] - t)
    v = np.concatenate([rect(*outer, lo[u]), rect(*outer, hi[u]), rect(*inner, hi[u]), rect(*inner, lo[u] + t)])
    O, T, I, F = 0, 4, 8, 12
    quads = [(O + 0, O + 1, O + 2, O + 3), (F + 0, F + 1, F + 2, F + 3)]
    for i in range(4):
        j = (i + 1) % 4
        quads += [(O + i, O + j, T + j, T + i), (T + i, T + j, I + j, I + i), (I + i, I + j, F + j, F + i)]
    faces = [(q[0], q[1], q[2]) for q in quads] + [(q[0], q[2], q[3]) for q in quads]
    mesh = trimesh.Trimesh(v, np.asarray(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def builtin_box(wall: BuiltinWall, up_axis: str) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box builtin_mesh's mesh spans before placement, without building it (for the
    size estimate before the run; tests/test_mesh_import checks it against the meshes)."""
    lo, hi = _bounds(wall, up_axis)
    if wall.builtin == "cylinder" and up_axis == "Y":  # (diameter, diameter, height) whatever the up axis
        c, s = np.asarray(wall.center, np.float64), np.asarray(wall.size, np.float64)
        return c + [-0.5 * s[0], 0.0, -0.5 * s[1]], c + [0.5 * s[0], s[2], 0.5 * s[1]]
    if wall.builtin == "plane":  # the slab below the floor level
        u = _axes(up_axis)[2]
        lo[u], hi[u] = lo[u] - (hi[u] - lo[u]), lo[u]
    return lo, hi


def builtin_corners(walls: list, up_axis: str) -> np.ndarray | None:
    """(8 per wall, 3) the placed corners of the builtin walls' boxes (builtin_box), whose bounds are
    the walls' bounds (exact but for a rotated cylinder, whose box's corners lie outside it); None
    when a wall is read from a file (its bounds are known once mesh_import has read it)."""
    from stages.common.placement import apply_placement

    out = []
    for w in walls:
        if not isinstance(w, BuiltinWall):
            return None
        lo, hi = builtin_box(w, up_axis)
        corners = np.array([[(lo, hi)[(k >> i) & 1][i] for i in range(3)] for k in range(8)])
        if w.fit is None and not any(w.rotate):  # as placement_matrix, without importing trimesh (~1 s)
            out.append(corners * np.asarray(w.scale, np.float64) + np.asarray(w.translate, np.float64))
        else:
            out.append(apply_placement(corners, w))
    return np.concatenate(out) if out else np.zeros((0, 3))
