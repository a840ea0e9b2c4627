"""3D wall maps: the wall density, wall pressure-gradient and wall viscosity terms of eq. 11-15
precomputed on a grid from the SDF (the "density map" improvement PHYSICS.md names), so edges and
corners, where two or three walls are within h, count every wall and not only the nearest plane.

Each node integrates the kernels over the wall region {d < 0} inside its support with a quadrature
lattice of spacing l0/2 (the wall particles of eq. 12 and 15 smeared into a continuum), then a 1D
factor per wall distance makes the flat-wall value equal the lattice-sum table of wall_tables.py
exactly (so a particle l0/2 above a flat floor gets rho0, as with the 1D tables).

Channels: 0 Z_rho (kg/m^3), 1-3 wall pressure direction G = (m/rho0) sum -grad W (1/m, eq. 6, 8),
4 Z_vis (1/m^2, eq. 15)."""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from stages.common.sdf import sdf_sample

from .kernels import poly6_coef, spiky_grad_coef, visc_lap_coef
from .wall_tables import build_tables, table_lookup


@nb.njit(cache=True, inline="always")
def _wall_weight(d, half_width):
    """Smooth occupancy of the wall region (1 deep inside, 0 in the fluid)."""
    t = 0.5 - d / (2.0 * half_width)
    return min(max(t, 0.0), 1.0)


@nb.njit(cache=True)
def _quadrature_at(sdf, so, sinv, px, py, pz, h, dq, offsets, c6, cs, cv, scale, mass, rho0, out):
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    out[3] = 0.0
    out[4] = 0.0
    h2 = h * h
    for k in range(offsets.shape[0]):
        ox = offsets[k, 0]
        oy = offsets[k, 1]
        oz = offsets[k, 2]
        r2 = ox * ox + oy * oy + oz * oz
        if r2 >= h2:
            continue
        d, _, _, _ = sdf_sample(sdf, so[0], so[1], so[2], sinv, px + ox, py + oy, pz + oz)
        w = _wall_weight(d, 0.5 * dq)
        if w == 0.0:
            continue
        r = math.sqrt(r2)
        q = h2 - r2
        out[0] += w * scale * mass * c6 * q * q * q
        if r > 1e-12:
            g = w * scale * (mass / rho0) * cs * (h - r) * (h - r) / r
            # -grad W points from the wall sample (x + o) to the particle: along -o
            out[1] -= g * ox
            out[2] -= g * oy
            out[3] -= g * oz
        out[4] += w * scale * (mass / rho0) * cv * (h - r)


@nb.njit(cache=True, parallel=True)
def _build(sdf, so, sinv, mo, mh, shape, h, dq, offsets, c6, cs, cv, scale, mass, rho0, maps):
    nx, ny, nz = shape[0], shape[1], shape[2]
    for i in nb.prange(nx):
        out = np.zeros(5)
        for j in range(ny):
            for k in range(nz):
                px = mo[0] + i * mh
                py = mo[1] + j * mh
                pz = mo[2] + k * mh
                d, _, _, _ = sdf_sample(sdf, so[0], so[1], so[2], sinv, px, py, pz)
                if d >= h + dq:
                    for c in range(5):
                        maps[i, j, k, c] = 0.0
                    continue
                _quadrature_at(sdf, so, sinv, px, py, pz, h, dq, offsets, c6, cs, cv, scale, mass, rho0, out)
                for c in range(5):
                    maps[i, j, k, c] = out[c]


def _offsets(h: float, dq: float) -> np.ndarray:
    k = int(math.ceil(h / dq)) + 1
    g = (np.arange(-k, k) + 0.5) * dq  # cell-centred, symmetric about 0
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    o = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    return np.ascontiguousarray(o[np.linalg.norm(o, axis=1) < h + dq])


class WallMaps:
    """The wall terms on a node grid of spacing ``l0 / 2`` over the SDF grid, plus the flat-wall
    correction factors (1D, indexed by the wall distance)."""

    def __init__(self, sdf, l0: float, h: float, mass: float, rho0: float, samples: int = 256):
        self.h = h
        dq = 0.5 * l0
        self.spacing = 0.5 * l0
        self.origin = np.asarray(sdf.origin, np.float64)
        shape = np.floor((sdf.upper - sdf.origin) / self.spacing).astype(np.int64) + 1
        self.maps = np.zeros((*shape, 5), np.float32)
        offsets = _offsets(h, dq)
        scale = dq ** 3 / l0 ** 3  # quadrature volume in units of one wall particle's volume
        args = (h, dq, offsets, poly6_coef(h), spiky_grad_coef(h), visc_lap_coef(h), scale, mass, rho0)
        _build(sdf.dist, sdf.origin, 1.0 / sdf.spacing, self.origin, self.spacing, shape, *args, self.maps)
        # flat-wall correction: the quadrature of a half space against the lattice-sum table
        _, z_rho, z_vis, z_press = build_tables(l0, h, mass, rho0, samples)
        r = np.linspace(0.0, h, samples)
        flat = np.zeros((samples, 5))
        lo = np.array([-2 * h, -2 * h, -2 * h])
        from stages.common.sdf import grid_from_function
        plane = grid_from_function(lambda p: p[:, 2], lo, -lo, dq / 2)
        out = np.zeros(5)
        for s, ri in enumerate(r):
            _quadrature_at(plane.dist, plane.origin, 1.0 / plane.spacing, 0.0, 0.0, ri, *args, out)
            flat[s] = out
        self.fix_rho = np.where(flat[:, 0] > 1e-12, z_rho / np.maximum(flat[:, 0], 1e-300), 1.0)
        self.fix_press = np.where(flat[:, 3] > 1e-12, z_press / np.maximum(flat[:, 3], 1e-300), 1.0)
        self.fix_vis = np.where(flat[:, 4] > 1e-12, z_vis / np.maximum(flat[:, 4], 1e-300), 1.0)
        self.inv_dr = (samples - 1) / h


@nb.njit(cache=True, inline="always")
def map_sample(maps, ox, oy, oz, inv_h, x, y, z, c):
    """Trilinear value of channel ``c`` of a node-centred (nx, ny, nz, C) map (clamped to the grid)."""
    nx, ny, nz = maps.shape[0], maps.shape[1], maps.shape[2]
    fx = min(max((x - ox) * inv_h, 0.0), nx - 1.000001)
    fy = min(max((y - oy) * inv_h, 0.0), ny - 1.000001)
    fz = min(max((z - oz) * inv_h, 0.0), nz - 1.000001)
    i = int(fx)
    j = int(fy)
    k = int(fz)
    tx = fx - i
    ty = fy - j
    tz = fz - k
    c00 = maps[i, j, k, c] + (maps[i + 1, j, k, c] - maps[i, j, k, c]) * tx
    c10 = maps[i, j + 1, k, c] + (maps[i + 1, j + 1, k, c] - maps[i, j + 1, k, c]) * tx
    c01 = maps[i, j, k + 1, c] + (maps[i + 1, j, k + 1, c] - maps[i, j, k + 1, c]) * tx
    c11 = maps[i, j + 1, k + 1, c] + (maps[i + 1, j + 1, k + 1, c] - maps[i, j + 1, k + 1, c]) * tx
    c0 = c00 + (c10 - c00) * ty
    c1 = c01 + (c11 - c01) * ty
    return c0 + (c1 - c0) * tz


__all__ = ["WallMaps", "map_sample", "table_lookup"]
