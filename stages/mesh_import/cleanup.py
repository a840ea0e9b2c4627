"""Mesh clean-up with a report: weld, drop degenerate and duplicate faces, count defects, fix winding."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # imported where used (about 1 s); here for the annotations only
    import trimesh


def clean_mesh(mesh: trimesh.Trimesh, weld_tolerance: float) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """Return the cleaned mesh and a report (counts of what was found and changed).

    ``weld_tolerance`` (scene units) is the distance under which vertices count as duplicates.
    Winding is made consistent per connected piece where the piece is orientable (trimesh), and a
    closed piece is turned outward (positive volume); the caller flips containers afterwards.
    """
    import trimesh  # imported where used: a cached run or `pipeline status` need not load it (~1 s)
    report: dict[str, Any] = {"vertices_in": int(len(mesh.vertices)), "faces_in": int(len(mesh.faces))}
    v = np.asarray(mesh.vertices, np.float64)
    keep, inverse = weld(v, weld_tolerance)
    m = trimesh.Trimesh(v[keep], inverse[np.asarray(mesh.faces, np.int64)], process=False)
    n_v = len(v)
    m.remove_unreferenced_vertices()
    report["welded_vertices"] = int(n_v - len(m.vertices))

    areas = m.area_faces
    keep = (areas > (weld_tolerance ** 2) * 1e-6) & m.nondegenerate_faces()
    report["degenerate_faces_removed"] = int((~keep).sum())
    m.update_faces(keep)
    n_f = len(m.faces)
    m.update_faces(m.unique_faces())
    report["duplicate_faces_removed"] = int(n_f - len(m.faces))
    m.remove_unreferenced_vertices()

    edges = np.sort(m.edges, axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    report["boundary_edges"] = int((counts == 1).sum())
    report["largest_hole"] = _largest_hole(m.vertices, unique[counts == 1])
    report["non_manifold_edges"] = int((counts > 2).sum())
    report["winding_consistent_in"] = bool(m.is_winding_consistent)
    if len(m.faces):
        trimesh.repair.fix_winding(m)
        if m.is_watertight and m.volume < 0:
            m.invert()
    report["winding_consistent"] = bool(m.is_winding_consistent)
    report["watertight"] = bool(m.is_watertight)
    report["components"] = int(len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(m.faces)))))
    report["vertices"] = int(len(m.vertices))
    report["faces"] = int(len(m.faces))
    return m, report


def weld(vertices: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(kept (K,) vertex indices, (N,) index into kept of each vertex): every pair closer than
    ``tolerance`` is one vertex, chains of them too (the first vertex of each cluster stays). Rounding to
    decimal digits left duplicates a float32 ulp apart unwelded where they straddled a rounding boundary."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(vertices)
    pairs = cKDTree(vertices).query_pairs(tolerance, output_type="ndarray") if n else np.zeros((0, 2), np.int64)
    if len(pairs) == 0:
        return np.arange(n), np.arange(n)
    # clusters of the "closer than tolerance" graph (union-find): labels in order of first vertex
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    _, keep, inverse = np.unique(label, return_index=True, return_inverse=True)
    order = np.argsort(keep)  # kept vertices in file order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return keep[order], rank[inverse.reshape(-1)]


def _largest_hole(vertices: np.ndarray, boundary: np.ndarray) -> float:
    """The width (bounding-box diagonal, scene units) of the largest loop of boundary edges: how wide
    an opening of the mesh is; 0 for a closed mesh."""
    if len(boundary) == 0:
        return 0.0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ids, inverse = np.unique(boundary, return_inverse=True)
    inverse = inverse.reshape(boundary.shape)
    graph = coo_matrix((np.ones(len(boundary)), (inverse[:, 0], inverse[:, 1])), shape=(len(ids), len(ids)))
    _, label = connected_components(graph, directed=False)
    pts = np.asarray(vertices)[ids]
    widest = 0.0
    for loop in np.unique(label):
        p = pts[label == loop]
        widest = max(widest, float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))))
    return widest
