"""Wall weight tables Z_rho(r) and Z_vis(r) of the distance-function walls (PHYSICS.md eq. 11-15).

Built once per (spacing, support): a particle at distance r above a flat wall, virtual wall particles
on the cubic lattice of spacing l0 below the plane (first layer l0/2 behind the surface), summed
with the density kernel (eq. 10, 12) and the viscosity Laplacian (eq. 9, 15). Looked up linearly
with the particle's SDF distance; zero for r >= h, clamped to the r = 0 value inside the wall."""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..kernels import poly6_np, spiky_grad_coef, visc_lap_np


def wall_lattice(l0: float, h: float) -> np.ndarray:
    """Virtual wall particles (M, 3) below the plane z = 0, covering the support of a particle above
    the lattice column x = y = 0."""
    k = int(math.ceil(h / l0)) + 1
    g = np.arange(-k, k + 1) * l0
    layers = -(0.5 + np.arange(k + 1)) * l0
    X, Y, Z = np.meshgrid(g, g, layers, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def build_tables(l0: float, h: float, mass: float, rho0: float, samples: int = 256):
    """Returns (r_max, z_rho, z_vis, z_press), each (samples,) on r = r_max * i / (samples - 1).

    z_press(r) = (m / rho0) sum_wall |grad W|_n (Spiky, eq. 8, the normal component): the wall
    particles' share of eq. 6 with p_wall = p_i and rho_wall = rho0, so a particle next to a wall feels
    the wall push back as it would with wall particles (eq. 16 stays as the hard backstop)."""
    wall = wall_lattice(l0, h)
    r = np.linspace(0.0, h, samples)
    z_rho = np.empty(samples)
    z_vis = np.empty(samples)
    z_press = np.empty(samples)
    cs = spiky_grad_coef(h)
    for i, ri in enumerate(r):
        dist = np.sqrt(wall[:, 0] ** 2 + wall[:, 1] ** 2 + (ri - wall[:, 2]) ** 2)
        z_rho[i] = mass * poly6_np(dist, h).sum()  # eq. 12
        z_vis[i] = (mass / rho0) * visc_lap_np(dist, h).sum()  # eq. 15
        inside = (dist < h) & (dist > 1e-12)
        dz = ri - wall[inside, 2]
        z_press[i] = (mass / rho0) * (cs * (h - dist[inside]) ** 2 * dz / dist[inside]).sum()
    z_rho[-1] = 0.0
    z_vis[-1] = 0.0
    z_press[-1] = 0.0
    return float(h), z_rho, z_vis, z_press


def half_space_density(r, h, rho0):
    """Continuum limit of Z_rho (PHYSICS.md): rho0 [1/2 - 315/256 P(r/h)]."""
    u = np.clip(np.asarray(r, float) / h, 0.0, 1.0)
    P = u - 4 * u ** 3 / 3 + 6 * u ** 5 / 5 - 4 * u ** 7 / 7 + u ** 9 / 9
    return rho0 * (0.5 - 315.0 / 256.0 * P)


@nb.njit(cache=True, inline="always")
def table_lookup(table, r, inv_dr):
    """Linear interpolation of a table sampled on [0, r_max]; clamped at both ends (0 beyond r_max)."""
    n = table.shape[0]
    f = r * inv_dr
    if f <= 0.0:
        return table[0]
    if f >= n - 1:
        return table[n - 1]
    i = int(f)
    t = f - i
    return table[i] + (table[i + 1] - table[i]) * t

