"""The scene's Effects as solver constants in SI units (PHYSICS.md "Effects"), shared by the solvers.

``compile_effects`` turns a pipeline.scene.Effects into an ``EffectConstants``: one field per declared
effect (None when absent), so a solver passes None for an absent effect and numba compiles a kernel
without it (see sph_kernels.forces). Gravity is resolved by driver.prepare (Setup.gravity).

Scene lengths are converted with meters_per_unit: wind velocity (scene units/s), the attractor's point
and softening radius (scene units) and its strength (m/s^2 at one scene unit, so a = strength u^2 / r^2
with u = meters_per_unit metres). Viscosity (Pa s), gamma (N/m), rates (1/s) are SI already."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

WATER_GAMMA = 0.0728  # N/m, the adhesion scale when surface_tension is not declared


def cohesion_coef(h: float) -> float:
    """Akinci et al. 2013 eq. 2: C(r) = 32 / (pi h^9) x {(h-r)^3 r^3 for r > h/2;
    2 (h-r)^3 r^3 - h^6/64 for 0 < r <= h/2}; returns the prefactor."""
    return 32.0 / (math.pi * h ** 9)


def cohesion_np(r, h):
    r = np.asarray(r, float)
    a = (h - r) ** 3 * r ** 3
    c = np.where(r > 0.5 * h, a, 2.0 * a - h ** 6 / 64.0)
    return np.where((r > 0) & (r < h), cohesion_coef(h) * c, 0.0)


def adhesion_np(r, h):
    """Akinci et al. 2013 eq. 7: A(r) = 0.007 / h^3.25 (-4 r^2 / h + 6 r - 2 h)^(1/4) for h/2 < r <= h."""
    r = np.asarray(r, float)
    inner = np.clip(-4.0 * r * r / h + 6.0 * r - 2.0 * h, 0.0, None)
    return np.where((r > 0.5 * h) & (r <= h), 0.007 / h ** 3.25 * inner ** 0.25, 0.0)


# How much stronger Akinci's model (cohesion + curvature term, as sph_kernels.forces weighs them) pulls
# than the Kirkwood-Buff integral of its cohesion alone says: measured, see tension_constant
TENSION_MODEL_FACTOR = 6.0


def cohesion_kirkwood_buff(rho0: float, h: float) -> float:
    """gamma per unit k (kg^2 / (m^4 s^2) ... i.e. N/m per m^4/(kg s^2)) of the cohesion pair force k m_i m_j C(r)
    alone: the Kirkwood-Buff integral of a pair force f(r) over a uniform fluid of number density
    n = rho0 / m gives gamma = (pi n^2 / 8) int r^4 f(r) dr, so gamma / k = (pi rho0^2 / 8) int_0^h r^4 C(r) dr
    (the masses cancel)."""
    r = np.linspace(0.0, h, 20001)
    return math.pi * rho0 * rho0 / 8.0 * np.trapezoid(r ** 4 * cohesion_np(r, h), r)


def tension_constant(gamma: float, rho0: float, h: float) -> float:
    """The model's constant k (m^4 / (kg s^2)) for a surface tension ``gamma`` (N/m).

    Akinci's force has two terms with the one k: cohesion k m_j C(r) and the curvature term
    k m / (100 h^3) (n_i - n_j) (sph_kernels.forces). The cohesion's share has a closed form, the
    Kirkwood-Buff integral (cohesion_kirkwood_buff); the curvature term has none that holds on a particle
    surface (the normals of a surface layer one to two spacings thick), and it is the larger share: on its
    own the cohesion does not even round a stretched drop (it clusters the surface into a stiff shell),
    while the curvature term alone does. Calibrating k by the cohesion alone made the model's surface
    tension ~6 x the declared gamma (the l=2 period of a drop 0.40-0.42 of Rayleigh's, i.e. gamma x 5.6-6.2).

    So k = gamma / (TENSION_MODEL_FACTOR x the cohesion's Kirkwood-Buff gamma per k), the factor measured
    by the model's own l=2 oscillation of a water drop in zero gravity against Rayleigh's
    omega^2 = 8 gamma / (rho R^3) (weakly compressible SPH, support 2 l0; both terms scale as
    k rho0^2 h^2 in the continuum, so the ratio should not depend on the resolution; the measurement is
    tests/test_surface_tension_physics.py's). Measured T / T_Rayleigh with the factor 6 (old: 0.35-0.42):
    a 15 %-stretched ball 0.95 at R / l0 = 6.25 and 0.84 at 9.4; a 2:1 block 1.07 and 0.90 (R = 6.25 mm),
    1.00 at R = 4 mm. Finer particles pull somewhat harder, so this is measured at R / l0 ~ 6-9 only."""
    return gamma / (TENSION_MODEL_FACTOR * cohesion_kirkwood_buff(rho0, h))


def adhesion_table(h: float, samples: int) -> np.ndarray:
    """I(d) = int_wall A(|x - y|) cos(theta) dV_y for a flat wall half-space at distance d, sampled at
    d = k h / (samples - 1): per spherical shell of radius r > d the cap beyond the plane contributes
    pi (r^2 - d^2) dr (int cos dOmega = pi (1 - d^2 / r^2), times r^2), so
    I(d) = pi int_max(d, h/2)^h A(r) (r^2 - d^2) dr (dimensionless)."""
    d = np.linspace(0.0, h, samples)
    out = np.zeros(samples)
    for k, dk in enumerate(d):
        r = np.linspace(max(dk, 0.5 * h), h, 4001)
        out[k] = math.pi * np.trapezoid(adhesion_np(r, h) * (r * r - dk * dk), r)
    return out


def adhesion_accel(beta: float, gamma: float, rho0: float, h: float, samples: int) -> np.ndarray:
    """The wall adhesion's acceleration table (m/s^2 towards the wall at d = k h / (samples - 1)) for a fluid
    of surface tension ``gamma``: a(d) = c I(d) (adhesion_table), c set by Young-Dupre so that the work of
    adhesion, the energy per area to pull the fluid off the wall, rho0 int_0^h a(d) d dd (the fluid
    half-space at height D feels rho0 int_D^h a per area; integrated over D), is beta times the work of
    cohesion 2 gamma: beta = 1 is "as strong as the fluid's own cohesion" (complete wetting, cos theta =
    2 beta - 1 for beta <= 1). (Before, c was the cohesion's constant k, whose work of adhesion was
    0.107 x 2 gamma of the cohesion alone, and a sixth of the model's tension: see tension_constant.)"""
    table = adhesion_table(h, samples)
    d = np.linspace(0.0, h, samples)
    return beta * 2.0 * gamma / (rho0 * np.trapezoid(table * d, d)) * table


@dataclass
class EffectConstants:
    """Declared effects in SI (None = absent). dt_limit: the tightest step an effect needs (s)."""
    mu: float | None = None  # Pa s
    wall_viscosity: bool = False
    tension_k: float | None = None  # m^4 / (kg s^2), see tension_constant
    adhesion_accel: np.ndarray | None = None  # m/s^2 towards the wall at distance k dr, k = 0..samples-1
    friction_rate: float | None = None  # 1/s
    wind_velocity: np.ndarray | None = None  # m/s
    wind_drag: float | None = None  # 1/s
    attractor_point: np.ndarray | None = None  # m
    attractor_k: float | None = None  # m^3/s^2: a = k / r^2
    attractor_soft: float | None = None  # m
    dt_limit: float = math.inf
    dt_limit_by: str = ""  # the effect setting that sets dt_limit, as the config names it (for errors)

    def limit(self, dt: float, by: str) -> None:
        if dt < self.dt_limit:
            self.dt_limit, self.dt_limit_by = dt, by


def compile_effects(effects, *, meters_per_unit: float, rho0: float, l0: float, h: float,
                    table_samples: int = 256) -> EffectConstants:
    """SI constants of ``effects`` (a pipeline.scene.Effects) for a fluid of rest density rho0 (kg/m^3),
    spacing l0 and support h (m)."""
    mpu = float(meters_per_unit)
    out = EffectConstants()
    if effects.viscosity is not None:
        out.mu = float(effects.viscosity.mu)
        out.wall_viscosity = bool(effects.viscosity.wall)
    gamma = None
    if effects.surface_tension is not None:
        gamma = float(effects.surface_tension.gamma)
        out.tension_k = tension_constant(gamma, rho0, h)
        if gamma > 0:  # capillary wave limit (Brackbill et al. 1992): dt <= sqrt(rho l0^3 / (2 pi gamma))
            out.limit(math.sqrt(rho0 * l0 ** 3 / (2.0 * math.pi * gamma)), f"effects.surface_tension.gamma ({gamma:g} N/m)")
    if effects.wall_adhesion is not None:
        out.adhesion_accel = adhesion_accel(float(effects.wall_adhesion.beta), gamma if gamma is not None else WATER_GAMMA,
                                            rho0, h, table_samples)
    if effects.wall_friction is not None:
        out.friction_rate = float(effects.wall_friction.rate)
        if out.friction_rate > 0:  # explicit decay stays monotone for rate dt <= 1
            out.limit(0.5 / out.friction_rate, f"effects.wall_friction.rate ({out.friction_rate:g} 1/s)")
    if effects.wind is not None:
        out.wind_velocity = np.asarray(effects.wind.velocity, np.float64) * mpu
        out.wind_drag = float(effects.wind.drag)
        if out.wind_drag > 0:
            out.limit(0.5 / out.wind_drag, f"effects.wind.drag ({out.wind_drag:g} 1/s)")
    if effects.attractor is not None:
        a = effects.attractor
        out.attractor_point = np.asarray(a.point, np.float64) * mpu
        out.attractor_k = float(a.strength) * mpu * mpu
        out.attractor_soft = float(a.softening) * mpu if a.softening is not None else 2.0 * l0
    return out
