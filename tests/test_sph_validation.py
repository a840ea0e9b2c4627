"""Physics validation at CI size: the hydrostatic tank (PHYSICS.md: p = rho g (H - z))."""
import numba as nb
import numpy as np
import pytest

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.driver import hydrostatic_start
from stages.simulate.emitters import lattice
from stages.simulate.sph import SPHParams, SPHSolver

L0, W, H, G = 0.01, 0.1, 0.2, 9.81  # 10 x 10 x 20 particles


def _settled_column(**params):
    """The column settled for 0.8 s, then each particle's pressure averaged over the last 0.2 s."""
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, 0.3]), [0, 0, 0], [W, W, 0.3], L0 / 2)
    x = lattice([0, 0, 0], [W, W, H], L0)
    # water's viscosity (issue 17: mu = 5 Pa s, 5,000 x water's, hid that the tank does not come to rest);
    # started from the hydrostatic state as a pipeline run starts it
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0,
                  params=SPHParams(threads=None, **params), gravity=(0, 0, -G), mu=0.001, v_ref=float(np.sqrt(2 * G * H)))
    hydrostatic_start(s)
    s.advance_to(0.8)
    p_by_id = np.zeros(len(x))
    for k in range(1, 11):  # WCSPH pressure is noisy: average each particle over the last 0.2 s
        s.advance_to(0.8 + 0.02 * k)
        f = s.frame()
        p_by_id[f.id] += f.p / 10
    f.p[:] = p_by_id[f.id]
    return f


def _error(f, depth_lo, depth_hi):
    """Mean pressure against rho g (H - z) over the layers depth_lo < (H - z) / l0 <= depth_hi, columns at
    least 2 l0 from the side walls (the layer counts its particle of depth depth_hi at H - (depth_hi - 0.5) l0)."""
    z = f.x[:, 2]
    depth = (H - z) / L0 + 0.5
    sel = (depth > depth_lo + 0.5) & (depth <= depth_hi + 0.5)
    sel &= np.minimum(f.x[:, :2], W - f.x[:, :2]).min(axis=1) > 2 * L0
    return f.p[sel].mean() / (1000.0 * G * (H - z[sel])).mean() - 1


def _at_rest(f):
    # at rest: sqrt(2 g H) = 2 m/s would be the speed of a free fall from the top
    speed = np.linalg.norm(f.v, axis=1)
    assert np.percentile(speed, 99) < 0.05 and speed.max() < 0.2, (np.percentile(speed, 99), speed.max())


def _dense(f, worst: float = 0.03):
    z = f.x[:, 2]
    assert z.min() > 0.0  # no particle below the floor
    deep = z < H - 3 * L0  # away from the top layers, which lack neighbours
    err = np.abs(f.rho / 1000.0 - 1)
    assert err[deep].mean() < 0.01
    # the worst particles sit in the tank's vertical edges and corners; away from them every one is in
    off_edges = deep & (np.sort(np.minimum(f.x[:, :2], W - f.x[:, :2]), axis=1)[:, 1] > 2 * L0)
    # (a few particles disordered by the start-up sloshing sit above 1 %: with the default artificial
    # viscosity the worst single one measured 2.7 %)
    assert np.percentile(err[off_edges], 99) < 0.01, np.percentile(err[off_edges], 99)
    assert err[off_edges].max() < worst, err[off_edges].max()


@pytest.mark.parametrize("kernel", ["spline", "poly6_spiky"])
def test_hydrostatic_tank_settles_to_rho_g_h(kernel):
    """No gradient correction: the single layer at depth 10 and the bottom three layers (18-20) within 15 % of
    rho g h. The floor row alone is not asserted: with every kernel it rests on the eq. 16 clamp (z = 0.500 l0,
    measured; at r_rep = 0.3 l0 it sinks to 0.300), since the conservative wall force -(p_i / rho_i^2) grad Z
    counts the particle's pressure once and cannot hold the column above it; its pressure is then the contact's
    (+25 % spline, +10 % Poly6 / Spiky in one session; +17 % and +0.8 % in another). Measured: depth 10 -1.4 %
    and 18-20 +8.6 % (spline), +6.6 % and +6.7 % (Poly6 / Spiky; +13 % at depth 10 in another run: the settled
    packing's gradient is ~3 % weak and the side walls give no share of the vertical gradient, see the
    gradient-correction test below); the column still churns (issue 17), which adds noise to one layer."""
    f = _settled_column(kernel=kernel)
    _dense(f)
    errors = {"10": _error(f, 9, 10), "18-20": _error(f, 17, 20)}
    print('hydrostatic relative error by depth (particles):', errors)
    assert max(abs(e) for e in errors.values()) < 0.15, errors


def _sampled_errors(params, t0: float = 0.8, t1: float = 1.0, samples: int = 10):
    """The last frame of a column settled to ``t0``, and each layer band's pressure error against rho g h at
    the particles' own depths, averaged over ``samples`` instants to ``t1`` (averaging each particle's pressure
    and comparing it at its last position mixed depths: the 9-11 band read +4.9 % on an AVX-512 machine where
    the instants' own errors average +2.2 %, and +0.2 % over 0.8-1.4 s). Two threads, fixed: with the
    process's thread count (which other tests in a pytest worker change) the worst particle's density error
    at 1 s came out 2.7 % in one run and 3.1 % in another."""
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, 0.3]), [0, 0, 0], [W, W, 0.3], L0 / 2)
    x = lattice([0, 0, 0], [W, W, H], L0)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0,
                  params=SPHParams(threads=None, **params), gravity=(0, 0, -G), mu=0.001, v_ref=float(np.sqrt(2 * G * H)))
    before = nb.get_num_threads()
    nb.set_num_threads(min(2, nb.config.NUMBA_NUM_THREADS))
    try:
        hydrostatic_start(s)
        s.advance_to(t0)
        bands = {"9-11": (8, 11), "18-20": (17, 20), 10: (9, 10), 20: (19, 20)}
        sums = dict.fromkeys(bands, 0.0)
        for k in range(1, samples + 1):
            s.advance_to(t0 + (t1 - t0) * k / samples)
            f = s.frame()
            for name, (lo, hi) in bands.items():
                sums[name] += _error(f, lo, hi) / samples
    finally:
        nb.set_num_threads(before)
    return f, sums


@pytest.mark.parametrize("params", [dict(gradient_correction=True, wall_gradient=True)])
def test_hydrostatic_tank_with_gradient_correction_within_3_percent(params):
    """Symmetric kernel-gradient correction + the walls' share of the hydrostatic gradient: the pressure
    over three layers around depth 10 and over the bottom three (18-20) within 3 % of rho g h, averaged over
    0.8-1.4 s (measured -0.6 % and +0.3 %; before the walls' contact velocity +0.2 % and -0.3 %; single layers
    carry a ~5 % sampling error, ~36 particles with a 30-50 % spatial spread). Over 0.8-1.0 s alone the first
    band read +2.2 % before and +3.3 / +3.5 % in two runs after: the mirrored wall this option uses lets the
    column circulate (the xfail below), and a fifth of a second samples its swing."""
    f, errors = _sampled_errors(params, 0.8, 1.4, 30)
    # the mirrored wall pressure this option is fitted to lets the column circulate (the xfail below), so
    # its single worst particle is a chaotic quantity: 2.7 % here, 3.1 % on CI's machine at the same
    # commit, two threads both; the 99th percentile (0.86 % there) carries the claim
    _dense(f, worst=0.04)
    bands = {k: errors[k] for k in ("9-11", "18-20")}
    singles = {k: errors[k] for k in (10, 20)}
    print('corrected hydrostatic error, 3-layer bands:', bands, 'single layers:', singles)
    assert max(abs(e) for e in bands.values()) < 0.03, bands
    assert max(abs(e) for e in singles.values()) < 0.08, singles


def test_hydrostatic_tank_comes_to_rest_with_water_viscosity():
    """The default (conservative) wall pressure: the column comes to rest with water's viscosity."""
    _at_rest(_settled_column())


@pytest.mark.xfail(strict=True, reason="issue 17, open: the mirrored wall pressure (which the gradient-corrected "
                   "hydrostatic option is fitted to) is not conservative: the column circulates (99th percentile "
                   "0.13-0.27 m/s after 1 s)")
def test_gradient_corrected_tank_comes_to_rest_with_water_viscosity():
    _at_rest(_settled_column(gradient_correction=True, wall_gradient=True))  # mirrored walls (auto)


def _tank_energy_trace(**params):
    """Total energy (kinetic + gravitational + the compression energy of the linear EOS, clamped at
    rho0 like the pressure) of a resting tank sampled every 0.05 s over 0.5 s, relative to the start;
    and the energy scale M g l0."""
    w, h, l0 = 0.15, 0.2, 0.0125
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [w, 0.1, 0.3]), [0, 0, 0], [w, 0.1, 0.3], l0 / 2)
    x = lattice([0, 0, 0], [w, 0.1, h], l0)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                  params=SPHParams(threads=None, **params), gravity=(0, 0, -G), mu=0.001,
                  v_ref=float(np.sqrt(2 * G * h)))
    hydrostatic_start(s)

    def energy():
        s.sort_and_density(rebuild=True)
        r = s.rho / 1000.0
        e = np.where(r > 1.0, s.c ** 2 * (np.log(np.maximum(r, 1.0)) + 1.0 / r - 1.0), 0.0)  # int p / rho^2 drho
        return s.mass * (0.5 * (s.v ** 2).sum() + G * s.x[:, 2].sum() + e.sum())

    e0 = energy()
    trace = []
    for k in range(1, 11):
        s.advance_to(0.05 * k)
        trace.append(energy() - e0)
    return np.array(trace), s.mass * len(x) * G * l0


@pytest.mark.parametrize("params", [
    dict(),
    dict(kernel="spline"),
    pytest.param(dict(wall_pressure="mirrored"), marks=pytest.mark.xfail(
        strict=True, reason="issue 17: the mirrored wall pressure does work around closed loops (+0.1 M g l0 in the "
                            "first 0.05 s), which is why the column circulated")),
])
def test_resting_tank_energy_never_grows(params):
    """Water's viscosity and the artificial viscosity only dissipate, and the pressure forces (the walls'
    included) are the derivative of the compression energy: the total energy may only fall. Measured with
    the default: falls monotonically by 0.09 M g l0 over 0.5 s; the mirrored wall gains 0.11 M g l0."""
    trace, scale = _tank_energy_trace(**params)
    print("energy - start, in M g l0:", np.round(trace / scale, 4))
    assert trace.max() < 1e-3 * scale, trace / scale
    assert np.all(np.diff(trace) < 1e-3 * scale), trace / scale


@pytest.mark.parametrize("kernel, worst", [("spline", 1e-4), ("poly6_spiky", None)])
def test_pressure_force_is_the_derivative_of_the_compression_energy(kernel, worst):
    """The pressure acceleration on a disordered block (walls out of reach, no viscosity) against
    -(1/m) dE/dx_k of E = sum_i m e(rho_i), e = int p / rho^2 drho, by central differences: with the
    spline (one kernel for the density and its gradient) they agree to the pair form's second-order
    term ((p_i + p_j) / (rho_i rho_j) for p_i / rho_i^2 + p_j / rho_j^2), so fluid at rest can settle;
    Poly6 density with the Spiky gradient (Mueller et al. 2003) is off by tens of percent per particle:
    its force has a curl, which keeps a resting tank moving (issue 17)."""
    l0, c = 0.01, 20.0
    box = [-0.1, -0.1, -0.1], [0.16, 0.16, 0.16]
    sdf = grid_from_function(box_interior_sdf(*box), *box, l0 / 2)
    rng = np.random.default_rng(3)
    x = lattice([0, 0, 0], [0.06, 0.06, 0.06], l0) + rng.uniform(-0.08, 0.08, (216, 3)) * l0
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                  params=SPHParams(kernel=kernel, sound_speed=c, clamp_pressure=False, artificial_viscosity=0.0),
                  gravity=(0, 0, 0))

    def energy(y):
        s.x[:] = y
        s.id[:] = np.arange(len(y))
        s.sort_and_density(rebuild=True)
        r = s.rho / 1000.0
        return s.mass * (c ** 2 * (np.log(r) + 1.0 / r - 1.0)).sum()

    energy(x)
    s.forces()
    acc = np.zeros_like(x)
    acc[s.id] = s.acc
    inner = np.flatnonzero(np.all((x > 0.015) & (x < 0.045), axis=1))  # full neighbourhoods
    errors = []
    for k in inner[:12]:
        grad = np.zeros(3)
        for a in range(3):
            e = 1e-7
            xp, xm = x.copy(), x.copy()
            xp[k, a] += e
            xm[k, a] -= e
            grad[a] = (energy(xp) - energy(xm)) / (2 * e)
        expected = -grad / s.mass
        errors.append(np.linalg.norm(acc[k] - expected) / np.linalg.norm(expected))
    print(kernel, "relative error of the pressure force against -dE/dx:", np.round(errors, 4))
    if worst is not None:
        assert max(errors) < worst, errors
    else:
        assert max(errors) > 0.1, errors  # the defect the spline removes, kept visible


@pytest.mark.parametrize("kernel, tank", [
    ("spline", (0.15, 0.1, 0.2)), ("spline", (0.3, 0.2, 0.25)),
    pytest.param("poly6_spiky", (0.15, 0.1, 0.2), marks=pytest.mark.xfail(
        strict=True, reason="issue 17: Poly6 density with the Spiky gradient keeps the tank at 0.017 m/s over 1-1.5 s"))],
    ids=["spline", "spline, issue 17's tank", "poly6_spiky"])
def test_resting_tank_with_water_viscosity_is_calm(kernel, tank):
    """Issue 17's goal with water's viscosity and the pipeline's hydrostatic start, no settling: the mean
    speed, sampled every 0.05 s, below 0.005 m/s averaged over 1-1.5 s, and decaying half second by half
    second. The issue's tank (0.3 x 0.2 m filled 0.25 m deep, 7,680 particles) and the energy test's (0.15 x
    0.1 m filled 0.2 m deep, 1,536). Measured (averages over 0-0.5 / 0.5-1 / 1-1.5 s): 0.0231 / 0.0075 /
    0.0039 and 0.0237 / 0.0081 / 0.0039 m/s; before the walls' contact velocity (walls.maps.contact_velocity)
    the issue's tank averaged 0.0070 over 1-1.5 s (bench_rest.py)."""
    w, d, h = tank
    l0 = 0.0125
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [w, d, h + 0.1]), [0, 0, 0], [w, d, h + 0.1], l0 / 2)
    x = lattice([0, 0, 0], [w, d, h], l0)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                  params=SPHParams(threads=None, kernel=kernel), gravity=(0, 0, -G), mu=0.001,
                  v_ref=float(np.sqrt(2 * G * h)))
    hydrostatic_start(s)
    means = []
    for k in range(1, 31):
        s.advance_to(0.05 * k)
        means.append(float(np.linalg.norm(s.v, axis=1).mean()))
    halves = np.array(means).reshape(3, 10).mean(axis=1)
    print(kernel, len(x), "mean speed averaged over 0-0.5, 0.5-1, 1-1.5 s:", np.round(halves, 4))
    assert halves[2] < 0.005, halves
    assert halves[2] < halves[1] < halves[0], halves


def test_a_block_released_in_mid_air_falls_without_swelling():
    """Water released in mid-air is in free fall: no pressure, so it keeps its volume while it falls.
    The hydrostatic start used to compress every column towards its lowest particle, floor or not; with
    negative pressure clamped nothing pulled the block back and it swelled 44 % in 0.3 s (a user's sweep).
    The same block standing on the floor is still compressed, and a block resting on another across a gap
    is compressed only in the lower block."""
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.3, 0.3, 1.0]), [0, 0, 0], [0.3, 0.3, 1.0], L0 / 2)
    lo, hi = np.array([0.1, 0.1, 0.6]), np.array([0.2, 0.2, 0.7])
    x = lattice(lo, hi, L0)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0, params=SPHParams(),
                  gravity=(0, 0, -G), mu=0.001, v_ref=float(np.sqrt(2 * G)))
    hydrostatic_start(s)
    assert np.array_equal(s.x[np.argsort(s.id)], x.astype(s.x.dtype))  # nothing holds it up: left as emitted
    s.advance_to(0.3)
    extent = s.x.max(axis=0) - s.x.min(axis=0)
    assert np.all(np.abs(extent - (x.max(axis=0) - x.min(axis=0))) < 0.25 * L0), extent
    assert abs(s.x[:, 2].mean() - (x[:, 2].mean() - 0.5 * G * 0.3 ** 2)) < 0.1 * L0

    floor = lattice([0.1, 0.1, 0.0], [0.2, 0.2, 0.1], L0)
    both = np.concatenate([floor, x])
    s = SPHSolver(both, np.zeros_like(both), np.arange(len(both)), sdf, spacing=L0, rho0=1000.0, params=SPHParams(),
                  gravity=(0, 0, -G), mu=0.001, v_ref=float(np.sqrt(2 * G)))
    hydrostatic_start(s)
    moved = np.abs(s.x[np.argsort(s.id)] - both).max(axis=1) > 0
    assert moved[:len(floor)].sum() > 0.8 * len(floor) and not moved[len(floor):].any()
