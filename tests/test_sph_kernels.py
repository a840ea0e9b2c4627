"""SPH kernels, wall tables, pair-force symmetry (PHYSICS.md eq. 6-15)."""
import math

import numpy as np
import pytest

from stages.common.sdf import box_interior_sdf, grid_from_function, wall_move_limit
from stages.simulate import sph_kernels as K
from conftest import no_wall_terms
from stages.simulate.walls.maps import BrickWallMaps, make_walls, push_out
from stages.simulate.effects import cohesion_coef
from stages.simulate.emitters import lattice
from stages.simulate.kernels import lattice_mass, poly6_coef, poly6_np, spiky_grad_coef, visc_lap_coef
from stages.simulate.neighbours import CellGrid
from stages.simulate.walls.tables import build_tables, half_space_density


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
    walls = no_wall_terms(sdf, h)
    K.density_pressure(x, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, poly6_coef(h), m, 1000.0, walls,
                       K.EOS_LINEAR, 100.0, False, rho, p, d, nrm)
    normals = np.zeros((n, 3))
    K.surface_normals(x, rho, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, spiky_grad_coef(h), m, normals)
    pressure = (p, spiky_grad_coef(h), 0.5)
    viscosity = (0.01, visc_lap_coef(h), zeros)
    tension = (0.05, normals, cohesion_coef(h))
    for pr, vis, ten in ((pressure, None, None), (pressure, viscosity, None), (None, None, tension),
                         (pressure, viscosity, tension)):
        acc = np.zeros((n, 3))
        K.forces(x, v, rho, d, nrm, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, m, 1000.0, walls, np.zeros(3),
                 acc, pr, vis, ten, None, None, None, None)
        total = (m * acc).sum(axis=0)
        scale = (m * np.abs(acc)).sum()
        assert scale > 0
        assert np.abs(total).max() < 1e-10 * scale


def test_wall_map_counts_every_wall_in_edges_and_corners():
    from stages.simulate.walls.maps import WallMaps, map_sample
    from stages.simulate.walls.tables import table_lookup
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


def _random_cloud(n=1400, seed=3):
    rng = np.random.default_rng(seed)
    l0 = 0.01
    h = 2.0 * l0
    x = rng.uniform(0.008, 0.11, (n, 3))  # ~30 % denser than the lattice, some within h of the walls
    v = rng.normal(0, 0.1, (n, 3))
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.14, 0.14, 0.14]), [0, 0, 0], [0.14, 0.14, 0.14], l0)
    grid = CellGrid(sdf.origin, sdf.upper, h)
    order = grid.sort(x)
    return x[order].copy(), v[order].copy(), sdf, grid, l0, h


def test_neighbour_list_is_exactly_the_pairs_within_h_in_scan_order_and_reports_overflow():
    from stages.simulate.neighbours import neighbour_list
    x, _, _, grid, _, h = _random_cloud()
    n = len(x)
    big = np.zeros((n, 200), np.int32)
    cnt = np.zeros(n, np.int32)
    neighbour_list(x, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, big, cnt)
    r2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    for i in range(n):
        brute = np.flatnonzero(r2[i] < h * h)
        assert sorted(big[i, :cnt[i]]) == list(brute)
    assert cnt.max() > 40
    # a capacity below the largest count: the true counts are still reported, the stored prefix agrees
    small = np.zeros((n, 16), np.int32)
    cnt2 = np.zeros(n, np.int32)
    neighbour_list(x, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, small, cnt2)
    assert np.array_equal(cnt, cnt2) and np.array_equal(small, big[:, :16])


def test_list_kernels_are_the_cell_scan_kernels():
    """density_verlet (a list at radius h) + surface_normals(neighbours) against the cell-scan kernels:
    the same pairs in the same order, so the same bits; forces(neighbours, inv_rho) the same to rounding
    (a fastmath build: the two loop forms may contract differently), for every effect set."""
    from stages.simulate.neighbours import neighbour_list
    x, v, sdf, grid, l0, h = _random_cloud()
    n = len(x)
    m = lattice_mass(1000.0, l0, h)
    g = (grid.starts, grid.lo, 1 / grid.cell, grid.dims)
    walls = make_walls(sdf, BrickWallMaps(sdf, l0, h, m, 1000.0, 64))  # walls within h of some particles
    common = (h, poly6_coef(h), m, 1000.0, walls, K.EOS_LINEAR, 100.0, True)
    a = [np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 3))]
    K.density_pressure(x, *g, *common, *a)
    nbr, cnt, inv_rho = np.zeros((n, 80), np.int32), np.zeros(n, np.int32), np.zeros(n)
    neighbour_list(x, *g, h, nbr, cnt)
    b = [np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 3))]
    cnt_in = np.zeros(n, np.int32)
    K.density_verlet(x, nbr, cnt, cnt_in, *common, *b, inv_rho)
    assert np.array_equal(cnt_in, cnt)
    for u, w in zip(a, b):
        assert np.array_equal(u, w)
    rho, p, d, nrm = b
    assert (d < h).any() and np.array_equal(inv_rho, 1.0 / rho)
    gc = spiky_grad_coef(h)
    n1, n2 = np.zeros((n, 3)), np.zeros((n, 3))
    K.surface_normals(x, rho, *g, h, gc, m, n1)
    K.surface_normals(x, rho, *g, h, gc, m, n2, (nbr, cnt))
    assert np.array_equal(n1, n2)
    walls = walls._replace(fix_rho=np.linspace(1.0, 0.5, 64))
    press = (p, gc, 0.5)
    vis = (0.01, visc_lap_coef(h), np.linspace(1.0, 0.0, 64))
    ten = (0.05, n1, cohesion_coef(h))
    adh, fri = (np.linspace(2.0, 0.0, 64),), (3.0,)
    wind, att = (np.array([1.0, 0.0, 0.0]), 2.0), (np.array([0.07, 0.07, 0.2]), 0.01, 0.01)
    grav = np.array([0.0, 0.0, -9.81])
    for effects in ((press, vis, None, None, None, None, None), (None, vis, ten, adh, fri, wind, att),
                    (press, vis, ten, adh, fri, wind, att)):
        acc1, acc2 = np.zeros((n, 3)), np.zeros((n, 3))
        args = (x, v, rho, d, nrm, *g, h, m, 1000.0, walls, grav)
        K.forces(*args, acc1, *effects)
        K.forces(*args, acc2, *effects, (nbr, cnt), inv_rho)
        assert np.abs(acc1).max() > 0 and np.abs(acc1 - acc2).max() <= 1e-13 * np.abs(acc1).max()


def test_verlet_density_finds_every_pair_while_particles_move_less_than_the_skin():
    """A list built at h + skin, particles then moved by up to skin / 2 each: density_verlet gives the
    density of the cell scan at the new positions (to rounding), its first cnt_in entries of each row
    are exactly the pairs r < h, and every candidate of the row is still there (only reordered)."""
    from stages.simulate.neighbours import neighbour_list
    x, _, sdf, grid, l0, h = _random_cloud()
    n = len(x)
    skin = 0.3 * l0
    m = lattice_mass(1000.0, l0, h)
    vgrid = CellGrid(sdf.origin, sdf.upper, h + skin)
    order = vgrid.sort(x)
    x = x[order].copy()
    nbr, cnt = np.zeros((n, 120), np.int32), np.zeros(n, np.int32)
    neighbour_list(x, vgrid.starts, vgrid.lo, 1 / vgrid.cell, vgrid.dims, h + skin, nbr, cnt)
    built = [sorted(nbr[i, :cnt[i]]) for i in range(n)]
    rng = np.random.default_rng(7)
    step = rng.normal(size=(n, 3))
    step *= (0.499 * skin * rng.uniform(0, 1, n) / np.linalg.norm(step, axis=1))[:, None]
    y = x + step
    walls = make_walls(sdf, BrickWallMaps(sdf, l0, h, m, 1000.0, 64))  # walls within h of some particles
    common = (h, poly6_coef(h), m, 1000.0, walls, K.EOS_LINEAR, 100.0, True)
    cnt_in, inv_rho = np.zeros(n, np.int32), np.zeros(n)
    b = [np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 3))]
    K.density_verlet(y, nbr, cnt, cnt_in, *common, *b, inv_rho)
    g = CellGrid(sdf.origin, sdf.upper, h)
    o2 = g.sort(y)
    a = [np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 3))]
    K.density_pressure(y[o2].copy(), g.starts, g.lo, 1 / g.cell, g.dims, *common, *a)
    inv = np.argsort(o2)
    assert np.allclose(b[0], a[0][inv], rtol=1e-13, atol=0) and np.allclose(b[1], a[1][inv], rtol=1e-12, atol=1e-9)
    r2 = ((y[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    moved = 0
    for i in range(n):
        assert sorted(nbr[i, :cnt_in[i]]) == list(np.flatnonzero(r2[i] < h * h))
        assert sorted(nbr[i, :cnt[i]]) == built[i]
        moved += cnt_in[i] != np.count_nonzero(((x[i] - x) ** 2).sum(1) < h * h)
    assert moved > 50  # the moves changed who is within h for many particles


def test_bulk_particles_skipping_the_sdf_changes_nothing():
    """integrate keeps a lower bound of each particle's wall distance, so particles far from the walls
    skip the SDF samples (eq. 16 test, density wall term): the run is bitwise the run that samples
    every particle every step, here a breaking dam whose particles hit the walls."""
    from stages.common.sdf import wall_move_limit
    from stages.simulate import sph as S
    from stages.simulate.timestep import step_to

    class SamplingEverywhere(S.SPHSolver):
        def step(self, t_end):
            self.d[:] = -1.0  # unknown: the density pass samples every particle
            self.sort_and_density()
            self.forces()
            dt = step_to(self.t, t_end, self.stable_dt(t_end - self.t))
            K.integrate(self.x, self.v, self.acc, dt, self.wall_terms,
                        self.p.r_rep * self.l0, 0.5 * self.l0, wall_move_limit(self.p.r_rep) * self.l0,
                        self.travel)  # no bound: every particle tested
            self.t = t_end if dt >= t_end - self.t else self.t + dt
            self.steps += 1
            return dt

    l0 = 0.01
    x = lattice_block([0.005, 0.005, 0.005], [0.1, 0.1, 0.12], l0)
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.3, 0.12, 0.2]), [0, 0, 0], [0.3, 0.12, 0.2], l0 / 2)
    runs = [cls(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=S.SPHParams(),
                gravity=(0, 0, -9.81), mu=0.01, v_ref=1.5) for cls in (S.SPHSolver, SamplingEverywhere)]
    for s in runs:
        s.advance_to(0.2)
    fast, slow = runs
    assert np.abs(fast.v).max() > 0.5 and fast.x[:, 0].max() > 0.2  # the surge ran along the floor
    assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.v, slow.v) and fast.steps == slow.steps


def lattice_block(lo, hi, l0):
    g = [np.arange(a, b, l0) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)


def test_solver_grows_the_neighbour_list_and_matches_a_roomy_one():
    """A list that starts too small (compressed start) is grown; the result does not depend on it."""
    from stages.simulate import sph as S
    rng = np.random.default_rng(5)
    l0 = 0.01
    x = rng.uniform(0.03, 0.09, (1500, 3))  # ~1.4 x the lattice density: > 16 neighbours everywhere
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.12, 0.12, 0.12]), [0, 0, 0], [0.12, 0.12, 0.12], l0)
    runs = []
    for cap in (16, 200):
        s = S.SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=S.SPHParams(),
                        gravity=(0, 0, -9.81), mu=0.01)
        s.nbr_cap = cap  # the list's starting size (else the rest lattice's count within h + skin)
        s._resized()
        for _ in range(5):
            s.step(1.0)
        runs.append(s)
    assert runs[0].nbr.shape[1] > 16 and runs[0].nbr.shape[1] >= runs[0].cnt.max()
    assert np.array_equal(runs[0].x, runs[1].x) and np.array_equal(runs[0].v, runs[1].v)


@pytest.mark.parametrize("kernel, slots", [("spline", 89), ("poly6_spiky", 48)])
def test_neighbour_list_starts_at_the_rest_lattice_count(kernel, slots):
    """The list starts at the kernel's rest-lattice count within h + skin plus the slack (81 + 8 for the spline at
    2.25 l0 with the 0.2 l0 skin; Poly6 / Spiky's 33 is below NEIGHBOUR_CAP): a hydrostatic tank's first builds
    do not grow it, so the peak memory never holds two lists (it held 48 + 89 slots before)."""
    from stages.simulate import sph as S
    from stages.simulate.driver import hydrostatic_start
    l0 = 0.01
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.1, 0.1, 0.2]), [0, 0, 0], [0.1, 0.1, 0.2], l0 / 2)
    x = lattice([0, 0, 0], [0.1, 0.1, 0.15], l0)
    s = S.SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                    params=S.SPHParams(kernel=kernel), gravity=(0, 0, -9.81), mu=0.001, v_ref=float(np.sqrt(2 * 9.81 * 0.15)))
    hydrostatic_start(s)
    assert s.nbr.shape[1] == slots
    for _ in range(3):
        s.step(1.0)
    assert s.nbr.shape[1] == slots and s.cnt.max() <= slots


def test_bricked_wall_maps_are_the_dense_maps():
    """BrickWallMaps keeps only the bricks near the walls, with the same node values as WallMaps, and
    the kernels' lookups through it give the same bits (a box with a sphere inside: edges, corners
    and a curved wall)."""
    from stages.simulate.walls.maps import BrickWallMaps, brick_sample
    from stages.simulate.walls.maps import WallMaps, map_sample
    l0, h, rho0 = 0.01, 0.02, 1000.0
    m = lattice_mass(rho0, l0, h)
    box = box_interior_sdf([0, 0, 0], [0.6, 0.4, 0.4])
    sdf = grid_from_function(lambda p: np.minimum(box(p), np.linalg.norm(p - [0.3, 0.2, 0.2], axis=1) - 0.08),
                             [0, 0, 0], [0.6, 0.4, 0.4], l0)
    dense = WallMaps(sdf, l0, h, m, rho0, 64)
    bricks = BrickWallMaps(sdf, l0, h, m, rho0, 64)
    assert bricks.nbytes < 0.7 * dense.maps.nbytes  # 0.61 here; the thinner the band, the less
    assert np.array_equal(bricks.maps, dense.maps)
    for name in ("fix_rho", "fix_press", "fix_vis", "inv_dr"):
        assert np.array_equal(getattr(bricks, name), getattr(dense, name))
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.01, 0.61, (3000, 3)) * [1, 2 / 3, 2 / 3]
    inv = 1 / dense.spacing
    for c in range(5):
        a = [map_sample(dense.maps, *dense.origin, inv, *p, c) for p in pts]
        b = [brick_sample(*bricks.wmap, *bricks.origin, inv, *p, c) for p in pts]
        assert np.array_equal(a, b) and np.count_nonzero(a) > 100


def _jittered_block(jitter=0.15, n=12, seed=4):
    """A cubic block of n^3 particles at l0 = 1 cm, each moved by up to ``jitter`` l0, in cell order,
    with its neighbour list and density (no walls within h)."""
    from stages.simulate.neighbours import neighbour_list
    rng = np.random.default_rng(seed)
    l0, h = 0.01, 0.02
    g = (np.arange(n) + 0.5) * l0 + 0.05
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = x + rng.uniform(-jitter, jitter, x.shape) * l0
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.22, 0.22, 0.22]), [0, 0, 0], [0.22, 0.22, 0.22], l0)
    grid = CellGrid(sdf.origin, sdf.upper, h)
    x = x[grid.sort(x)].copy()
    m = lattice_mass(1000.0, l0, h)
    N = len(x)
    nbr, cnt = np.zeros((N, 80), np.int32), np.zeros(N, np.int32)
    neighbour_list(x, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, nbr, cnt)
    rho, p, d, nrm, inv_rho = np.zeros(N), np.zeros(N), np.zeros(N), np.zeros((N, 3)), np.zeros(N)
    walls = no_wall_terms(sdf, h)
    K.density_verlet(x, nbr, cnt, np.zeros(N, np.int32), h, poly6_coef(h), m, 1000.0, walls, K.EOS_LINEAR, 100.0, False,
                     rho, p, d, nrm, inv_rho)
    return x, nbr, cnt, rho, inv_rho, d, nrm, grid, m, l0, h


def _correction(x, nbr, cnt, rho, inv_rho, d, nrm, m, h, wall_t=None, inv_dr=1.0):
    from stages.simulate.kernels import spiky_lattice_factor
    gc = spiky_grad_coef(h) / spiky_lattice_factor(1000.0, 0.01, h, m)
    L = np.zeros((len(x), 6))
    K.gradient_correction(x, nbr, cnt, inv_rho, rho, 1000.0, h, gc, m, 0.9, 0.97, d, nrm, wall_t, inv_dr, True, L)
    return L, gc


def test_gradient_correction_makes_the_pressure_gradient_exact_on_a_disordered_packing():
    """L_i = T_i^-1: sum_j V_j (p_j - p_i) L_i grad W_ij = grad p for a linear p on a jittered lattice
    (where the plain normalised Spiky sum is off by several %), L = I on the rest lattice, and the
    identity where the support is not full (the block's faces)."""
    x, nbr, cnt, rho, inv_rho, d, nrm, grid, m, l0, h = _jittered_block()
    L, gc = _correction(x, nbr, cnt, rho, inv_rho, d, nrm, m, h)
    gp = np.array([300.0, -200.0, -9810.0])  # Pa / m
    p = x @ gp
    # full support, and dense enough for the full correction (it fades out below 0.97 rho0)
    inner = np.all(np.abs(x - x.mean(0)) < 0.06 - 2.5 * l0, axis=1) & (rho >= 0.97 * 1000.0)
    assert inner.sum() > 100
    plain_err, corr_err = [], []
    for i in np.flatnonzero(inner):
        j = nbr[i, :cnt[i]]
        j = j[j != i]
        dx = x[i] - x[j]
        r = np.linalg.norm(dx, axis=1)
        grad = -(gc * (h - r) ** 2 / r)[:, None] * dx  # grad_i W_ij
        s = ((m * inv_rho[j] * (p[j] - p[i]))[:, None] * grad).sum(0)
        Li = L[i][[0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(3, 3)
        plain_err.append(np.linalg.norm(s - gp) / np.linalg.norm(gp))
        corr_err.append(np.linalg.norm(Li @ s - gp) / np.linalg.norm(gp))
    assert np.mean(plain_err) > 0.02 and max(corr_err) < 1e-9
    # the particles with a thin support (faces, edges) keep the plain gradient
    assert np.allclose(L[rho < 0.9 * 1000.0], [1, 1, 1, 0, 0, 0])
    # the rest lattice: T = I (the Spiky normalisation), so L = I
    x0, nbr0, cnt0, rho0, inv0, d0, nrm0, _, _, _, _ = _jittered_block(jitter=0.0)
    L0, _ = _correction(x0, nbr0, cnt0, rho0, inv0, d0, nrm0, m, h)
    full = np.all(np.abs(x0 - x0.mean(0)) < 0.06 - 2.5 * l0, axis=1)
    assert np.abs(L0[full] - [1, 1, 1, 0, 0, 0]).max() < 1e-9


def _box_sdf(grid):
    """A box SDF over the cell grid: the pressure term's SDF (its walls are out of reach: d = 1 m is passed)."""
    sdf = grid_from_function(box_interior_sdf(grid.lo, grid.lo + grid.cell * grid.dims), grid.lo,
                             grid.lo + grid.cell * grid.dims, grid.cell)
    return sdf


def test_corrected_pair_forces_conserve_momentum():
    """0.5 (L_i + L_j) grad W_ij keeps the pair force antisymmetric: the internal forces sum to zero."""
    x, nbr, cnt, rho, inv_rho, d, nrm, grid, m, l0, h = _jittered_block(jitter=0.3)
    L, gc = _correction(x, nbr, cnt, rho, inv_rho, d, nrm, m, h)
    assert np.abs(L - [1, 1, 1, 0, 0, 0]).max() > 0.05
    rng = np.random.default_rng(7)
    n = len(x)
    p = rng.uniform(0, 500.0, n)
    v = rng.normal(0, 0.1, (n, 3))
    acc = np.zeros((n, 3))
    walls = no_wall_terms(_box_sdf(grid), h)
    K.forces(x, v, rho, np.full(n, 1.0), nrm, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, m, 1000.0, walls,
             np.zeros(3), acc, (p, gc, 0.5), None, None, None, None, None, None,
             (nbr, cnt), inv_rho, (L,))
    total = (m * acc).sum(axis=0)
    assert np.abs(total).max() < 1e-10 * (m * np.abs(acc)).sum()


def test_wall_gradient_tables_complete_the_lattice_tensor_at_a_flat_wall():
    """Fluid lattice above a flat wall: its share of T = sum V grad W (x) (x_j - x_i) plus the wall's
    table share t_nn n n^T + t_tt (I - n n^T) is the identity, at every lattice distance from the wall."""
    from stages.simulate.kernels import spiky_lattice_factor, wall_gradient_tables
    l0, h, rho0 = 0.01, 0.02, 1000.0
    m = lattice_mass(rho0, l0, h)
    gn = spiky_lattice_factor(rho0, l0, h, m)
    samples = 81
    t_nn, t_tt = wall_gradient_tables(l0, h, m, rho0, gn, samples)
    g = np.arange(-3, 4) * l0
    X, Y, Z = np.meshgrid(g, g, (np.arange(6) + 0.5) * l0, indexing="ij")
    fluid = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    for k in (0, 1, 2):
        xi = np.array([0.0, 0.0, (k + 0.5) * l0])
        dx = xi - fluid
        r = np.linalg.norm(dx, axis=1)
        sel = (r > 1e-12) & (r < h)
        w = m / rho0 * spiky_grad_coef(h) / gn * (h - r[sel]) ** 2 / r[sel]
        T = (w[:, None, None] * dx[sel, :, None] * dx[sel, None, :]).sum(0)
        i = (k + 0.5) * l0 / h * (samples - 1)  # a table node for k = 0, 1; linear between for 2 (beyond h: 0)
        tn, tt = (np.interp(i, np.arange(samples), t) for t in (t_nn, t_tt))
        assert np.allclose(T + np.diag([tt, tt, tn]), np.eye(3), atol=1e-9 if k < 2 else 5e-3)
    assert t_nn[0] > 0.5 and t_tt[0] > 0.4 and t_nn[-1] == 0.0 and t_tt[-1] == 0.0


def test_wall_pressure_force_is_the_derivative_of_the_wall_density():
    """The conservative wall pressure (issue 17): a lone particle near a box's floor, an edge and a corner
    feels a = -(p / rho^2) grad rho, rho its density from density_pressure (its own kernel value plus the
    wall term Z_rho fix_rho at its position), the gradient by central differences half a wall-map node
    apart as the force kernel takes it (continuous across the map's node planes, where the trilinear
    slope jumps; the energy test in test_sph_validation.py checks that this keeps the energy falling)."""
    from stages.simulate.walls.maps import WallMaps
    l0, h = 0.01, 0.02
    m = lattice_mass(1000.0, l0, h)
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.1, 0.1, 0.1]), [0, 0, 0], [0.1, 0.1, 0.1], l0 / 2)
    wm = WallMaps(sdf, l0, h, m, 1000.0, 256)
    grid = CellGrid(sdf.origin, sdf.upper, h)
    walls = make_walls(sdf, BrickWallMaps(sdf, l0, h, m, 1000.0, 256))

    def density(p):
        x = np.array([p], float)
        grid.sort(x)
        out = [np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((1, 3))]
        K.density_pressure(x, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, poly6_coef(h), m, 1000.0, walls,
                           K.EOS_LINEAR, 100.0, False, *out)
        return x, out

    for point in ([0.05, 0.05, 0.0063], [0.0071, 0.05, 0.0113], [0.0062, 0.0125, 0.0135]):
        x, (rho, p, d, nrm) = density(point)
        acc = np.zeros((1, 3))
        K.forces(x, np.zeros((1, 3)), rho, d, nrm, grid.starts, grid.lo, 1 / grid.cell, grid.dims, h, m, 1000.0,
                 walls, np.zeros(3), acc, (p, spiky_grad_coef(h), 0.0), None, None, None, None, None, None)
        e = 0.5 * wm.spacing
        grad = np.array([(density(np.add(point, e * u))[1][0][0] - density(np.subtract(point, e * u))[1][0][0]) / (2 * e)
                         for u in np.eye(3)])
        expected = -p[0] / rho[0] ** 2 * grad
        assert np.linalg.norm(expected) > 1.0  # a real wall force (m/s^2)
        assert np.linalg.norm(acc[0] - expected) < 1e-6 * np.linalg.norm(expected), (point, acc[0], expected)


def _plain_push_out(p, v, sdf, r_rep, max_corr):
    """The eq. 16 push-out along the normal alone (before walls.maps.push_move)."""
    p, v = np.array(p, float), np.array(v, float)
    for _ in range(3):
        d, nx, ny, nz = K.sdf_sample(sdf.dist, *sdf.origin, 1.0 / sdf.spacing, *p)
        if d >= r_rep * 0.999:
            break
        n = np.array([nx, ny, nz])
        p += min(r_rep - d, max_corr) * n
        vn = v @ n
        if vn < 0:
            v -= vn * n
    return p, v


def _push_out(p, v, sdf, r_rep, max_corr):
    return push_out(no_wall_terms(sdf, 2 * r_rep), None, -1, *p, *v, r_rep, max_corr, True)


def test_push_out_leaves_an_acute_v_and_keeps_right_angled_corners():
    """A particle in the apex of a 20 degree V trough (both sides within r_rep) ends outside both sides
    with no velocity into a side it touches, where projections along the normal alone ping-pong between
    the sides and leave some inside one (the stability suite's wedge); in a box's edges and corners the
    push-out moves the particle as the plain projection (to rounding)."""
    l0, r_rep, max_corr = 0.02, 0.2 * 0.02, 0.5 * 0.02
    half = math.radians(10.0)
    n1 = np.array([math.cos(half), 0.0, math.sin(half)])
    n2 = np.array([-math.cos(half), 0.0, math.sin(half)])
    apex = np.array([0.15, 0.0, 0.0])

    def planes(q):
        return np.minimum((q - apex) @ n1, (q - apex) @ n2)

    lo, hi = np.zeros(3), np.array([0.3, 0.1, 0.2])
    sdf = grid_from_function(lambda q: np.minimum(box_interior_sdf(lo, hi)(q), planes(q)), lo, hi, l0 / 2)
    rng = np.random.default_rng(3)
    worst_plain, worst = np.inf, np.inf
    for _ in range(200):  # points in the apex, within r_rep of both sides, moving down
        z = rng.uniform(0.1, 1.0) * r_rep / math.sin(half)
        x = 0.15 + rng.uniform(-0.9, 0.9) * z * math.tan(half)
        p0 = np.array([x, 0.05, z])
        out = _push_out(p0, (0.0, 0.0, -1.0), sdf, r_rep, max_corr)
        worst = min(worst, float(planes(np.array(out[:3])[None])[0]))
        worst_plain = min(worst_plain, float(planes(_plain_push_out(p0, [0, 0, -1.0], sdf, r_rep, max_corr)[0][None])[0]))
        q, v = np.array(out[:3]), np.array(out[3:])
        for n in (n1, n2):  # no velocity left into a side the particle touches
            assert (q - apex) @ n > 1.001 * r_rep or v @ n > -0.02  # (the grid normal, not the exact one)
    assert worst_plain < -0.1 * r_rep  # the plain projection leaves some inside a side
    assert worst > 0.0, worst / r_rep
    # a box: edges and corners (orthogonal normals) moved as by the plain projection, to the last bits (numpy's
    # dot product is the CPU's BLAS kernel: on an AVX-512 machine it rounded one velocity 1 ulp off numba's sum);
    # the velocity as the plain projection's, or with more of it taken away where the particle is left on a
    # wall (contact_velocity: only taken away, along the grid's normals)
    box = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    same = 0
    for _ in range(200):
        p0 = rng.uniform(-0.3, 0.6, 3) * l0 + np.where(rng.random(3) < 0.5, lo, hi - 0.3 * l0)
        v0 = rng.normal(size=3)
        out = _push_out(p0, v0, box, 0.5 * l0, max_corr)
        p, v = _plain_push_out(p0, v0, box, 0.5 * l0, max_corr)
        np.testing.assert_allclose(np.array(out[:3]), p, rtol=1e-14, atol=1e-17)
        u = np.array(out[3:])
        same += bool(np.allclose(u, v, rtol=1e-14, atol=1e-17))
        assert u @ u <= v @ v + 1e-12
    assert same > 150, same


@pytest.mark.parametrize("pressed, along, exact", [
    ([0, 0, -1], [0.1, 0.05, 0], True), ([-1, 0, -1], [0, 0.1, 0], True), ([-1, -1, -1], [0, 0, 0], True),
    ([-1, 0, -2], [0, 0.1, 0], False), ([-1, -0.5, -2], [0, 0, 0], False)],
    ids=["floor", "edge", "corner", "edge, pressed unevenly", "corner, pressed unevenly"])
def test_a_particle_pressed_on_walls_keeps_no_velocity_into_them(pressed, along, exact):
    """A particle held on a floor, in an edge or in a corner by a steady push (gravity, the fluid's pressure:
    10 g here) stays where the push-out holds it, keeps its velocity along the walls, and none into them.
    The push-out alone took the velocity into a wall only on the steps that crossed its tolerance (0.999 r_rep),
    so a particle on a wall kept up to a dt of the push into it between them (0.03 m/s here; 0.015 on average
    over the steps on the floor), and in an edge the velocity into the wall whose normal the SDF's gradient did
    not give: at rest the clamped rows carried up to 0.03 m/s into the walls (issue 17; maps.contact_velocity).
    Pressed unevenly into an edge or corner the particle still jitters: the trilinear SDF rounds the walls'
    meeting within a node, where its normal is diagonal, and a push there moves it a thousandth of r_rep off
    the wall pressed less (measured, edge / corner: 0.0054 / 0.0038 m/s into the walls on average over the
    steps, against 0.016 / 0.018 with the push-out alone; evenly pressed: 0, against 0.010 / 0.008)."""
    l0, dt = 0.02, 3e-4
    r_rep = 0.5 * l0
    lo, hi = np.zeros(3), np.array([0.3, 0.1, 0.2])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    walls = no_wall_terms(sdf, 2 * l0)
    pressed = np.array(pressed, float)
    held = pressed < 0
    x = np.where(held, r_rep, [0.1337, 0.0421, 0.0913])[None]  # off the SDF's nodes along the walls
    v = np.array([along], float)
    acc = 10 * 9.81 * pressed[None] / np.linalg.norm(pressed)
    push = 10 * 9.81 * dt  # the velocity one step of the push gives
    into = []
    for _ in range(100):
        K.integrate(x, v, acc, dt, walls, r_rep, 0.5 * l0, wall_move_limit(0.5) * l0)
        assert np.all(np.abs(x[0, held] / r_rep - 1) < 2e-3), x / r_rep
        into.append(max(0.0, float((v[0, held] * np.sign(pressed[held])).max())))  # the fastest into a held wall
        np.testing.assert_allclose(v[0, ~held], np.array(along, float)[~held], rtol=1e-12)  # all of it along them
    print("into the walls, m/s: mean", np.mean(into), "max", max(into), "a dt", push)
    if exact:
        assert max(into) < 1e-12, max(into)
    else:
        assert np.mean(into) < 0.25 * push, (np.mean(into), push)


def test_a_move_takes_at_most_max_sub_steps_so_a_diverged_step_returns_to_the_guard():
    """A move near a wall is split into sub-steps of at most max_move; a diverged solve's velocity (1e21 m/s in
    test_dfsph's runs beyond the Jacobi limit) made that 1e24 sub-steps, and the step never returned to the guard that
    reports the blow-up. The count is now bounded; a non-finite move takes one (the guard stops it after the step)."""
    assert K.sub_steps(0.5, 1.0) == 1
    assert K.sub_steps(2.5, 1.0) == 3
    assert K.sub_steps(1e30, 1.0) == K.MAX_SUB_STEPS
    assert K.sub_steps(math.inf, 1.0) == K.MAX_SUB_STEPS
    assert K.sub_steps(math.nan, 1.0) == 1
