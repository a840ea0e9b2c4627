"""simulate.dfsph (experimental): the pieces of the solver against brute force and finite differences;
the hydrostatic tank is a strict xfail until the odd-even decoupling is fixed (see dfsph.py)."""
import numpy as np
import pytest

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
from stages.simulate.emitters import lattice
from stages.simulate.kernels import poly6_np

L0, W, H, G = 0.01, 0.1, 0.2, 9.81


def _tank(jitter=0.0, **params):
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, 0.3]), [0, 0, 0], [W, W, 0.3], L0 / 2)
    x = lattice([0, 0, 0], [W, W, H], L0)
    if jitter:
        x = x + np.random.default_rng(0).normal(0, jitter * L0, x.shape)
    return DFSPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0,
                       params=DFSPHParams(threads=None, **params), gravity=(0, 0, -G), mu=0.01)


def test_neighbour_lists_and_density_match_brute_force():
    s = _tank(jitter=0.05)
    s.cap = 4  # far too small: the pass must grow it, never drop a neighbour
    s._alloc()
    s.refresh()
    assert s.cap >= s.count.max()
    for i in (0, 137, 801, 1999):
        r = np.linalg.norm(s.x - s.x[i], axis=1)
        expect = set(np.flatnonzero(r < s.h)) - {i}
        assert set(s.nbr[i * s.cap:i * s.cap + s.count[i]].tolist()) == expect
        fluid = s.mass * poly6_np(r, s.h).sum()
        assert s.rho[i] >= fluid - 1e-9  # plus the wall's share (eq. 11)
        if s.d[i] >= s.h:
            assert s.rho[i] == pytest.approx(fluid, rel=1e-12)


def test_wall_gradient_balances_the_fluid_gradient_on_a_flat_floor():
    """A particle l0/2 above the floor in the rest lattice: sum_fluid m grad W + Psi = 0 (the wall stands
    in for the missing half of the neighbourhood), with the exact Poly6 derivative of the density."""
    s = _tank(gradient="poly6")
    s.refresh()
    i = np.argmin(np.linalg.norm(s.x - [0.045, 0.045, 0.005], axis=1))
    n = s.count[i]
    j = s.nbr[i * s.cap:i * s.cap + n]
    S = -s.mass * (s.fac[i * s.cap:i * s.cap + n, None] * (s.x[i] - s.x[j])).sum(axis=0)
    assert S[2] > 0 and s.psi[i, 2] < 0
    assert abs(S[2] + s.psi[i, 2]) < 0.05 * S[2]
    assert np.allclose(s.psi[i, :2], 0.0, atol=1e-6 * S[2])


def test_predicted_density_rate_matches_the_real_change():
    """D rho / Dt of the solver (fluid pairs + wall term) against the density recomputed after a tiny move."""
    from stages.simulate import dfsph_kernels as D
    s = _tank(jitter=0.05, gradient="poly6")
    s.refresh()
    vel = np.random.default_rng(1).normal(0, 1, s.x.shape)
    rate = np.zeros(len(s.x))
    for sign in (1, -1):  # the kernel clamps at 0: the signed rate from +v and -v
        s.v[:] = sign * vel
        kappa, err = np.zeros(len(s.x)), np.zeros(len(s.x))
        D.jacobi_density(s.x, s.v, np.zeros_like(s.x), s.nbr, s.fac, s.count, s.cap, s.mass, s.psi, s.rho * 0,
                         s.alpha, 0.0, 1.0, kappa, err)
        rate += sign * err
    dt = 1e-6
    moved = DFSPHSolver(s.x + dt * vel, np.zeros_like(s.x), s.id, s.sdf, spacing=L0, rho0=1000.0, params=s.p,
                        gravity=(0, 0, -G), mu=0.01)
    moved.refresh()
    after = np.empty(len(s.x))
    after[moved.id] = moved.rho
    before = np.empty(len(s.x))
    before[s.id] = s.rho
    real = np.empty(len(s.x))
    real[s.id] = rate
    actual = (after - before) / dt
    d = np.empty(len(s.x))
    d[s.id] = s.d
    far = d >= s.h
    # away from walls the Poly6 rate is the exact derivative of the density
    assert np.abs(actual - real)[far].max() < 1e-3 * np.abs(actual).max()
    # near walls Psi is a central difference (step l0/4) of the trilinear wall map, whose own slope jumps
    # at the map's cell faces (l0/2): they agree in the mean, not per particle
    assert np.corrcoef(actual[~far], real[~far])[0, 1] > 0.95


def test_resume_is_bitwise_identical():
    a = _tank()
    a.advance_to(0.02)
    saved = {k: np.copy(v) for k, v in a.state().items()}
    a.advance_to(0.04)
    b = _tank()
    b.load_state(saved)
    b.advance_to(0.04)
    fa, fb = a.frame(), b.frame()
    assert np.array_equal(fa.x, fb.x) and np.array_equal(fa.v, fb.v) and np.array_equal(fa.id, fb.id)


@pytest.mark.xfail(strict=True, reason="a resting column still sinks (odd-even decoupling), see dfsph.py")
def test_hydrostatic_tank_stays_at_rest():
    s = _tank()
    s.advance_to(0.1)
    assert np.linalg.norm(s.v, axis=1).max() < 0.05
    assert np.maximum(s.rho / 1000.0 - 1, 0).mean() < 0.01
