"""SPH kernels, wall tables, pair-force symmetry (PHYSICS.md eq. 6-15)."""
import math

import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate import sph_kernels as K
from stages.simulate.effects import cohesion_coef
from stages.simulate.kernels import lattice_mass, poly6_coef, poly6_np, spiky_grad_coef, visc_lap_coef
from stages.simulate.neighbours import CellGrid
from stages.simulate.wall_tables import build_tables, half_space_density


def test_poly6_integrates_to_one():
    h = 0.7
    r = np.linspace(0, h, 20001)
    integral = np.trapezoid(4 * math.pi * r * r * poly6_np(r, h), r)
    assert abs(integral - 1.0) < 1e-6


def test_lattice_mass_gives_rest_density():
    l0, h = 0.01, 0.02
    m = lattice_mass(1000.0, l0, h)
    g = np.arange(-3, 4) * l0
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    rho = m * poly6_np(np.sqrt(X ** 2 + Y ** 2 + Z ** 2), h).sum()
    assert abs(rho - 1000.0) < 1e-9


def test_wall_tables_match_brute_force_wall_particles():
    l0, h, rho0 = 0.01, 0.025, 1000.0
    m = lattice_mass(rho0, l0, h)
    _, z_rho, z_vis, _ = build_tables(l0, h, m, rho0, samples=101)
    # explicit wall: a wide slab of particles below z = 0, first layer at -l0/2
    g = np.arange(-8, 9) * l0
    X, Y, Z = np.meshgrid(g, g, -(0.5 + np.arange(6)) * l0, indexing="ij")
    wall = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    for k in (0, 20, 50, 80):
        r = h * k / 100
        dist = np.linalg.norm(wall - [0, 0, r], axis=1)
        brute = m * poly6_np(dist, h).sum()
        lap = (m / rho0) * np.where(dist < h, visc_lap_coef(h) * (h - dist), 0).sum()
        assert abs(z_rho[k] - brute) <= 1e-9 * rho0
        assert abs(z_vis[k] - lap) <= 1e-9 * max(lap, 1)
    # the continuum limit of PHYSICS.md: Z(0) about rho0 / 2, decaying to 0 at h
    r = np.linspace(0, h, 101)
    assert np.max(np.abs(z_rho - half_space_density(r, h, rho0))) < 0.08 * rho0
    assert z_rho[-1] == 0.0 and np.all(np.diff(z_rho) <= 1e-9)


def test_pair_forces_conserve_momentum_without_walls():
    rng = np.random.default_rng(1)
    l0 = 0.01
    h = 2.0 * l0
    n = 600
    x = rng.uniform(0.2, 0.28, (n, 3))
    v = rng.normal(0, 0.1, (n, 3))
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.5, 0.5, 0.5]), [0, 0, 0], [0.5, 0.5, 0.5], 0.02)
    grid = CellGrid(sdf.origin, sdf.upper, h)
    order = grid.sort(x)
    x, v = x[order].copy(), v[order].copy()
    m = lattice_mass(1000.0, l0, h)
    rho, p, d, nrm = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 3))
    zeros = np.zeros(8)
    no_walls = np.zeros((2, 2, 2, 5), np.float32)  # no wall terms: internal forces only
    wo = np.zeros(3)
    K.density_pressure(x, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, poly6_coef(h), m, 1000.0, no_walls, wo,
                       1.0, zeros, 7 / h, sdf.dist, sdf.origin, 1 / sdf.spacing, K.EOS_LINEAR, 100.0, False, rho, p, d, nrm)
    normals = np.zeros((n, 3))
    K.surface_normals(x, rho, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, spiky_grad_coef(h), m, normals)
    pressure = (p, spiky_grad_coef(h), zeros, 0.5)
    viscosity = (0.01, visc_lap_coef(h), zeros)
    tension = (0.05, normals, cohesion_coef(h))
    for pr, vis, ten in ((pressure, None, None), (pressure, viscosity, None), (None, None, tension),
                         (pressure, viscosity, tension)):
        acc = np.zeros((n, 3))
        K.forces(x, v, rho, d, nrm, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, m, 1000.0, no_walls, wo, 1.0,
                 7 / h, np.zeros(3), acc, pr, vis, ten, None, None, None, None)
        total = (m * acc).sum(axis=0)
        scale = (m * np.abs(acc)).sum()
        assert scale > 0
        assert np.abs(total).max() < 1e-10 * scale


def test_wall_map_counts_every_wall_in_edges_and_corners():
    from stages.simulate.wall_maps import WallMaps, map_sample
    from stages.simulate.wall_tables import table_lookup
    l0, h, rho0 = 0.01, 0.02, 1000.0
    m = lattice_mass(rho0, l0, h)
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.1, 0.1, 0.1]), [0, 0, 0], [0.1, 0.1, 0.1], l0 / 2)
    wm = WallMaps(sdf, l0, h, m, rho0)
    _, z_rho, _, _ = build_tables(l0, h, m, rho0)

    def z(p):
        d, _ = sdf.sample(np.array([p]))
        return map_sample(wm.maps, *wm.origin, 1 / wm.spacing, *p, 0) * table_lookup(wm.fix_rho, d[0], wm.inv_dr)

    flat = z((0.05, 0.05, 0.005))
    assert abs(flat - table_lookup(z_rho, 0.005, wm.inv_dr)) < 0.005 * rho0  # a flat floor: the lattice table
    edge, corner = z((0.005, 0.05, 0.005)), z((0.005, 0.005, 0.005))
    assert 1.7 * flat < edge < 2.0 * flat and 2.4 * flat < corner < 3.0 * flat  # every wall counted once
