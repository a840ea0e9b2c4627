"""Small triangle-mesh helpers shared by surface_extract and wall_snap."""
from __future__ import annotations

import numpy as np


def signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    """Volume enclosed by a closed mesh; positive when the faces are oriented outwards."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (length = twice the area)."""
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (zero for isolated vertices)."""
    fn = face_normals(v, f)
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def boundary_edge_count(f: np.ndarray) -> int:
    """Edges used by one triangle only (0 for a closed mesh)."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())
