"""Small triangle-mesh helpers shared by surface_extract and wall_snap (numba where it runs per frame)."""
from __future__ import annotations

import math

import numba as nb
import numpy as np


def _coords(v: np.ndarray) -> np.ndarray:
    """``v`` as a contiguous float32 or float64 array: float32 vertices (a surface's) are not copied to float64."""
    return np.ascontiguousarray(v, np.float32 if np.asarray(v).dtype == np.float32 else np.float64)


def signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    """Volume enclosed by a closed mesh; positive when the faces are oriented outwards. Summed in float64
    about the mesh's own centre: about the origin, a fluid 1000 m away had terms 1e12 x its volume, and
    in float32 products the sign was a coin toss."""
    v = _coords(v)
    if len(v) == 0 or len(f) == 0:
        return 0.0
    lo, hi = _bounds(v)
    return float(_signed_volume(v, np.ascontiguousarray(f), 0.5 * (lo + hi)))


def bounds(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (lo, hi) corners of the points' box, float64 (one numba pass: (N, 3).min(axis=0) is a slow strided
    reduction, 15 ms for a 200k-vertex surface)."""
    v = _coords(v).reshape(-1, 3)
    if len(v) == 0:
        raise ValueError("bounds of no points")
    return _bounds(v)


def face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (length = twice the area), float64."""
    out = np.empty((len(f), 3), np.float64)
    _face_normals(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(f), out)
    return out


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (zero for isolated vertices), in the vertices' precision (float32 or
    float64)."""
    v = _coords(v)
    out = np.empty_like(v)
    _vertex_normals(v, np.ascontiguousarray(f), out)
    return out


def tidy(v: np.ndarray, f: np.ndarray, passes: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The same surface without zero-area triangles or unreferenced vertices (what wall_snap leaves where
    vertices land on one wall edge or corner: a zero normal renders black, tangents fail, a stray point
    shows in Houdini). A triangle whose height is below 1e-5 of its longest edge: a zero-length edge is
    collapsed; otherwise the corner on the long edge splits the triangle across that edge in two (the
    edge flip that takes the sliver out: the surface is unchanged, the mesh stays closed and oriented)."""
    v64 = np.asarray(v, np.float64)
    f = np.asarray(f, np.int64).copy()
    changed = False
    for _ in range(passes):
        if len(f) == 0:
            break
        flags = np.empty(len(f), np.bool_)
        _slivers(v64, f, flags)
        bad = np.flatnonzero(flags)
        if len(bad) == 0:
            break
        p = v64[f[bad]]
        e = np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], axis=1)  # edge opposite corner k
        lengths = np.linalg.norm(e, axis=2)  # row k: triangle bad[k]
        at = dict(zip(bad.tolist(), range(len(bad))))
        # a zero-length edge: its two ends become one (the triangles on that edge drop out below)
        short = lengths.min(axis=1) <= 1e-5 * lengths.max(axis=1)
        into = np.arange(len(v64))
        for t in bad[short]:
            k = int(np.argmin(lengths[at[t]]))
            a, b = f[t, (k + 1) % 3], f[t, (k + 2) % 3]
            while into[a] != a:
                a = into[a]
            while into[b] != b:
                b = into[b]
            if a != b:
                into[max(a, b)] = min(a, b)
        for _ in range(len(v64)):
            nxt = into[into]
            if (nxt == into).all():
                break
            into = nxt
        changed = True
        f = into[f]
        # a sliver (m, q, p), m on its edge q -> p: the triangle across it, (p, q, d), becomes (p, m, d) + (m, q, d);
        # the triangle across is looked up among those on a long edge's start vertex only (not a sort of every edge)
        nv = len(v64)
        split = bad[~short]
        start = np.zeros(nv, np.bool_)
        start[f[split, (np.argmax(lengths[~short], axis=1) + 2) % 3]] = True
        near = np.flatnonzero(_any_corner(start, f))
        keys = f[near][:, [0, 1, 2]] * nv + f[near][:, [1, 2, 0]]  # directed edge k: corner k -> corner k + 1
        order = np.argsort(keys, axis=None)
        flat = keys.ravel()[order]
        touched = np.zeros(len(f), np.bool_)
        extra = []
        for t in split:
            if touched[t] or len(set(f[t].tolist())) < 3:
                continue
            k = int(np.argmax(lengths[at[t]]))  # the corner opposite the long edge
            m, q, pp = f[t, k], f[t, (k + 1) % 3], f[t, (k + 2) % 3]  # the long edge q -> pp, m on it
            i = np.searchsorted(flat, pp * nv + q)  # the triangle across holds pp -> q
            if i >= len(flat) or flat[i] != pp * nv + q:
                continue  # an open edge: nothing across to split
            u = int(near[order[i] // 3])
            if touched[u] or u == t:
                continue
            j = int(order[i] % 3)  # the edge starts at corner j of u: (pp, q, d)
            d = f[u, (j + 2) % 3]
            f[u] = (pp, m, d)
            extra.append((m, q, d))
            touched[[t, u]] = True
            f[t] = (m, m, m)  # gone
        if extra:
            f = np.concatenate([f, np.array(extra, np.int64)])
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    if changed:
        f = _without_cancelling_pairs(f)
    used = np.zeros(len(v64), np.bool_)
    used[f.ravel()] = True
    new = np.cumsum(used) - 1
    return np.asarray(v)[used], new[f].astype(np.int32)


@nb.njit(cache=True)
def _same_corners(f, nv, order):
    """The triangles in the order of their sorted corners (a stable sort: by the smallest corner, bucketed,
    then the other two; ``order`` out), and per position whether the next triangle has the same corners."""
    n = f.shape[0]
    s = np.empty((n, 3), np.int64)
    for t in range(n):
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        if a > b:
            a, b = b, a
        if b > c:
            b, c = c, b
        if a > b:
            a, b = b, a
        s[t, 0], s[t, 1], s[t, 2] = a, b, c
    start = np.zeros(nv + 1, np.int64)
    for t in range(n):
        start[s[t, 0] + 1] += 1
    for k in range(nv):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    for t in range(n):
        order[fill[s[t, 0]]] = t
        fill[s[t, 0]] += 1
    for k in range(nv):  # each bucket by its other two corners, stably: an insertion sort of the usual few
        lo, hi = start[k], start[k + 1]
        if hi - lo > 16:  # a fan's hub
            idx = order[lo:hi].copy()
            keys = s[idx, 1] * nv + s[idx, 2]
            order[lo:hi] = idx[np.argsort(keys, kind="mergesort")]
            continue
        for i in range(lo + 1, hi):
            t = order[i]
            j = i - 1
            while j >= lo and (s[order[j], 1] > s[t, 1] or (s[order[j], 1] == s[t, 1] and s[order[j], 2] > s[t, 2])):
                order[j + 1] = order[j]
                j -= 1
            order[j + 1] = t
    same = np.zeros(max(n - 1, 0), np.bool_)
    for i in range(n - 1):
        a, b = order[i], order[i + 1]
        same[i] = s[a, 0] == s[b, 0] and s[a, 1] == s[b, 1] and s[a, 2] == s[b, 2]
    return same


def _any_corner(flag: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per triangle: whether ``flag`` holds at any of its corners (three gathers: (F, 3).any(axis=1) is a slow
    reduction)."""
    return flag[f[:, 0]] | flag[f[:, 1]] | flag[f[:, 2]]


@nb.njit(cache=True, parallel=True)
def _slivers(v, f, out):
    """out[t]: triangle t's height is at most 1e-5 of its longest edge (in float64)."""
    for t in nb.prange(f.shape[0]):
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        ux, uy, uz = v[b, 0] - v[a, 0], v[b, 1] - v[a, 1], v[b, 2] - v[a, 2]
        wx, wy, wz = v[c, 0] - v[a, 0], v[c, 1] - v[a, 1], v[c, 2] - v[a, 2]
        sx, sy, sz = v[c, 0] - v[b, 0], v[c, 1] - v[b, 1], v[c, 2] - v[b, 2]
        longest = max(ux * ux + uy * uy + uz * uz, wx * wx + wy * wy + wz * wz, sx * sx + sy * sy + sz * sz)
        cx, cy, cz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        # height = |u x w| / longest <= 1e-5 longest, squared
        out[t] = cx * cx + cy * cy + cz * cz <= 1e-10 * longest * longest


def _without_cancelling_pairs(f: np.ndarray) -> np.ndarray:
    """Without triangles on the same three vertices in opposite orientations: a flat pillow of no volume
    (left where a sliver's split met its twin), whose corner vertex got a zero normal. Each pair's edges are
    its own twins, so the rest stays closed."""
    if len(f) < 2:
        return f
    order = np.empty(len(f), np.int64)
    same = np.flatnonzero(_same_corners(f, int(f.max()) + 1, order))
    drop = np.zeros(len(f), np.bool_)
    for i in same:
        a, b = order[i], order[i + 1]
        if drop[a] or drop[b]:
            continue
        # opposite orientations: b's corners are a's read backwards from some start
        ra = f[a][::-1]
        if any((np.roll(ra, k) == f[b]).all() for k in range(3)):
            drop[[a, b]] = True
    return f[~drop]


def boundary_edge_count(f: np.ndarray) -> int:
    """Edges used by one triangle only (0 for a closed mesh)."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


def winding_number(v: np.ndarray, f: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The generalized winding number of mesh (v, f) at ``points`` (libigl's fast approximation), computed
    about the mesh's box centre: in world coordinates a box 1e5 m off the origin read w = 0.5 one centimetre
    inside its face (igl's expansions lose the digits there), which emptied a mesh emitter's outer layers."""
    import igl

    v = np.asarray(v, np.float64).reshape(-1, 3)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0)) if len(v) else np.zeros(3)
    return igl.fast_winding_number(np.ascontiguousarray(v - centre), np.ascontiguousarray(f, np.int64),
                                   np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3) - centre))


@nb.njit(cache=True, inline="always")
def _triangle_normal(v, a, b, c):
    """(b - a) x (c - a) of the triangle (a, b, c) of ``v``: its normal, twice its area long."""
    ux = v[b, 0] - v[a, 0]
    uy = v[b, 1] - v[a, 1]
    uz = v[b, 2] - v[a, 2]
    wx = v[c, 0] - v[a, 0]
    wy = v[c, 1] - v[a, 1]
    wz = v[c, 2] - v[a, 2]
    return uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx


@nb.njit(cache=True)
def _face_normals(v, f, out):
    """The normal of each triangle of ``f`` into ``out``."""
    for t in range(f.shape[0]):
        out[t, 0], out[t, 1], out[t, 2] = _triangle_normal(v, f[t, 0], f[t, 1], f[t, 2])


@nb.njit(cache=True)
def _vertex_normals(v, f, out):
    """Area-weighted unit vertex normals of the triangle mesh (v, f) into ``out`` (zeros first)."""
    for a in range(out.shape[0]):
        out[a, 0] = 0.0
        out[a, 1] = 0.0
        out[a, 2] = 0.0
    for t in range(f.shape[0]):
        a = f[t, 0]
        b = f[t, 1]
        c = f[t, 2]
        nx, ny, nz = _triangle_normal(v, a, b, c)
        for p in (a, b, c):
            out[p, 0] += nx
            out[p, 1] += ny
            out[p, 2] += nz
    for a in range(out.shape[0]):
        n = math.sqrt(out[a, 0] ** 2 + out[a, 1] ** 2 + out[a, 2] ** 2)
        if n > 0.0:
            out[a, 0] /= n
            out[a, 1] /= n
            out[a, 2] /= n


@nb.njit(cache=True)
def _bounds(v):
    """The box corners (lo, hi) of the points ``v`` (N >= 1), in float64."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for a in range(v.shape[0]):
        for k in range(3):
            c = np.float64(v[a, k])
            lo[k] = min(lo[k], c)
            hi[k] = max(hi[k], c)
    return lo, hi


@nb.njit(cache=True)
def _signed_volume(v, f, o):
    """Volume enclosed by the closed mesh (v, f), in float64 about the point o; positive when faces are
    oriented outwards."""
    s = 0.0
    for t in range(f.shape[0]):
        a = f[t, 0]
        b = f[t, 1]
        c = f[t, 2]
        ax, ay, az = np.float64(v[a, 0]) - o[0], np.float64(v[a, 1]) - o[1], np.float64(v[a, 2]) - o[2]
        bx, by, bz = np.float64(v[b, 0]) - o[0], np.float64(v[b, 1]) - o[1], np.float64(v[b, 2]) - o[2]
        cx, cy, cz = np.float64(v[c, 0]) - o[0], np.float64(v[c, 1]) - o[1], np.float64(v[c, 2]) - o[2]
        s += ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    return s / 6.0
