"""The particles' implicit function on a grid (PHYSICS.md eq. 17-18), numba.

Phi(x) = sum_j (m / rho_j) W(|x - x_j|) with the Poly6 kernel of support R, so Phi is about 1 inside
the fluid and 0 outside. Gathered per grid node (each node reads the particles of the 27 cells
around it), so every node is written by one thread: deterministic, no atomics.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np


def sort_into_cells(x: np.ndarray, lo: np.ndarray, cell: float, dims: np.ndarray):
    """Counting sort of particles into cells of size ``cell``; returns (order, starts)."""
    c = np.clip(np.floor((x - lo) / cell).astype(np.int64), 0, dims - 1)
    cid = (c[:, 2] * dims[1] + c[:, 1]) * dims[0] + c[:, 0]
    order = np.argsort(cid, kind="stable")
    starts = np.searchsorted(cid[order], np.arange(int(np.prod(dims)) + 1))
    return order, starts.astype(np.int64)


@nb.njit(cache=True, parallel=True)
def implicit_function(x, vol, starts, lo, cell, dims, grid_lo, spacing, shape, radius, out):
    """Phi at every node of a regular grid (node (i, j, k) at grid_lo + spacing (i, j, k)).

    ``x`` (N, 3) and ``vol`` (N,) = m / rho_j in cell order; ``out`` has ``shape`` (nx, ny, nz)."""
    r2max = radius * radius
    coef = 315.0 / (64.0 * math.pi * radius ** 9)
    cnx, cny, cnz = dims[0], dims[1], dims[2]
    for k in nb.prange(shape[2]):
        pz = grid_lo[2] + spacing * k
        cz = min(max(int(math.floor((pz - lo[2]) / cell)), 0), cnz - 1)
        for j in range(shape[1]):
            py = grid_lo[1] + spacing * j
            cy = min(max(int(math.floor((py - lo[1]) / cell)), 0), cny - 1)
            for i in range(shape[0]):
                px = grid_lo[0] + spacing * i
                cx = min(max(int(math.floor((px - lo[0]) / cell)), 0), cnx - 1)
                x0 = max(cx - 1, 0)
                x1 = min(cx + 1, cnx - 1)
                s = 0.0
                for kz in range(max(cz - 1, 0), min(cz + 2, cnz)):
                    for ky in range(max(cy - 1, 0), min(cy + 2, cny)):
                        base = (kz * cny + ky) * cnx
                        for q in range(starts[base + x0], starts[base + x1 + 1]):
                            dx = px - x[q, 0]
                            dy = py - x[q, 1]
                            dz = pz - x[q, 2]
                            r2 = dx * dx + dy * dy + dz * dz
                            if r2 < r2max:
                                w = r2max - r2
                                s += vol[q] * w * w * w
                out[i, j, k] = coef * s
