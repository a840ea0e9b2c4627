"""Physics validation at CI size: the hydrostatic tank (PHYSICS.md: p = rho g (H - z))."""
import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.simulate.sph import SPHParams, SPHSolver


def test_hydrostatic_tank_settles_to_rho_g_h():
    l0, W, H, g = 0.01, 0.1, 0.2, 9.81  # 10 x 10 x 20 particles
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, 0.3]), [0, 0, 0], [W, W, 0.3], l0 / 2)
    x = lattice([0, 0, 0], [W, W, H], l0)
    # a strong viscosity damps the start-up sloshing so the tank settles within a second (see report)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=SPHParams(threads=None),
                  gravity=(0, 0, -g), mu=5.0, v_ref=float(np.sqrt(2 * g * H)))
    s.advance_to(0.8)
    p_by_id = np.zeros(len(x))
    for k in range(1, 11):  # WCSPH pressure is noisy: average each particle over the last 0.2 s
        s.advance_to(0.8 + 0.02 * k)
        f = s.frame()
        p_by_id[f.id] += f.p / 10
    f.p[:] = p_by_id[f.id]
    z = f.x[:, 2]
    assert z.min() > 0.0  # no particle below the floor
    assert np.linalg.norm(f.v, axis=1).max() < 0.1
    deep = z < H - 3 * l0  # away from the top layers, which lack neighbours
    err = np.abs(f.rho / 1000.0 - 1)
    assert err[deep].mean() < 0.01
    # the worst particles sit in the tank's vertical edges and corners; away from them every one is in
    off_edges = deep & (np.sort(np.minimum(f.x[:, :2], W - f.x[:, :2]), axis=1)[:, 1] > 2 * l0)
    # (a few particles disordered by the start-up sloshing sit above 1 %: with the default artificial
    # viscosity the worst single one measured 2.7 %)
    assert np.percentile(err[off_edges], 99) < 0.01 and err[off_edges].max() < 0.03
    errors = {}
    for depth in (5, 10, 15):  # particles of depth
        # one layer, away from the side walls (the edges carry the one-wall-table error)
        layer = (np.abs(z - (H - (depth - 0.5) * l0)) < 0.5 * l0) & (np.minimum(f.x[:, :2], W - f.x[:, :2]).min(axis=1) > 2 * l0)
        expected = 1000.0 * g * (H - z[layer]).mean()
        errors[depth] = abs(f.p[layer].mean() - expected) / expected
    print('hydrostatic relative error by depth (particles):', errors, 'density error mean', err[deep].mean(),
          'p99 off edges', np.percentile(err[off_edges], 99), 'max', err[deep].max())
    assert max(errors.values()) < 0.12, errors
