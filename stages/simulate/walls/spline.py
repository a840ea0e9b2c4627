"""DFSPH's kernel and wall terms: the cubic spline for the density AND its gradient (as SPlisHSPlasH,
Bender and Koschier), with the wall density Z_rho and the wall gradient Psi as quadratures of that same
kernel and its gradient over the wall region (the analogue of walls/maps.py, which does Poly6 / Spiky).

Why one kernel: the solve predicts the density change with sum_j m (v_i - v_j) . grad_i W_ij; that is
the density's Jacobian only if W is the density's kernel. With a Poly6 density and a Spiky gradient the
per-pair ratio ran 0.45..3 and a resting tank never came to rest.

Cubic spline (support h, q = r / h, 3D): W = k (6 q^3 - 6 q^2 + 1) for q <= 1/2, 2 k (1 - q)^3 for
q < 1, k = 8 / (pi h^3); -grad_i W_ij = f(r) (x_i - x_j) with f = l (2 - 3 q) / h^2 (q <= 1/2) and
l (1 - q)^2 / (r h) (q < 1), l = 48 / (pi h^3).

Wall maps (bricked like walls.maps.BrickWallMaps, read with walls.maps.wall_sample / wall_sample_1234):
channel 0 Z_rho = sum_wall m W (kg/m^3), 1-3 G = (m / rho0) sum_wall -grad_i W (1/m, points into the
fluid; Psi = -rho0 G), 4 Z_vis of eq. 15 (the viscosity Laplacian, for sph_kernels.forces). Each node
integrates over {d < 0} with the l0/2 quadrature of walls/maps.py; 1D flat-wall factors (by wall
distance) make a flat floor match the lattice sum over wall particles exactly (tables.wall_lattice),
so a particle l0/2 above a floor on the rest lattice has rho0 and S_i + Psi_i = 0.

Used by DFSPHParams(gradient="spline"), opt-in: it did not bring a resting tank to rest (dfsph.py)."""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from stages.common.sdf import SDFGrid

from ..kernels import rest_lattice, visc_lap_np
from .maps import BrickWallMaps, build_bricks, flat_wall_sums, quadrature_stencil
from .tables import wall_lattice


def spline_coefs(h: float) -> tuple[float, float]:
    """(k, l) = (8 / (pi h^3), 48 / (pi h^3)): the cubic spline's value and gradient coefficients."""
    return 8.0 / (math.pi * h ** 3), 48.0 / (math.pi * h ** 3)


@nb.njit(cache=True, inline="always")
def spline_w(r, h, k):
    """The cubic spline W(r) (zero for r >= h). Both pieces are computed and one selected: no branch
    to mispredict in the pair loops (lattice neighbours sit at q = 0.5, the pieces' seam)."""
    q = r / h
    t = max(1.0 - q, 0.0)
    inner = 6.0 * q * q * (q - 1.0) + 1.0
    outer = 2.0 * t * t * t
    return k * (inner if q <= 0.5 else outer)


@nb.njit(cache=True, inline="always")
def spline_f(r, h, l):
    """f(r) with -grad_i W_ij = f (x_i - x_j) (zero for r >= h; finite at r = 0); branch-free as spline_w."""
    q = r / h
    t = max(1.0 - q, 0.0)
    inner = (2.0 - 3.0 * q) / (h * h)
    outer = t * t / (max(r, 1e-300) * h)
    return l * (inner if q <= 0.5 else outer)


def spline_np(r, h):
    """Vectorised cubic spline (tests, tables)."""
    k, _ = spline_coefs(h)
    q = np.asarray(r, float) / h
    t = np.clip(1.0 - q, 0.0, None)
    return np.where(q <= 0.5, k * (6 * q ** 3 - 6 * q ** 2 + 1), 2 * k * t ** 3)


def spline_f_np(r, h):
    """Vectorised f(r) of spline_f."""
    _, l = spline_coefs(h)
    r = np.asarray(r, float)
    q = r / h
    t = np.clip(1.0 - q, 0.0, None)
    return np.where(q <= 0.5, l * (2 - 3 * q) / h ** 2, l * t * t / (np.maximum(r, 1e-300) * h))


def spline_lattice_mass(rho0: float, l0: float, h: float) -> float:
    """Particle mass such that the spline sum over a full cubic lattice (self included) gives rho0
    (kernels.lattice_mass for Poly6)."""
    _, r = rest_lattice(l0, h)
    return float(rho0 / spline_np(r, h).sum())


def flat_wall_tables(l0: float, h: float, mass: float, rho0: float, samples: int):
    """Lattice sums over the wall particles of tables.wall_lattice for a particle at r = h i /
    (samples - 1) above a flat floor: (z_rho, z_grad, z_vis), z_rho = m sum W, z_grad = (m / rho0)
    sum f dz (the normal component of G), z_vis = (m / rho0) sum lap W_vis (eq. 15)."""
    wall = wall_lattice(l0, h)
    z_rho, z_grad, z_vis = np.zeros(samples), np.zeros(samples), np.zeros(samples)
    for i, ri in enumerate(np.linspace(0.0, h, samples)):
        dz = ri - wall[:, 2]
        r = np.sqrt(wall[:, 0] ** 2 + wall[:, 1] ** 2 + dz ** 2)
        z_rho[i] = mass * spline_np(r, h).sum()
        z_grad[i] = (mass / rho0) * (np.where(r < h, spline_f_np(r, h), 0.0) * dz).sum()
        z_vis[i] = (mass / rho0) * visc_lap_np(r, h).sum()
    for t in (z_rho, z_grad, z_vis):
        t[-1] = 0.0
    return z_rho, z_grad, z_vis


class SplineWallMaps(BrickWallMaps):
    """The wall map of this module, bricked as walls.maps.BrickWallMaps (whose storage and lookups it shares),
    with the flat-wall factors fix_rho, fix_press (for G), fix_vis indexed by the wall distance."""

    def __init__(self, sdf: SDFGrid, l0: float, h: float, mass: float, rho0: float, samples: int = 256):
        self.h = h
        slots = self._allocate(sdf, l0, h)
        dq = self.spacing
        idx, w = quadrature_stencil(h, dq, dq ** 3 / l0 ** 3, mass, rho0,
                                    kernel=lambda r: (mass * spline_np(r, h), (mass / rho0) * spline_f_np(r, h)))
        build_bricks(sdf.dist, sdf.origin, 1.0 / sdf.spacing, self.origin, dq, self.shape, self.index, slots, h + dq,
                     idx, w, self.bricks)
        # flat-wall factors: the lattice sums over the quadrature of a half space, per wall distance
        z_rho, z_grad, z_vis = flat_wall_tables(l0, h, mass, rho0, samples)
        flat = flat_wall_sums(idx, w, dq, np.linspace(0.0, h, samples))
        self.fix_rho = np.where(flat[:, 0] > 1e-12, z_rho / np.maximum(flat[:, 0], 1e-300), 1.0)
        self.fix_press = np.where(flat[:, 3] > 1e-12, z_grad / np.maximum(flat[:, 3], 1e-300), 1.0)
        self.fix_vis = np.where(flat[:, 4] > 1e-12, z_vis / np.maximum(flat[:, 4], 1e-300), 1.0)
        self.inv_dr = (samples - 1) / h
