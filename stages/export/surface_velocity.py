"""The particles' velocity at the fluid surface's vertices, for the USD surface's ``velocities``: a renderer
blurs a mesh whose topology changes every frame only from them (UsdGeomPointBased)."""
from __future__ import annotations

import math
from pathlib import Path

import numba as nb
import numpy as np

from stages.common.formats import ParticleMeta, load_particle_frame
from stages.common.meshes import bounds


@nb.njit(cache=True)
def _cell_ids(x, lo, cell, dims):
    """The cell of each point of ``x`` in the grid of ``cell`` from ``lo`` (clamped onto it), x fastest."""
    ids = np.empty(x.shape[0], np.int64)
    for p in range(x.shape[0]):
        i = min(max(int((x[p, 0] - lo[0]) / cell), 0), dims[0] - 1)
        j = min(max(int((x[p, 1] - lo[1]) / cell), 0), dims[1] - 1)
        k = min(max(int((x[p, 2] - lo[2]) / cell), 0), dims[2] - 1)
        ids[p] = (k * dims[1] + j) * dims[0] + i
    return ids


@nb.njit(cache=True)
def _cells(x, lo, cell, dims):
    """Particles sorted by their cell of a grid of ``cell`` from ``lo``: (order, CSR starts per cell)."""
    n = x.shape[0]
    ids = _cell_ids(x, lo, cell, dims)
    order = np.argsort(ids, kind="mergesort")
    starts = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for p in range(n):
        starts[ids[p] + 1] += 1
    for c in range(len(starts) - 1):
        starts[c + 1] += starts[c]
    return order, starts


@nb.njit(cache=True)
def _query_blocks(points, lo, cell, dims):
    """The query points grouped by the cell they fall in: (order, CSR starts per group, each group's cell)."""
    n = points.shape[0]
    ids = _cell_ids(points, lo, cell, dims)
    order = np.argsort(ids, kind="mergesort")
    groups = 0
    for m in range(n):
        if m == 0 or ids[order[m]] != ids[order[m - 1]]:
            groups += 1
    starts = np.empty(groups + 1, np.int64)
    cells = np.empty(groups, np.int64)
    g = 0
    for m in range(n):
        if m == 0 or ids[order[m]] != ids[order[m - 1]]:
            starts[g] = m
            cells[g] = ids[order[m]]
            g += 1
    starts[groups] = n
    return order, starts, cells


@nb.njit(cache=True, parallel=True)
def _gather(points, q_order, q_starts, q_cells, x, v, starts, dims, span, reach, out):
    """out_i = sum_j w_ij v_j / sum_j w_ij, w = (1 - r^2 / reach^2)^3 over the particles within ``reach``; a
    point with none there takes its nearest particle's velocity among the cells searched (else zero). The
    points in groups of one cell (_query_blocks) share one list of the candidates in the (2 span + 1)^3 cells
    around it; ``x`` and ``v`` in cell order."""
    r2max = reach * reach
    for g in nb.prange(q_cells.shape[0]):
        c0 = q_cells[g]
        ci = c0 % dims[0]
        cj = (c0 // dims[0]) % dims[1]
        ck = c0 // (dims[0] * dims[1])
        total = 0
        for k in range(max(ck - span, 0), min(ck + span + 1, dims[2])):
            for j in range(max(cj - span, 0), min(cj + span + 1, dims[1])):
                row = (k * dims[1] + j) * dims[0]
                total += starts[row + min(ci + span, dims[0] - 1) + 1] - starts[row + max(ci - span, 0)]
        near = np.empty(total, np.int64)  # the cells' particles in (k, j, i) order, as one search would meet them
        n = 0
        for k in range(max(ck - span, 0), min(ck + span + 1, dims[2])):
            for j in range(max(cj - span, 0), min(cj + span + 1, dims[1])):
                row = (k * dims[1] + j) * dims[0]
                for p in range(starts[row + max(ci - span, 0)], starts[row + min(ci + span, dims[0] - 1) + 1]):
                    near[n] = p
                    n += 1
        for m in range(q_starts[g], q_starts[g + 1]):
            q = q_order[m]
            px, py, pz = points[q, 0], points[q, 1], points[q, 2]
            sw = 0.0
            sx = sy = sz = 0.0
            best, best_r2 = -1, np.inf
            for t in range(n):
                p = near[t]
                r2 = (x[p, 0] - px) ** 2 + (x[p, 1] - py) ** 2 + (x[p, 2] - pz) ** 2
                if r2 < best_r2:
                    best, best_r2 = p, r2
                if r2 < r2max:
                    w = (1.0 - r2 / r2max) ** 3
                    sw += w
                    sx += w * v[p, 0]
                    sy += w * v[p, 1]
                    sz += w * v[p, 2]
            if sw > 0.0:
                out[q, 0], out[q, 1], out[q, 2] = sx / sw, sy / sw, sz / sw
            elif best >= 0:
                out[q, 0], out[q, 1], out[q, 2] = v[best, 0], v[best, 1], v[best, 2]
            else:
                out[q, 0] = out[q, 1] = out[q, 2] = 0.0


def surface_velocities(vertices: np.ndarray, particles: Path, frame: int) -> np.ndarray:
    """The particles' velocity at each surface vertex (scene units per second): a kernel-weighted mean over the
    particles within 2 l0 (the surface lies within the surface kernel's 1.7 l0 of a particle), the nearest
    particle's where none is that near. At the free surface the neighbourhood is one-sided, so a rotation's
    velocity is off by up to about omega l0."""
    p = load_particle_frame(particles, frame)
    out = np.zeros((len(vertices), 3))
    if len(vertices) == 0 or len(p) == 0:
        return out
    reach = 2.0 * ParticleMeta.load(particles).spacing
    x = np.ascontiguousarray(p.x, np.float64)
    pts = np.ascontiguousarray(vertices, np.float64)
    (x_lo, x_hi), (p_lo, p_hi) = bounds(x), bounds(pts)
    lo, hi = np.minimum(x_lo, p_lo), np.maximum(x_hi, p_hi)
    # cells of half the kernel's reach (5^3 searched, about a particle each: a third of the candidates of 3^3
    # cells of the reach), fewer and larger where a stray particle far off would make the grid huge
    cell = max(0.5 * reach, float(np.prod(hi - lo + reach) / max(8 * len(x), 4096)) ** (1.0 / 3.0))
    dims = (np.floor((hi - lo) / cell).astype(np.int64) + 1)
    order, starts = _cells(x, lo, cell, dims)
    q_order, q_starts, q_cells = _query_blocks(pts, lo, cell, dims)
    _gather(pts, q_order, q_starts, q_cells, x[order], np.asarray(p.v, np.float64)[order], starts, dims,
            int(math.ceil(reach / cell)), reach, out)
    return out
