"""Exact closest points on a triangle mesh (numba), for queries near the mesh.

The triangles are listed in the cells of a uniform grid (cell >= ``reach``) whose boxes their bounding
boxes, widened by ``reach``, overlap. A query looks at the triangles of its own cell first: any
triangle within ``reach`` of it is listed there, so when the best of them is within ``reach`` it is
the closest of all. Otherwise the search widens by a shell of cells or two (a triangle at distance D
is listed in a cell at most (D - reach) / cell cells away); beyond that, or outside the grid, it
checks every triangle whose bounding box is no farther than the best so far. Closest point on a
triangle: Ericson, Real-Time Collision Detection 5.1.5 (Voronoi regions); a degenerate triangle is
the closest of its three edges. Ties go to the lower triangle index. All in float64 (open3d's
RaycastingScene works in float32).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

MAX_CELLS = 128  # per axis: the grid stays a few MB whatever the reach
SHELLS = 2  # cell shells searched around a query before every triangle is (pruned by its box)


class ClosestPoints:
    """Closest points of the triangle mesh (``vertices`` (V, 3), ``faces`` (F, 3)) to query points:
    fast for points within ``reach`` (scene units) of it, exact for all."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, reach: float):
        self.tri = np.ascontiguousarray(np.asarray(vertices, np.float64)[np.asarray(faces)], np.float64).reshape(-1, 3, 3)
        n = np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0])
        length = np.linalg.norm(n, axis=1)
        # the mesh's own size, not its coordinates (with |x| + 1 a tank 2e5 m out had every triangle "degenerate"
        # and no normals: snapped surfaces there relaxed and collapsed 4x as much)
        scale = float(np.ptp(self.tri.reshape(-1, 3), axis=0).max()) if len(self.tri) else 1.0
        scale = scale if scale > 0 else 1.0
        self.degenerate = length <= 1e-12 * scale * scale
        self.normals = n / np.where(self.degenerate, 1.0, length)[:, None]
        self.normals[self.degenerate] = 0.0
        self.box = np.ascontiguousarray(np.hstack([self.tri.min(axis=1), self.tri.max(axis=1)]))  # (F, 6)
        lo = self.tri.min(axis=(0, 1)) if len(self.tri) else np.zeros(3)
        hi = self.tri.max(axis=(0, 1)) if len(self.tri) else np.zeros(3)
        self.reach = float(reach)
        self.cell = max(self.reach, float((hi - lo).max()) / MAX_CELLS, 1e-12 * scale)
        self.origin = lo - self.reach
        self.dims = (np.floor((hi + self.reach - self.origin) / self.cell).astype(np.int64) + 1)
        self.start, self.items = _cell_lists(self.tri, self.origin, self.cell, self.dims, self.reach)

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points (N, 3), the unit normals of their triangles ((b - a) x (c - a); zero for a
        degenerate one) and the triangles' indices, for ``points`` (N, 3)."""
        p = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        near = np.empty_like(p)
        ids = np.empty(len(p), np.int64)
        if len(self.tri) == 0:
            raise ValueError("no triangles to project onto")
        _closest(self.tri, self.degenerate, self.box, self.start, self.items, self.origin, self.cell, self.dims,
                 self.reach, SHELLS, p, near, ids)
        return near, self.normals[ids], ids


@nb.njit(cache=True)
def _cell_lists(tri, origin, cell, dims, reach):
    """CSR lists (start, items) of the triangles whose bounding box widened by ``reach`` overlaps each
    cell (cell (i, j, k) is at index (i * dims[1] + j) * dims[2] + k), in triangle order."""
    n_cells = dims[0] * dims[1] * dims[2]
    count = np.zeros(n_cells + 1, np.int64)
    box = np.empty((tri.shape[0], 6), np.int64)
    for t in range(tri.shape[0]):
        for a in range(3):
            lo = min(tri[t, 0, a], tri[t, 1, a], tri[t, 2, a]) - reach
            hi = max(tri[t, 0, a], tri[t, 1, a], tri[t, 2, a]) + reach
            box[t, a] = max(math.floor((lo - origin[a]) / cell), 0)
            box[t, 3 + a] = min(math.floor((hi - origin[a]) / cell), dims[a] - 1)
        for i in range(box[t, 0], box[t, 3] + 1):
            for j in range(box[t, 1], box[t, 4] + 1):
                for k in range(box[t, 2], box[t, 5] + 1):
                    count[(i * dims[1] + j) * dims[2] + k + 1] += 1
    for c in range(n_cells):
        count[c + 1] += count[c]
    fill = count[:-1].copy()
    items = np.empty(count[n_cells], np.int32)  # a small triangle sits in up to 27 cells: int32 halves them
    for t in range(tri.shape[0]):
        for i in range(box[t, 0], box[t, 3] + 1):
            for j in range(box[t, 1], box[t, 4] + 1):
                for k in range(box[t, 2], box[t, 5] + 1):
                    c = (i * dims[1] + j) * dims[2] + k
                    items[fill[c]] = t
                    fill[c] += 1
    return count, items


@nb.njit(cache=True)
def _on_segment(px, py, pz, ax, ay, az, bx, by, bz):
    """Closest point to p on the segment ab (a if a == b)."""
    ux, uy, uz = bx - ax, by - ay, bz - az
    uu = ux * ux + uy * uy + uz * uz
    s = 0.0
    if uu > 0.0:
        s = min(max(((px - ax) * ux + (py - ay) * uy + (pz - az) * uz) / uu, 0.0), 1.0)
    return ax + s * ux, ay + s * uy, az + s * uz


@nb.njit(cache=True)
def _on_triangle(tri, degenerate, t, px, py, pz):
    """Closest point to p on triangle t (Ericson 5.1.5; a degenerate one: the closest of its edges)."""
    ax, ay, az = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
    bx, by, bz = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
    cx, cy, cz = tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2]
    if degenerate[t]:
        best = np.inf
        qx, qy, qz = ax, ay, az
        for e in range(3):
            sx, sy, sz = tri[t, e, 0], tri[t, e, 1], tri[t, e, 2]
            ex, ey, ez = tri[t, (e + 1) % 3, 0], tri[t, (e + 1) % 3, 1], tri[t, (e + 1) % 3, 2]
            x, y, z = _on_segment(px, py, pz, sx, sy, sz, ex, ey, ez)
            d = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
            if d < best:
                best = d
                qx, qy, qz = x, y, z
        return qx, qy, qz
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        s = d1 / (d1 - d3)
        return ax + s * abx, ay + s * aby, az + s * abz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        s = d2 / (d2 - d6)
        return ax + s * acx, ay + s * acy, az + s * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + s * (cx - bx), by + s * (cy - by), bz + s * (cz - bz)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@nb.njit(cache=True)
def _nearer(tri, degenerate, t, px, py, pz, best, best_t, qx, qy, qz):
    """The closer of triangle t and the best so far (distance squared, triangle, point); ties: lower t."""
    x, y, z = _on_triangle(tri, degenerate, t, px, py, pz)
    d = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
    if d < best or (d == best and t < best_t):
        return d, t, x, y, z
    return best, best_t, qx, qy, qz


@nb.njit(cache=True)
def _closest(tri, degenerate, box, start, items, origin, cell, dims, reach, shells, points, near, ids):
    """near[p], ids[p]: the closest point of the mesh to points[p] and its triangle (see the module)."""
    for p in range(points.shape[0]):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        best = np.inf
        best_t = -1
        qx, qy, qz = px, py, pz
        ci = math.floor((px - origin[0]) / cell)
        cj = math.floor((py - origin[1]) / cell)
        ck = math.floor((pz - origin[2]) / cell)
        found = False
        if 0 <= ci < dims[0] and 0 <= cj < dims[1] and 0 <= ck < dims[2]:
            for r in range(shells + 1):  # the cells r away (Chebyshev) from the point's
                for i in range(max(ci - r, 0), min(ci + r, dims[0] - 1) + 1):
                    for j in range(max(cj - r, 0), min(cj + r, dims[1] - 1) + 1):
                        # the whole column on the shell's sides, its two ends inside them
                        step = 1 if abs(i - ci) == r or abs(j - cj) == r else 2 * r
                        for k in range(ck - r, ck + r + 1, step):
                            if 0 <= k < dims[2]:
                                c = (i * dims[1] + j) * dims[2] + k
                                for s in range(start[c], start[c + 1]):
                                    t = np.int64(items[s])
                                    best, best_t, qx, qy, qz = _nearer(tri, degenerate, t, px, py, pz, best, best_t,
                                                                       qx, qy, qz)
                # a triangle D away is listed within (D - reach) / cell cells: all up to here are seen
                if best <= (reach + r * cell) ** 2:
                    found = True
                    break
        if not found:  # far from the walls: every triangle whose box is not farther than the best so far
            for t in range(tri.shape[0]):
                dx = max(box[t, 0] - px, 0.0, px - box[t, 3])
                dy = max(box[t, 1] - py, 0.0, py - box[t, 4])
                dz = max(box[t, 2] - pz, 0.0, pz - box[t, 5])
                if dx * dx + dy * dy + dz * dz <= best:
                    best, best_t, qx, qy, qz = _nearer(tri, degenerate, t, px, py, pz, best, best_t, qx, qy, qz)
        near[p, 0] = qx
        near[p, 1] = qy
        near[p, 2] = qz
        ids[p] = best_t
