"""Catmull-Clark refinement of a polygon cage (USD's default ``subdivisionScheme``), so a wall can be
the smooth surface a renderer draws from the cage rather than the cage itself.

One level turns every n-gon into n quads: face points at the face centroids; edge points at the mean of
an edge's ends and its two faces' points; vertex points (F + 2 R + (n - 3) P) / n (F the mean of the
adjacent face points, R of the incident edges' midpoints, n the valence). USD's default boundary rule
``edgeAndCorner``: a boundary (or non-manifold) edge is a sharp crease, its edge point the midpoint and
its vertices 3/4 P + 1/8 (the two neighbours along it); a vertex of one face only, or on more than two
creases, stays put. Authored creases and corners are not applied (the caller says so)."""
from __future__ import annotations

import numpy as np


def catmull_clark(points: np.ndarray, counts: np.ndarray, indices: np.ndarray,
                  levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``levels`` refinements of the polygon mesh (points, faceVertexCounts, faceVertexIndices); the
    result is quads, wound as the cage's faces."""
    p, c, idx = np.asarray(points, np.float64), np.asarray(counts, np.int64), np.asarray(indices, np.int64)
    for _ in range(levels):
        p, c, idx = _refine(p, c, idx)
    return p, c, idx


def _refine(p: np.ndarray, counts: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    nv, nf = len(p), len(counts)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face = np.repeat(np.arange(nf), counts)  # the face of each corner
    k = np.arange(len(idx)) - start[face]  # the corner's place in its face
    nxt = idx[start[face] + (k + 1) % counts[face]]
    face_pt = np.zeros((nf, 3))
    np.add.at(face_pt, face, p[idx])
    face_pt /= counts[:, None]

    # edges: the corner's edge (idx -> nxt); one id per unordered pair
    pair = np.sort(np.stack([idx, nxt], axis=1), axis=1)
    edges, edge_of = np.unique(pair, axis=0, return_inverse=True)
    edge_of = edge_of.reshape(-1)
    ne = len(edges)
    n_faces = np.bincount(edge_of, minlength=ne)  # faces on each edge: 2 inside, else a crease
    crease = n_faces != 2
    mid = 0.5 * (p[edges[:, 0]] + p[edges[:, 1]])
    face_sum = np.zeros((ne, 3))
    np.add.at(face_sum, edge_of, face_pt[face])
    edge_pt = np.where(crease[:, None], mid, 0.5 * mid + 0.5 * face_sum / np.maximum(n_faces, 1)[:, None])

    # vertices: valence, adjacent faces (by corners), incident edges, creases through each
    valence = np.bincount(edges.ravel(), minlength=nv)
    corners = np.bincount(idx, minlength=nv)
    f_mean = np.zeros((nv, 3))
    np.add.at(f_mean, idx, face_pt[face])
    f_mean /= np.maximum(corners, 1)[:, None]
    r_mean = np.zeros((nv, 3))
    np.add.at(r_mean, edges.ravel(), np.repeat(mid, 2, axis=0))
    r_mean /= np.maximum(valence, 1)[:, None]
    n = np.maximum(valence, 1)[:, None]
    vert_pt = (f_mean + 2.0 * r_mean + (n - 3.0) * p) / n
    ce = edges[crease]
    n_crease = np.bincount(ce.ravel(), minlength=nv)
    along = np.zeros((nv, 3))
    np.add.at(along, ce[:, 0], p[ce[:, 1]])
    np.add.at(along, ce[:, 1], p[ce[:, 0]])
    on_crease = n_crease == 2
    vert_pt[on_crease] = 0.75 * p[on_crease] + 0.125 * along[on_crease]
    fixed = (n_crease > 2) | ((n_crease > 0) & (corners == 1)) | (valence == 0)
    vert_pt[fixed] = p[fixed]

    # a quad per corner: the vertex, its edge forward, the face point, its edge back
    back = edge_of[start[face] + (k - 1) % counts[face]]  # the previous corner's edge ends here
    quads = np.stack([idx, nv + edge_of, nv + ne + face, nv + back], axis=1)
    new_p = np.concatenate([vert_pt, edge_pt, face_pt])
    return new_p, np.full(len(quads), 4, np.int64), quads.ravel()
