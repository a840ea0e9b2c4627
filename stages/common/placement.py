"""Placement (scale, rotate, fit, translate) and unit / up-axis conversion as 4x4 matrices."""
from __future__ import annotations

import numpy as np
import trimesh

from pipeline.scene import Placement


def up_axis_matrix(src: str, dst: str) -> np.ndarray:
    """Rotation taking a ``src``-up frame to a ``dst``-up frame (right-handed, +90 deg about X for Y->Z)."""
    if src == dst:
        return np.eye(4)
    angle = np.pi / 2 if (src, dst) == ("Y", "Z") else -np.pi / 2
    return trimesh.transformations.rotation_matrix(angle, [1.0, 0.0, 0.0])


def apply_placement(vertices: np.ndarray, p: Placement) -> np.ndarray:
    """Scale, then rotate about X, Y, Z (degrees), then fit into ``p.fit`` (uniform scale, centred),
    then translate. All about the model's own origin."""
    v = np.asarray(vertices, np.float64) * np.broadcast_to(np.asarray(p.scale, np.float64), (3,))
    rx, ry, rz = np.radians(p.rotate)
    r = trimesh.transformations.euler_matrix(rx, ry, rz, axes="sxyz")[:3, :3]
    v = v @ r.T
    if p.fit is not None and len(v):
        lo, hi = v.min(axis=0), v.max(axis=0)
        flo, fhi = np.asarray(p.fit.min), np.asarray(p.fit.max)
        ext = np.where(hi - lo > 0, hi - lo, np.inf)
        s = float(np.min((fhi - flo) / ext))
        v = (v - 0.5 * (lo + hi)) * s + 0.5 * (flo + fhi)
    return v + np.asarray(p.translate, np.float64)
