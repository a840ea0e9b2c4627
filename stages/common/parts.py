"""The parts of a wall mesh: sets of triangles joined across edges.

Two triangles are joined across an edge only they use; a shared vertex, or an edge more triangles use (four
where two boxes share it), joins nothing, and open pieces whose free edges meet once each way are joined again
(a box whose every bottom edge another box uses too falls apart there into its bottom and the rest). So the
boxes of a kitbashed tank that share corner vertices are separate closed parts, as the sign of their overlap
needs them (``open3d_bake.interpenetrating_parts``); an open tank and a closed rock exported in one file are
two parts, one a shell and one a solid (``solid_faces``: mesh_import chooses per part with it and flags the
solid faces, WallMesh.solid, which sdf_bake and wall_snap read).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Parts:
    part: np.ndarray  # (F,) the part of each face
    count: int
    boundary_edges: np.ndarray  # (count,) edges one face of the part uses
    widest_hole: np.ndarray  # (count,) the widest boundary loop (bounding-box diagonal), 0 for none
    closed: np.ndarray  # (count,) bool: every edge of the part used once each way (a closed, oriented shell)


def weld_equal(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a triangle soup (T, 3, 3), equal vertices made one."""
    verts, inv = np.unique(np.asarray(tri, np.float64).reshape(-1, 3), axis=0, return_inverse=True)
    return verts, inv.reshape(-1, 3).astype(np.int64)


def mesh_parts(vertices: np.ndarray, faces: np.ndarray) -> Parts:
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, np.int64)
    n_f, n_v = len(faces), max(len(vertices), 1)
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    forward = np.where(directed[:, 0] < directed[:, 1], 1, -1)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    _, edge, uses = np.unique(lo * n_v + hi, return_inverse=True, return_counts=True)
    edge = edge.reshape(-1)
    # faces across each edge two faces use (the two uses adjacent once sorted by edge)
    two = np.flatnonzero(uses[edge] == 2)
    two = two[np.argsort(edge[two], kind="stable")]
    graph = sparse.coo_matrix((np.ones(len(two) // 2, np.int8), (two[0::2] // 3, two[1::2] // 3)), shape=(n_f, n_f))
    count, part = connected_components(graph, directed=False)
    while True:
        group, n_in, way, group_part, group_edge, first = _groups(part, edge, forward, n_f)
        closed = np.ones(count, np.bool_)
        closed[group_part[(n_in != 2) | (way != 0)]] = False
        # a box whose every bottom edge another box uses too (four faces on each) splits there into its bottom
        # and the rest, each open: join open parts across an edge that two of their faces use, once each way
        loose = np.flatnonzero((n_in == 1) & ~closed[group_part])
        loose = loose[np.argsort(group_edge[loose], kind="stable")]
        e = group_edge[loose]
        starts = np.flatnonzero(np.r_[True, e[1:] != e[:-1]])
        sizes = np.diff(np.r_[starts, len(e)])
        pair = starts[sizes == 2]
        a, b = loose[pair], loose[pair + 1]
        a, b = a[way[a] == -way[b]], b[way[a] == -way[b]]
        if not len(a):
            break
        joined = sparse.coo_matrix((np.ones(len(a), np.int8), (group_part[a], group_part[b])), shape=(count, count))
        count, relabel = connected_components(joined, directed=False)
        part = relabel[part]
    boundary = n_in == 1
    boundary_edges = np.bincount(group_part[boundary], minlength=count)
    widest = _widest_holes(np.asarray(vertices, np.float64), np.sort(directed[first[boundary]], axis=1),
                           group_part[boundary], count)
    return Parts(part, int(count), boundary_edges, widest, closed)


def _groups(part: np.ndarray, edge: np.ndarray, forward: np.ndarray, n_f: int):
    """Each edge within each part: (group of each edge use, uses in the group, their sum of directions, the
    group's part, its edge, one use of it)."""
    edge_part = np.repeat(part, 3)
    _, group, n_in = np.unique(edge_part * (3 * n_f) + edge, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    way = np.bincount(group, forward, minlength=len(n_in)).astype(np.int64)
    first = np.zeros(len(n_in), np.int64)
    first[group] = np.arange(len(group))
    return group, n_in, way, edge_part[first], edge[first], first


def _widest_holes(vertices: np.ndarray, edges: np.ndarray, edge_part: np.ndarray, count: int) -> np.ndarray:
    """Per part the widest loop of its boundary ``edges`` (bounding-box diagonal, as mesh_import's clean-up
    report measures a mesh's largest hole); loops of two parts meeting at a vertex kept apart."""
    widest = np.zeros(count)
    if not len(edges):
        return widest
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    nodes, inv = np.unique(edge_part[:, None] * len(vertices) + edges, return_inverse=True)
    inv = inv.reshape(edges.shape)
    graph = sparse.coo_matrix((np.ones(len(edges), np.int8), (inv[:, 0], inv[:, 1])), shape=(len(nodes), len(nodes)))
    n_loops, loop = connected_components(graph, directed=False)
    pts = vertices[nodes % len(vertices)]
    lo = np.full((n_loops, 3), np.inf)
    hi = np.full((n_loops, 3), -np.inf)
    np.minimum.at(lo, loop, pts)
    np.maximum.at(hi, loop, pts)
    loop_part = np.zeros(n_loops, np.int64)
    loop_part[loop] = nodes // len(vertices)
    np.maximum.at(widest, loop_part, np.linalg.norm(hi - lo, axis=1))
    return widest


def solid_faces(tri: np.ndarray, small_hole: float) -> tuple[np.ndarray, Parts]:
    """(T,) bool: the triangles (T, 3, 3) of the parts closed, or closed but for holes no wider than
    ``small_hole`` (scene units): the parts mesh_import makes solids (fluid outside) in a wall whose other
    parts are shells; and the parts."""
    parts = mesh_parts(*weld_equal(tri))
    solid = (parts.boundary_edges == 0) | (parts.widest_hole <= small_hole)
    return solid[parts.part], parts
