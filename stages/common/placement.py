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


def placement_matrix(vertices: np.ndarray, p: Placement) -> np.ndarray:
    """4x4 matrix (column vectors) of the placement: scale, then rotate about X, Y, Z (degrees), then
    fit into ``p.fit`` (uniform scale, centred on the box of ``vertices`` after rotation), then
    translate. All about the model's own origin."""
    import trimesh
    m = np.eye(4)
    rx, ry, rz = np.radians(p.rotate)
    m[:3, :3] = trimesh.transformations.euler_matrix(rx, ry, rz, axes="sxyz")[:3, :3] @ np.diag(
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
