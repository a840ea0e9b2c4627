"""SPH smoothing kernels of PHYSICS.md (support radius h; all zero for r >= h).

The inline numba helpers take precomputed coefficients (no globals) so a caller evaluates only
the polynomial in its pair loop."""
from __future__ import annotations

import math

import numba as nb


def poly6_coef(h: float) -> float:
    """Eq. 10: W(r) = 315 / (64 pi h^9) (h^2 - r^2)^3."""
    return 315.0 / (64.0 * math.pi * h ** 9)


def spiky_grad_coef(h: float) -> float:
    """Eq. 8: grad W(r) = -45 / (pi h^6) (h - r)^2 r_hat; returns the positive 45 / (pi h^6)."""
    return 45.0 / (math.pi * h ** 6)


def visc_lap_coef(h: float) -> float:
    """Eq. 9: lap W(r) = 45 / (pi h^6) (h - r)."""
    return 45.0 / (math.pi * h ** 6)


@nb.njit(cache=True, inline="always")
def poly6(r2, h2, coef):
    """Eq. 10 as a function of r^2."""
    if r2 >= h2:
        return 0.0
    q = h2 - r2
    return coef * q * q * q


@nb.njit(cache=True, inline="always")
def visc_lap(r, h, coef):
    """Eq. 9."""
    if r >= h:
        return 0.0
    return coef * (h - r)


def poly6_np(r, h):
    """Vectorised eq. 10 (tests, tables)."""
    import numpy as np
    r = np.asarray(r, float)
    return np.where(r < h, poly6_coef(h) * np.clip(h * h - r * r, 0, None) ** 3, 0.0)


def visc_lap_np(r, h):
    """Vectorised eq. 9 (tables)."""
    import numpy as np
    r = np.asarray(r, float)
    return np.where(r < h, visc_lap_coef(h) * np.clip(h - r, 0, None), 0.0)


def lattice_modes(support: float, samples: int = 24):
    """(offsets, r, waves): the cubic lattice's neighbours within ``support`` (in units of l0, the particle itself
    left out) and wave vectors sampling the Brillouin zone's octant, [0, pi]^3 at ``samples``^3 + points: what the
    largest eigenvalue of a lattice sum's operator is taken over (dfsph.jacobi_limit, timestep.viscous_coefficient)."""
    import numpy as np
    g = np.arange(-math.ceil(support), math.ceil(support) + 1, dtype=float)
    offsets = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    r = np.linalg.norm(offsets, axis=1)
    keep = (r > 0) & (r < support)
    k = np.linspace(0.0, math.pi, samples + 1)
    waves = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)
    return offsets[keep], r[keep], waves


def rest_lattice(l0: float, reach: float):
    """(z, r): the height and distance of every point of the full cubic lattice of spacing l0 within a cube
    reaching past ``reach`` around a particle at the origin (itself included, r = 0), as (n, n, n) arrays: the
    rest state the lattice sums (mass, gradient and viscosity factors, MPS's n0) are calibrated on."""
    import numpy as np
    k = int(math.ceil(reach / l0)) + 1
    g = np.arange(-k, k + 1) * l0
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    return Z, np.sqrt(X * X + Y * Y + Z * Z)


def lattice_mass(rho0: float, l0: float, h: float) -> float:
    """Particle mass such that the eq. 4 kernel sum over a full cubic lattice gives exactly rho0."""
    _, r = rest_lattice(l0, h)
    return float(rho0 / poly6_np(r, h).sum())


def spiky_lattice_factor(rho0: float, l0: float, h: float, mass: float) -> float:
    """sum_j (m / rho0) |grad W(r_j)| x_j^2 / r_j over the rest lattice (1 in the continuum, about 0.95
    at h = 2 l0): dividing the eq. 8 gradient by it makes the discrete pressure force reproduce grad p
    exactly on the rest lattice (a scalar kernel-gradient normalisation)."""
    Z, r = rest_lattice(l0, h)
    sel = (r > 0) & (r < h)
    return float((mass / rho0 * spiky_grad_coef(h) * (h - r[sel]) ** 2 * Z[sel] ** 2 / r[sel]).sum())


def visc_lattice_factor(rho0: float, l0: float, h: float, mass: float) -> float:
    """sum_j (m / rho0) lap W(r_j) z_j^2 / 2 over the rest lattice: what the eq. 9 viscosity sum makes of the
    Laplacian of v = z^2 / 2, whose true value is 1 (the continuum integral is exactly 1 at any h). On the lattice it
    swings with the support: 0.98 at h = 2 l0, 0.87 at 2.25 l0, 1.03 at 2.5 l0 (Poly6's mass), so a user's support of
    2.25 l0 damped a shear mode 17 % below nu k^2. Dividing mu by it makes the viscosity exact on the rest lattice at
    any support (fluid and wall terms alike), as spiky_lattice_factor does for the pressure gradient."""
    Z, r = rest_lattice(l0, h)
    return float((mass / rho0 * visc_lap_np(r, h) * Z * Z).sum() / 2.0)


def wall_gradient_tables(l0: float, h: float, mass: float, rho0: float, grad_norm: float, samples: int = 256):
    """The wall's share of the gradient tensor, T_wall(r) = sum_wall (m / rho0) grad_i W (x) (x_w - x_i)
    (eq. 8 divided by ``grad_norm``), for a particle at distance r above a flat wall of virtual particles
    on the lattice (tables.wall_lattice): T_wall = t_nn n n^T + t_tt (I - n n^T). Returns
    (t_nn, t_tt), each (samples,) on r = h i / (samples - 1). On the rest lattice the fluid's share plus
    this is the identity: the wall's part of grad p that a uniform wall pressure cannot give."""
    import numpy as np
    from .walls.tables import wall_lattice
    wall = wall_lattice(l0, h)
    c = mass / rho0 * spiky_grad_coef(h) / grad_norm
    t_nn = np.zeros(samples)
    t_tt = np.zeros(samples)
    for i, ri in enumerate(np.linspace(0.0, h, samples)):
        dz = ri - wall[:, 2]
        r = np.sqrt(wall[:, 0] ** 2 + wall[:, 1] ** 2 + dz ** 2)
        sel = (r < h) & (r > 1e-12)
        w = c * (h - r[sel]) ** 2 / r[sel]
        t_nn[i] = (w * dz[sel] ** 2).sum()
        t_tt[i] = (w * wall[sel, 0] ** 2).sum()
    t_nn[-1] = 0.0
    t_tt[-1] = 0.0
    return t_nn, t_tt


# The fastmath flags of the hot kernels: reassociation, contraction and fast reciprocals, but not
# 'nnan'/'ninf' (full fastmath), which let LLVM assume no NaN or Inf and fold away the checks that
# catch a blow-up (driver.SolverBase.advance_to).
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}  # a set: numba rejects a frozenset


@nb.njit(cache=True, parallel=True)
def count_blown(x, v, v_limit2):
    """(particles with a non-finite position or velocity, particles faster than sqrt(v_limit2))."""
    bad = 0
    fast = 0
    for i in nb.prange(x.shape[0]):
        s = x[i, 0] + x[i, 1] + x[i, 2] + v[i, 0] + v[i, 1] + v[i, 2]
        if not math.isfinite(s):
            bad += 1
        elif v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2] > v_limit2:
            fast += 1
    return bad, fast
