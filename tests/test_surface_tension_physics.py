"""Surface tension against physics: a water drop's l=2 oscillation against Rayleigh, and the wall
adhesion's work against the fluid's own (Young-Dupre).

Surface tension used to be ~6 x the declared gamma (the period 0.42 of Rayleigh's): its constant was
calibrated by the cohesion term alone, while Akinci's curvature term, with the same constant, does most
of the pulling (effects.tension_constant)."""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import curve_fit

from pipeline.scene import Effects
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.driver import capillary_speed
from stages.simulate.effects import adhesion_accel, cohesion_kirkwood_buff, tension_constant
from stages.simulate.emitters import lattice
from stages.simulate.sph import SPHParams, SPHSolver

GAMMA = 0.0728  # N/m, water
RHO = 1000.0  # kg/m^3


def _l2_period(l0: float, n: int, t_end: float, samples: int = 300, jitter_seed: int | None = None) -> tuple[float, float]:
    """A ball of water of the volume of 2 n^3 particles (R = 6.25 l0 for n = 8) in zero gravity, stretched
    15 % (the linear regime: a 2:1 block's first swing is slower, its later ones match), default
    parameters (Monaghan alpha 0.05, no physical viscosity): the period of its l=2 oscillation (a damped
    cosine fitted to <x^2> - (<y^2> + <z^2>) / 2 from its first minimum) and Rayleigh's,
    omega^2 = 8 gamma / (rho R^3). ``jitter_seed``: the particles start up to 1e-4 l0 off the lattice
    (one member of an ensemble)."""
    R = l0 * (3 * 2 * n ** 3 / (4 * math.pi)) ** (1 / 3)
    box = 2 * R + 40 * l0
    g = lattice(np.full(3, box / 2 - R - 2 * l0), np.full(3, box / 2 + R + 2 * l0), l0)
    c = g[np.argmin(np.linalg.norm(g - box / 2, axis=1))]
    x = g[np.linalg.norm(g - c, axis=1) < R]  # a lattice ball, stretched by 15 % along x at constant volume
    x = c + (x - c) * np.array([1.15, 1.15 ** -0.5, 1.15 ** -0.5])
    if jitter_seed is not None:
        x = x + np.random.default_rng(jitter_seed).uniform(-1e-4, 1e-4, x.shape) * l0
    lo, hi = np.zeros(3), np.full(3, box)
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0)
    eff = Effects(surface_tension={"gamma": GAMMA})
    p = SPHParams()
    from stages.simulate.effects import compile_effects

    consts = compile_effects(eff, meters_per_unit=1.0, rho0=RHO, l0=l0, h=p.support * l0)
    v_ref = capillary_speed(eff, RHO, l0) + math.sqrt(9.81 * l0)  # as driver.prepare's bound for this scene
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=RHO,
                  params=SPHParams(sound_speed=10 * v_ref), v_ref=v_ref, effects=consts)
    t = np.arange(1, samples + 1) * t_end / samples
    q = np.empty(samples)
    for k, tk in enumerate(t):
        s.advance_to(tk)
        d = s.x - s.x.mean(axis=0)
        q[k] = (d[:, 0] ** 2).mean() - 0.5 * ((d[:, 1] ** 2).mean() + (d[:, 2] ** 2).mean())
    assert np.isfinite(q).all()
    t_ray = 2 * math.pi * math.sqrt(RHO * R ** 3 / (8 * GAMMA))
    first = int(np.argmin(q[: samples // 2]))  # the first minimum: the drop flattened the other way
    f = lambda tt, b, a, tau, w, ph: b + a * np.exp(-(tt - t[first]) / tau) * np.cos(w * (tt - t[first]) + ph)
    best = None
    for guess in (0.5, 1.0, 2.0):  # periods relative to twice the first half period
        try:
            pp, _ = curve_fit(f, t[first:], q[first:], maxfev=20000,
                              p0=[q[first:].mean(), q[first] - q[first:].mean(), t_end, math.pi / (guess * t[first]), 0.0])
        except RuntimeError:
            continue
        res = float(((f(t[first:], *pp) - q[first:]) ** 2).mean())
        if best is None or res < best[0]:
            best = (res, pp)
    return 2 * math.pi / abs(best[1][3]), t_ray


def test_a_water_drop_oscillates_at_rayleighs_period():
    """The tester's drop: the volume of 16 x 8 x 8 mm of water at 1 mm spacing (R = 6.25 mm = 6.25 l0),
    Rayleigh's period 0.129 s, on the mean of three starts 1e-4 l0 off the lattice: 0.125 / 0.121 / 0.122 s
    (0.95 of Rayleigh's; README "surface_tension"); the old calibration gave 0.05 s. The exact lattice ball is
    a symmetric start whose outcome rounding decides: it gave 0.122 s in earlier sessions and 0.107 s (0.83,
    the suite's one failure) on session 28's machine with the same code, so one run of it is not a measurement."""
    runs = np.array([_l2_period(0.001, 8, 0.4, jitter_seed=seed) for seed in range(3)])
    period, rayleigh = runs.mean(axis=0)
    assert abs(period / rayleigh - 1) < 0.15, runs


def test_tension_constant_counts_both_terms():
    """k is gamma over the model's pull per k: the cohesion's Kirkwood-Buff integral times the measured
    share of the curvature term (a factor, not the cohesion alone)."""
    h = 0.002
    k = tension_constant(GAMMA, RHO, h)
    assert 5.0 < GAMMA / (k * cohesion_kirkwood_buff(RHO, h)) < 7.0


def test_adhesion_beta_one_is_the_fluids_own_cohesion():
    """beta = 1, "as strong as the fluid's own cohesion": the work of adhesion (energy per area to pull the
    fluid half-space off the wall, rho0 int a(d) d dd) equals the work of cohesion 2 gamma, complete
    wetting by Young-Dupre (cos theta = W_a / gamma - 1); beta = 0.5 is a 90 degree contact angle. It is
    linear in beta and follows the declared gamma, at any resolution."""
    for h, gamma, beta in ((0.002, GAMMA, 1.0), (0.0005, GAMMA, 0.5), (0.04, 0.485, 1.0)):
        samples = 256
        a = adhesion_accel(beta, gamma, RHO, h, samples)
        d = np.linspace(0.0, h, samples)
        work = RHO * np.trapezoid(a * d, d)
        assert math.isclose(work, 2 * beta * gamma, rel_tol=1e-9), (h, gamma, beta, work)
        assert (a >= 0).all() and a[-1] == 0.0  # towards the wall, none beyond h
