"""Placement (scale, rotate, fit, translate) and unit / up-axis conversion as 4x4 matrices."""
from __future__ import annotations

import numpy as np

from pipeline.scene import Placement


def up_axis_matrix(src: str, dst: str) -> np.ndarray:
    """Rotation taking a ``src``-up frame to a ``dst``-up frame (right-handed, +90 deg about X for Y->Z)."""
    import trimesh  # imported where used: a cached run or `pipeline status` need not load it (~1 s)
    if src == dst:
        return np.eye(4)
    angle = np.pi / 2 if (src, dst) == ("Y", "Z") else -np.pi / 2
    return trimesh.transformations.rotation_matrix(angle, [1.0, 0.0, 0.0])


def rotation_xyz(degrees) -> np.ndarray:
    """3x3 rotation of the config's ``rotate: [x, y, z]``: degrees about X, then Y, then Z (fixed axes,
    i.e. Rz @ Ry @ Rx): the one conversion of a config rotation (placement and motion keyframes)."""
    rx, ry, rz = np.radians(np.asarray(degrees, np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    z = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return z @ y @ x


def placement_matrix(vertices: np.ndarray, p: Placement) -> np.ndarray:
    """4x4 matrix (column vectors) of the placement: scale, then rotate about X, Y, Z (degrees), then
    fit into ``p.fit`` (uniform scale, centred on the box of ``vertices`` after rotation), then
    translate. All about the model's own origin."""
    m = np.eye(4)
    m[:3, :3] = rotation_xyz(p.rotate) @ np.diag(
        np.broadcast_to(np.asarray(p.scale, np.float64), (3,)))
    v = np.asarray(vertices, np.float64)
    if p.fit is not None and len(v):
        w = v @ m[:3, :3].T
        lo, hi = w.min(axis=0), w.max(axis=0)
        flo, fhi = np.asarray(p.fit.min, np.float64), np.asarray(p.fit.max, np.float64)
        ext = np.where(hi - lo > 0, hi - lo, np.inf)
        s = float(np.min((fhi - flo) / ext))
        fit = np.eye(4)
        fit[:3, :3] *= s
        fit[:3, 3] = 0.5 * (flo + fhi) - s * 0.5 * (lo + hi)
        m = fit @ m
    m[:3, 3] += np.asarray(p.translate, np.float64)
    return m


def apply_placement(vertices: np.ndarray, p: Placement) -> np.ndarray:
    """The vertices placed by ``placement_matrix``."""
    m = placement_matrix(vertices, p)
    return np.asarray(vertices, np.float64) @ m[:3, :3].T + m[:3, 3]
