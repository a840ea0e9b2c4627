"""simulate.dfsph: Divergence-Free SPH (Bender and Koschier 2015, 2017) with the distance-function
walls of the seed method (PHYSICS.md eq. 11-16) used like a boundary density map.

Weakly compressible SPH (simulate.sph) needs a time step below the speed of sound; DFSPH solves for
the pressure instead, so its step is bound by the CFL condition only. One step (Bender and Koschier
2017, Alg. 1), from a state whose density, factors and neighbour lists are current:
  1. non-pressure accelerations (gravity, viscosity, effects: sph_kernels.forces with pressure=None);
  2. dt = cfl l0 / v_max (capped by the frame interval, dt_max, viscous/force limits, effects);
  3. v* = v + dt a; constant-density solve on v* (predicted density back to rho0);
  4. x += dt v*; the eq. 16 position clamp as a safety net;
  5. sort, density, factors, neighbour lists at the new positions; divergence-free solve on v.
The stage shares the scene set-up and frame loop with the other solvers (driver.py).

Walls: walls.maps.BrickWallMaps (the 3D wall map, bricked; no dense map over the SDF box). Density: Z_rho
from its channel 0. Wall gradient Psi (the Spiky default): from the map's wall direction channels, the
same Spiky sums as the fluid's gradient, so on the rest lattice S_i + Psi_i = 0 within 1 % at a floor
and in a corner and 4 % in an edge (grad Z_rho, the Poly6 slope, was 11-13 % short there).

Status: the dam break runs (surge front 8-12 % ahead of Martin & Moyce at CI size, like sph) at a
mean density error of 0.1-0.2 %. A resting tank is NOT at rest yet (tests/test_dfsph.py keeps the
hydrostatic test as a strict xfail: 10 x 10 x 20 tank, l0 = 1 cm, mean speed 0.1-0.3 m/s, max 0.3-1
m/s, for 0.6 s and more; SPlisHSPlasH's DFSPH on bench_rest's tank at water's viscosity moves as much, 0.20 m/s
at 1.5 s against our 0.21). What was measured:
- not the cause alone: dt (0.001-0.005 s), relaxation, warm start, r_rep, iteration bound, the Poly6
  gradient, relaxing the lattice first, and ONE kernel for density and gradient (gradient="spline",
  the cubic spline with walls as the quadrature of the same kernel, walls/spline.py: the solve's rate is
  then the density's derivative, tested; the tank boils just the same, and the CI dam break front runs
  11-16 % ahead at 4.7 density iterations a step instead of 6-10 % at 2.2, so it stays opt-in);
- the floor: with S_i + Psi_i = 0 and the wall counting kappa_i once (WALL_MIRROR = 1, the symmetric
  form whose solve is J M^-1 J^T), a floor particle's own kappa puts no net force on it (the wall's
  kappa_i Psi_i cancels the kappa_i half of its pairs) and the layer above pushes it down: even a solve
  converged to 1e-5 leaves the column falling at g dt in the first step and the bottom layer ends on the
  eq. 16 clamp (0.2 l0), its kappa swinging 6x to 0.2x the hydrostatic value (a bouncing column). A
  mirrored wall pressure (WALL_MIRROR = 2, the momentum balance of p_wall = p_i) makes the solve
  non-symmetric; it bounced as much (both kernels). SPlisHSPlasH's volume maps (as we read them) put the
  wall's volume at the nearest surface point, so |Psi| > |S| there and a kappa_i-once wall can hold a column;
- edges and corners: the flat-wall factors of the wall map over-count the rest density there by 1.1
  / 1.6 % (Poly6) and 1.4 / 2.3 % (spline), and S + Psi misses by 0.8 % (edge) and 4 % (corner): at
  the bottom corners that is kappa |S + Psi| ~ 0.3 g of spurious force; the fastest particles sit in
  the vertical edges and corners. Without gravity the tank keeps a bounded 0.02-0.05 m/s;
- the solve's error counted compression only, so a warm-started pressure that now expands the fluid was
  never undone; counting |e| where kappa > 0 (the complementarity residual; since session 39 each solve
  counts the expansion at a fifth, dfsph_kernels.EXPANSION_WEIGHT, which stops the energy made in narrow
  passages) lowered the mean speed (0.13-0.2 -> 0.11-0.14 m/s), not enough (bench_rest's tank in session
  39: 0.17 m/s at 1.5 s, as before).
  A wall density Z phi(d) (spline, phi the flat-wall Z over its rest value: the slope doubled at the
  rest distance, Psi its exact gradient) kept the bottom layer off the clamp (>= 0.4 l0) but the column
  bounced as before, also with both solves converged to 1e-5: the fastest particles then sat in the
  bottom edges and corners.
- session 32 (bench_rest's tank, throw-away harnesses): per step, the density solve ADDS kinetic energy
  and the divergence solve takes it away (over the first second +2.8 J and -2.6 J; the tank holds 0.2 J),
  spread over the whole depth. The density solve's kappa is about 0 above the bottom layers, where the
  divergence solve's kappa_v carries the hydrostatic pressure (0.9-1.2 g depth): v* keeps g dt through
  the position update, the fluid sinks g dt^2 a step and the next step's error term pushes it back up.
  The fluid also circulates: with WALL_MIRROR = 1 the band by the side walls sinks (10 mm at 1 s) and the
  interior rises. The hydrostatic state (kappa = g depth) on the rest lattice is far from a balance with
  WALL_MIRROR = 1 (first row at a side wall -5.2 g into it, floor row -10 g); WALL_MIRROR = 2 with the
  walls' share of the hydrostatic gradient (-T_wall g, Adami et al. 2012: kernels.wall_gradient_tables)
  balances it at flat walls (within 0.007 g) and leaves 0.14-0.66 g in edges. Not the cause, measured
  (mean speed, m/s, at 1 s unless said): Psi the exact gradient of Z (spline, central differences) 0.19 at
  1.5 s; both solves to 1e-5 0.165; the error term's share beta x 0.2 0.086 (the divergence solve then
  adds energy); no warm start 0.13 (0.066 with beta x 0.2); the density solve warm-started with kappa +
  kappa_v and the divergence solve from zero 0.33 (0.35 with mirror 2 and -T_wall g); mirror 2 0.26, with
  -T_wall g 0.18 (0.087 at 0.4 s); mirror 1 with -T_wall g 0.21, the circulation reversed (sides up 41 mm);
  and the start made an exact balance (mirror 2, -T_wall g, the lattice's residual subtracted as a fixed
  field) 0.06 at 0.1 s growing to 0.17. So the wall terms are not the whole cause: the split pressure
  (kappa, kappa_v) lets the two solves trade energy every step.
- session 33 (the same tank; mean speed at 1 s unless said). Started with kappa = g depth: with WALL_MIRROR = 1
  the first density solve holds the bulk (vz -0.0001 m/s) but the floor row falls at 0.31 m/s in that step (its
  own kappa cancels on it); with mirror 2 and -T_wall g the first step is calm (0.004 m/s), then the bulk
  compresses within the solve's average tolerance (0.1-0.16 %), kappa rises to 1.13 g depth and the column
  bounces: it lifts 10-12 mm at 0.14-0.18 s with its density 5-7 % low (kappa >= 0 cannot hold it together once it
  moves apart) and falls back, 0.2 m/s at 1 s. Not the cause: both solves to 1e-5 (0.20), the complementarity
  residual as the error (|e| where kappa > 0: 0.2), the spline (0.20), SPlisHSPlasH's warm start (0.5 x, only
  where the flow compresses; the density solve then hits its 100-iteration cap every step: 0.14 with mirror 1,
  0.23 with 2); a 1 ms step is worse (0.28, the surface 10 cm up: the tolerances bound dt D rho / Dt, so a shorter
  step allows a larger velocity error). The error term kept out of the velocity (a velocity projection of v*,
  beta = 0, then a second solve whose displacement alone fixes the density error) held the surface within 3 mm
  and gave 0.06 m/s at 1.5 s with mirror 2, -T_wall g and kappa = g depth, but ran away (0.3-1.2 m/s) without
  any one of the three and with 20 % of the correction fed back to the velocity (0.10-0.13): a velocity solve
  that no position error corrects must be exact, and an average-error Jacobi solve is not. Not kept. Both solves
  also held to a largest error within 5 x their tolerance: 0.2 m/s (mirror 1 and mirror 2 alike). Bilateral solves
  in the full bulk (kappa may go negative where rho >= 0.97 rho0, the error |e|): 0.22-0.26. Viscosity 50 x water's:
  0.14; none: 0.15. No divergence solve: 0.33, the fluid up to the tank's lid: the density solve is the source
  (each step removes the last step's compression by expansion under the hydrostatic pressure, p dV of work kept as
  kinetic energy: 0.1 % of the tank's volume a step at 1.2 kPa and 200 steps a second is 3.6 J/s, against the 2.8
  J/s measured in session 32).
  The split with a largest error within 3 x the tolerance still ran away (0.27-0.37 m/s at 1 s from kappa = 0, 57
  iterations a step, often at the cap of 100). An exact projection (Chorin: v = P(v*) by preconditioned CG to
  1e-6, about 90 iterations a step, kappa = 0 where rho < 0.97 rho0, no divergence solve; the walls' share counted
  twice in both the force and the rate so the system stays symmetric, with -T_wall g and the lattice's residual
  subtracted: an exact start) was calm at 0.1 s (0.003 m/s) and at 0.06 by 0.3-0.5 s, the surface sinking 4 mm:
  a discretely divergence-free velocity still changes the density (the rate is Spiky's and the wall's doubled,
  the density Poly6's and Z's; with the spline 0.06 as well), so volume is lost and its potential energy feeds the
  motion; adding the drift's displacement ran away (0.18 at 0.2 s); with the wall counted once (symmetric) the
  floor cannot be held: 0.12-0.2 m/s with the surface 5.6 cm down by 0.5 s (0.3 with the drift's displacement).
  With the rate the density's own (the spline, the wall once in the rate and twice in the force, so not symmetric:
  BiCGSTAB, about 70 iterations a step) from an exact start: 0.008 m/s at 0.1 s, 0.06 at 0.2 s. The exact
  projection with the drift's displacement, from an exact start: 0.08 at 0.1 s, 0.4 by 0.3 s.
- session 35: one step linearised about a small resting tank (benchmarks/bench_rest_modes.py, both solves a fixed 50
  Jacobi iterations): 95 non-oscillating modes grow faster than 0.5 sqrt(g / l0), the fastest at 37 / s (1.32 sqrt(g
  / l0)) in the bottom layers by the side walls; but WCSPH, calm, amplifies 40 at up to 21 / s, so the linear growth
  about the lattice does not explain the churn. The step's forces are far from conservative in the interior (|K -
  K^T| / |K + K^T| of K = d v_new / d x: 0.31, WCSPH 0.007; 0.084 with gradient="spline", which session 33 measured
  at 0.20 m/s at 1 s). Restarted at rest after 3 s of bench_rest's tank (every velocity zeroed), DFSPH is back at
  0.26 m/s within 0.1 s: the step keeps the motion up at the states it reaches.
- session 42: both solves really converged (1e-5, 90-130 iterations a step; earlier "to 1e-5" runs stopped at
  the cap of 100): 0.12 m/s at 1.5 s against 0.17; after the first step the even layers fall at 0.7-0.85 g dt
  and the odd ones are held (session 13's decoupling: a converged solve keeps it).
Next: the energy each step's density solve adds at a churned state (session 32's budget, taken at t = 3 s), term by
term; the tank of the test is the check. (One pressure field for both solves, named here until session 46, is in
effect measured: the two solves cannot share kappa, since the divergence solve would apply the hydrostatic pressure
again with no gravity to hold; one field means one solve a step on v*, warm started with the last pressure, which
is the run without the divergence solve above: 0.33 m/s.)"""
from __future__ import annotations

import functools
import math
from typing import Literal, Mapping

import numpy as np
from pydantic import Field, model_validator

from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import ParticleFrame
from stages.common.sdf import SDFGrid, wall_move_limit
from stages.common.sizes import simulate_estimate

from . import dfsph_kernels as D
from . import sph_kernels as K
from .driver import SolverBase, drive, moving_wall, prepare, set_threads
from .emitters import check_emitters, emitter_files
from .effects import EffectConstants, compile_effects
from .walls.spline import SplineWallMaps, spline_coefs, spline_f_np, spline_lattice_mass
from .kernels import lattice_mass, lattice_modes, poly6_coef, spiky_grad_coef, spiky_lattice_factor, visc_lattice_factor
from .neighbours import CellGrid
from .sph import SPHSolver
from .walls.maps import BrickWallMaps, make_walls
from .timestep import REFERENCE_SPACING, stable_dt, step_to


# the default largest step: 5 ms, set for the PEERS dam break at 2 cm spacing; Froude-scaled for coarser ones
DT_MAX_REF = 0.005
CFL_REF = 0.8  # the default cfl, which the solves' tolerances and warm start are set for
RELAXATION = 0.5  # the solves' default Jacobi relaxation (Bender and Koschier 2017), where it is below the limit
RELAXATION_MARGIN = 0.8  # the most a relaxation may be, as a fraction of jacobi_limit (walls and the free surface
# move the real threshold: Spiky at 2 l0 diverged at 0.95 of it in test_dfsph's tank, ran at 0.9)


@functools.lru_cache(maxsize=None)
def jacobi_limit(gradient: str, support: float, samples: int = 24) -> float:
    """The relaxation omega above which the solves' Jacobi iterations diverge on the rest lattice: 2 / the
    largest eigenvalue of D^-1 A, A = J J^T their system (J the density's gradient: the pair force
    (kappa_i + kappa_j) grad W_ij and its transpose the density rate), D its diagonal (the factor alpha).
    A mode kappa_j = exp(i k . x_j) of the full cubic lattice has the eigenvalue
    |sum_j sin(k . x_j) grad W(x_j)|^2 / sum_j |grad W(x_j)|^2, largest inside the Brillouin zone (sampled at
    samples^3 wave vectors); it grows with the neighbours. The limit is 0.71 for Spiky and the spline at 2 l0
    and 0.53 for Poly6, 0.52 / 0.48 for Spiky at 2.4 / 2.5 l0, 0.30 at 3 l0, 0.14 at 4 l0. At omega 0.5 the
    solves on bench_rest's tank diverged (1e4-1e41 m/s in the first steps) from support 2.5 l0 (Spiky), 2.4
    (spline) and 2.25 (Poly6), and at 2 l0 (Spiky) with omega 0.68, 0.96 of the limit."""
    offsets, r, waves = lattice_modes(support, samples)
    if gradient == "spiky":
        slope = (support - r) ** 2
    elif gradient == "poly6":
        slope = r * (support * support - r * r) ** 2
    else:
        slope = spline_f_np(r, support) * r
    grad = slope[:, None] * offsets / r[:, None]
    eig = ((np.sin(waves @ offsets.T) @ grad) ** 2).sum(axis=1) / (grad ** 2).sum()
    return float(2.0 / eig.max())


class DFSPHParams(Params):
    support: float = Field(2.0, ge=1.5, le=4.0, description="kernel support radius h in units of the spacing l0")
    cfl: float = Field(CFL_REF, gt=0, le=1.0, description="advective limit dt <= cfl l0 / v_max (0.8: the PEERS dam "
                       "break keeps a mean density error of 0.08 %, 0.05 % at 0.5, in 25 % fewer steps; below 0.8 the "
                       "warm start is scaled by cfl / 0.8)")
    dt_max: float | None = Field(None, gt=0, description="largest time step, s (also capped by the frame interval); "
                                 "default 5 ms at spacings up to 2 cm, Froude-scaled above (5 ms sqrt(l0 / 2 cm)): a "
                                 "scene 10,000 x larger runs the same steps at 100 x their length")
    max_density_error: float = Field(0.001, gt=0, le=0.05, description="constant-density solve: stop when the "
                                     "average predicted compression (plus a fifth of the expansion where the "
                                     "pressure is positive) is below this fraction of rho0")
    max_divergence_error: float = Field(0.001, gt=0, le=0.05, description="divergence solve: stop when the average "
                                        "dt D rho / Dt (compressing, plus a fifth of it expanding where the "
                                        "pressure is positive) is below this fraction of rho0")
    min_iterations: int = Field(2, ge=1, description="constant-density solve: at least this many iterations")
    max_iterations: int = Field(100, ge=1, description="iteration cap of each solve")
    relaxation: float | None = Field(None, gt=0, le=1, description="Jacobi relaxation omega (kappa may also "
                                     "decrease, never below 0); default 0.5, or 0.8 x the solves' stability limit "
                                     "where that is lower (Poly6 at 2 l0: 0.43; Spiky at 3 l0: 0.24); beyond the limit "
                                     "the solves diverge, so more than 0.8 x it is refused (dfsph.jacobi_limit)")
    warm_start: float = Field(1.0, ge=0, le=1, description="start each solve from this fraction of the last "
                              "step's pressure (Bender and Koschier 2017, sec. 4.4), times cfl / 0.8 and dt_max / "
                              "its default where those are less than 1 (steps shorter than the defaults')")
    divergence_solve: bool = Field(True, description="run the divergence-free solve (Bender and Koschier 2015)")
    gradient: Literal["spiky", "poly6", "spline"] = Field("spiky", description="pressure kernel gradient: Spiky "
                                                          "(eq. 8, normalised as in sph) or the exact Poly6 derivative "
                                                          "of the density; 'spline': the cubic spline for the density and "
                                                          "its gradient, walls as its quadrature (walls/spline.py)")
    r_rep: float = Field(0.2, gt=0, le=0.5, description="eq. 16 wall clamp distance, in units of l0: a safety net "
                         "below the first layer's rest distance 0.5 l0, so the solver, not the clamp, holds the fluid "
                         "(at most 0.5: beyond it the clamp pushes that layer off the walls and makes energy)")
    checkpoint_every: int = Field(10, ge=1, description="write a checkpoint every this many frames")
    threads: int | None = Field(None, ge=1, description="numba threads (fixed count = reproducible results)")
    table_samples: int = Field(256, ge=16, description="samples of the wall tables over [0, h]")

    @model_validator(mode="after")
    def _solves_that_converge(self):
        if self.min_iterations > self.max_iterations:
            raise ValueError(f"min_iterations {self.min_iterations} is above max_iterations {self.max_iterations}")
        # resolved once, so the cache key and every reader see the relaxation that runs
        most = RELAXATION_MARGIN * jacobi_limit(self.gradient, self.support)
        if self.relaxation is None:
            object.__setattr__(self, "relaxation", min(RELAXATION, round(most, 3)))
        elif self.relaxation > most:
            raise ValueError(f"relaxation {self.relaxation:g} is above {most:.3f}, 0.8 of the limit "
                             f"{most / RELAXATION_MARGIN:.3f} beyond which the Jacobi solves diverge for the "
                             f"{self.gradient} gradient at support {self.support:g} l0: lower it, or leave it out")
        return self


class DFSPHSolver(SolverBase):
    """State (x, v, id, kappa in cell order) plus the per-step kernels; every buffer is reused."""

    carried = ("kappa", "kappa_v")
    stiffness_settings = "lower max_density_error or raise max_iterations"

    c = 0.0  # no speed of sound: incompressible

    def __init__(self, x, v, ids, sdf: SDFGrid, *, spacing: float, rho0: float, params: DFSPHParams,
                 gravity=(0.0, 0.0, 0.0), mu: float | None = None, wall_viscosity: bool = True,
                 domain=None, effects: EffectConstants | None = None):
        if effects is None:
            effects = EffectConstants(mu=mu, wall_viscosity=wall_viscosity)
        self.effects = effects
        self.p = params
        self.l0 = float(spacing)
        self.h = params.support * self.l0
        # an absolute 5 ms cap held a kilometre-wide scene to 1/100 of its Froude-scaled step (steps that short
        # blew up until step() removed the density error over the natural step: test_dfsph_survives_a_step...)
        self.dt_default = DT_MAX_REF * math.sqrt(max(self.l0, REFERENCE_SPACING) / REFERENCE_SPACING)
        self.dt_max = params.dt_max or self.dt_default
        # the warm start scaled by how much shorter the settings make the steps than the defaults' (cfl 0.8, dt_max
        # 5 ms Froude-scaled; an effect's step limit): the solves' tolerances bound dt x the error's rate, so at short
        # steps a warm-started pressure passed as converged and was applied whole every step (the suite's 10 m/s jet
        # blew up at cfl 0.2, its dam break at 0.1; the jet's energy rose 2.9 x at dt_max 0.2 ms); 1 at the defaults
        shortest = min(self.dt_max, effects.dt_limit)
        self.warm_start = params.warm_start * min(1.0, params.cfl / CFL_REF) * min(1.0, shortest / self.dt_default)
        self.rho0 = float(rho0)
        self.mode = {"spiky": D.SPIKY, "poly6": D.POLY6, "spline": D.SPLINE}[params.gradient]
        if self.mode == D.SPLINE:  # one kernel for the density and its gradient, walls included
            self.mass = spline_lattice_mass(self.rho0, self.l0, self.h)
            self.walls = SplineWallMaps(sdf, self.l0, self.h, self.mass, self.rho0, params.table_samples)
        else:
            self.mass = lattice_mass(self.rho0, self.l0, self.h)
            self.walls = BrickWallMaps(sdf, self.l0, self.h, self.mass, self.rho0, params.table_samples)
        self.fix_vis = self.walls.fix_vis if effects.wall_viscosity else np.zeros_like(self.walls.fix_vis)
        if effects.adhesion_accel is not None and len(effects.adhesion_accel) != params.table_samples:
            raise ValueError("effects.adhesion_accel must be sampled like the wall tables (table_samples)")
        self.grad_norm = spiky_lattice_factor(self.rho0, self.l0, self.h, self.mass)
        self.grad_coef = spiky_grad_coef(self.h) / self.grad_norm if self.mode == D.SPIKY else 6.0 * poly6_coef(self.h)
        self.fix_press = self.walls.fix_press / self.grad_norm  # Spiky wall gradient, normalised like grad_coef
        self.density_coefs = (poly6_coef(self.h), self.grad_coef)
        if self.mode == D.SPLINE:
            self.density_coefs = spline_coefs(self.h)
            self.grad_coef = spiky_grad_coef(self.h) / self.grad_norm  # surface tension's normals only
            self.fix_press = self.walls.fix_press  # the spline's own wall gradient, not normalised
        self.gravity = np.asarray(gravity, np.float64)
        # as SPHSolver: mu over the eq. 9 sum's Laplacian on the rest lattice
        self.mu = (float(effects.mu) / visc_lattice_factor(self.rho0, self.l0, self.h, self.mass)
                   if effects.mu is not None else 0.0)
        self.nu = float(effects.mu) / self.rho0 if effects.mu is not None else 0.0  # for the viscous step limit
        self.sdf = sdf
        self.sdf_inv = 1.0 / sdf.spacing
        self.wall_terms = make_walls(sdf, self.walls)  # what the shared WCSPH kernels take
        lo, hi = (sdf.origin, sdf.upper) if domain is None else domain
        self.domain = (np.asarray(lo, float), np.asarray(hi, float))
        self.grid = CellGrid(sdf.origin, sdf.upper, self.h)
        self.wall_mirror = D.WALL_MIRROR
        self.cap = 48  # neighbour-list stride, grown when a pass finds more
        self.x = np.array(x, np.float64)
        self.v = np.array(v, np.float64)
        self.id = np.array(ids, np.int32)
        self.kappa = np.zeros(len(self.x))  # constant-density solve's kappa = p / rho (kept: warm start)
        self.kappa_v = np.zeros(len(self.x))  # divergence solve's kappa
        self.min_rho = 0.6 * self.rho0  # divergence solve: leave sparse free-surface particles alone
        self.t = 0.0
        self.steps = 0
        self.left_domain = 0
        self.iterations = [0, 0]  # total (density, divergence) iterations, for the statistics
        self.unsolved: tuple[str, float, float] | None = None  # the last step's solve that stopped at its cap
        self.solve_error = [0.0, 0.0]  # sum over steps of the final average (density, divergence) error / rho0
        self._fresh = False
        self._alloc()

    def _alloc(self) -> None:
        n = len(self.x)
        self.rho = np.zeros(n)
        self.pr = np.zeros(n)
        self.alpha = np.zeros(n)
        self.d = np.zeros(n)
        self.nrm = np.zeros((n, 3))
        self.psi = np.zeros((n, 3))
        self.acc = np.zeros((n, 3))
        self.zero_acc = np.zeros((n, 3))
        self.u = np.zeros((n, 3))  # v + dt a(kappa) during a solve
        self.kr = np.zeros(n)  # kappa / rho of the density solve (warm started by the density pass)
        self.kr_v = np.zeros(n)  # kappa_v / rho of the divergence solve
        self.kr_next = np.zeros(n)  # a sweep's proposal for the next kr (kr_v)
        # the state's second buffers: the sort gathers into them and the two sets swap
        self._back = (np.empty_like(self.x), np.empty_like(self.v), np.empty_like(self.id), np.empty_like(self.kappa),
                      np.empty_like(self.kappa_v))
        self.err = np.zeros(n)
        self.count = np.zeros(n, np.int32)
        self.nbr = np.zeros(n * self.cap, np.int32)
        self.fac = np.zeros(n * self.cap, np.float32)
        self.normals = np.zeros((n, 3)) if self.effects.tension_k is not None else None

    # -- the pieces of a step -----------------------------------------------------------------
    def refresh(self) -> None:
        """Sort into cell order, then density, factors and neighbour lists at the current positions."""
        order = self.grid.sort(self.x)
        front = (self.x, self.v, self.id, self.kappa, self.kappa_v)
        D.gather_state(order, *front, *self._back)
        (self.x, self.v, self.id, self.kappa, self.kappa_v), self._back = self._back, front
        g, w = self.grid, self.walls
        while True:
            most = D.density_alpha_neighbours(
                self.x, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, *self.density_coefs, self.mass,
                self.rho0, w.wmap, w.origin, 1.0 / w.spacing, w.fix_rho, self.fix_press, 0.25 * self.l0, w.inv_dr, self.sdf.dist,
                self.sdf.origin, self.sdf_inv, self.wall_mirror, self.mode, self.cap, self.nbr, self.fac, self.count, self.rho, self.alpha,
                self.d, self.nrm, self.psi, self.warm_start, self.kappa, self.kappa_v, self.kr, self.kr_v)
            if most <= self.cap:
                break
            self.cap = int(most) + 8  # never drop a neighbour: grow and run the pass again
            self.nbr = np.zeros(len(self.x) * self.cap, np.int32)
            self.fac = np.zeros(len(self.x) * self.cap, np.float32)
        self._fresh = True

    # the same members (effects, mu, h, fix_vis, normals) feed the same force kernel
    effect_args = SPHSolver.effect_args

    def non_pressure_forces(self) -> None:
        g = self.grid
        if self.normals is not None:
            K.surface_normals(self.x, self.rho, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, self.grad_coef,
                              self.mass, self.normals)
        # over this step's neighbour lists (same pairs, same order as the cell scan: the same sums)
        lists = (self.nbr.reshape(len(self.x), self.cap), self.count)
        K.forces(self.x, self.v, self.rho, self.d, self.nrm, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, self.mass,
                 self.rho0, self.wall_terms, self.gravity, self.acc, None,
                 *self.effect_args(), neighbours=lists)

    def natural_dt(self) -> float:
        """The CFL, viscous and force limits at this state, uncapped (inf at rest): the step is this under
        the caps (the frame's end, dt_max, effects)."""
        v2, a2 = K.max_speed2_accel2(self.v, self.acc)
        return stable_dt(l0=self.l0, h=self.h, v_max=math.sqrt(v2), a_max=math.sqrt(a2), cfl=self.p.cfl,
                         sound_speed=None, dt_viscous=self.viscous_dt(), dt_max=math.inf)

    viscous_dt = SPHSolver.viscous_dt  # the same eq. 9 sum

    def _solve(self, dt: float, divergence: bool, beta: float = 1.0) -> tuple[int, float]:
        """Projected, relaxed Jacobi iterations of the constant-density (or divergence-free) solve from
        the warm start the density pass left in kr (kr_v); the density solve includes the non-pressure
        accelerations (self.v is the velocity before them). Sets self.v = v + dt a (in place). Returns
        (iterations, final average error / rho0).
        A sweep measures the error of u = v + dt a(kr) and proposes the next kr: once the error is within
        the tolerance, that u and its kr are the solve's answer, and the sweep's proposal is dropped (no
        further pass over the neighbours to apply it: about 5 % of a step at 20k)."""
        p = self.p
        kappa = self.kappa_v if divergence else self.kappa
        kr, kr_next = (self.kr_v if divergence else self.kr), self.kr_next
        acc = self.zero_acc if divergence else self.acc  # zeros, not None: one build of predict_velocity, not two
        eta = p.max_divergence_error if divergence else p.max_density_error
        least = 1 if divergence else p.min_iterations
        lists = (self.nbr, self.fac, self.count, self.cap, self.mass, self.psi)
        n = max(len(self.x), 1)
        it = 0
        avg = 0.0
        converged = False
        while it < p.max_iterations:
            D.predict_velocity(self.x, self.v, acc, dt, *lists, kr, self.wall_mirror, self.u)
            if divergence:
                D.jacobi_divergence(self.x, self.u, *lists, self.rho, self.alpha, dt, p.relaxation, self.min_rho,
                                    kappa, kr, kr_next, self.err)
                avg = float(self.err.sum()) * dt / n / self.rho0
            else:
                D.jacobi_density(self.x, self.u, *lists, self.rho, self.alpha, self.rho0, dt, beta, p.relaxation, kappa,
                                 kr, kr_next, self.err)
                avg = float(self.err.sum()) / n / self.rho0
            it += 1
            if avg <= eta and it >= least:
                converged = True
                break
            kr, kr_next = kr_next, kr
        if converged:
            np.copyto(self.v, self.u)  # u is the answer (a copy: others may hold self.v)
            np.multiply(kr, self.rho, out=kappa)  # the kappa of that answer (the sweep wrote its proposal)
        else:
            D.predict_velocity(self.x, self.v, acc, dt, *lists, kr, self.wall_mirror, self.v)
        # the buffers may have swapped: kr (kr_v) names the solve's field again for the warm start and output
        if divergence:
            self.kr_v, self.kr_next = kr, kr_next
        else:
            self.kr, self.kr_next = kr, kr_next
        return it, avg

    def step(self, t_end: float) -> float:
        """One DFSPH step towards t_end (never past it); returns dt."""
        if not self._fresh:
            self.refresh()
        self.non_pressure_forces()
        natural = self.natural_dt()
        dt = step_to(self.t, t_end, min(natural, t_end - self.t, self.dt_max, self.effects.dt_limit))
        if not (dt > 0.0 and math.isfinite(dt)):
            raise FloatingPointError(f"dfsph: the solver diverged at t = {self.t:.4g} s (time step {dt})")
        # the density error the step finds is removed over the scene's natural step (CFL and force limits,
        # the default cap), not within a step shortened by a frame's end or a user's dt_max: removing it
        # in dt takes a velocity of (error / rho0) l0 / dt, and a 0.05 ms step turned the start lattice's
        # 0.7 % at the walls into 9 m/s in one step (Baumgarte's stabilisation of the constraint)
        beta = min(1.0, dt / min(natural, self.dt_default))
        it, err = self._solve(dt, divergence=False, beta=beta)  # v* = v + dt (a_nonpressure + a_pressure)
        self.iterations[0] += it
        self.solve_error[0] += err
        self.unsolved = ("density", err, self.p.max_density_error) if err > self.p.max_density_error else None
        # x += dt v*, then the eq. 16 clamp along the SDF normal as a safety net (acceleration already in v);
        # with self.d, the density pass's wall distances at these positions, particles far from the walls skip
        # the SDF (3.4-4.4 -> 1.5-2.2 ms a step at 20k); the refresh below samples every d again
        K.integrate(self.x, self.v, self.zero_acc, dt, self.wall_terms,
                    self.p.r_rep * self.l0, 0.5 * self.l0, wall_move_limit(self.p.r_rep) * self.l0, None, self.d)
        self.refresh()
        if self.p.divergence_solve:
            it, err = self._solve(dt, divergence=True)
            self.iterations[1] += it
            self.solve_error[1] += err
            if self.unsolved is None and err > self.p.max_divergence_error:
                self.unsolved = ("divergence", err, self.p.max_divergence_error)
        self.t = t_end if dt >= t_end - self.t else self.t + dt
        self.steps += 1
        return dt

    def unconverged(self) -> str | None:
        if self.unsolved is None:
            return None
        which, err, eta = self.unsolved
        return (f"the {which} solve stopped at max_iterations ({self.p.max_iterations}) with an average error of "
                f"{err:.3g} (max_{which}_error {eta:g}): raise max_iterations, or lower the cfl")

    def _resized(self) -> None:
        self._alloc()
        self._fresh = False

    def frame(self) -> ParticleFrame:
        """The current state with its density and pressure (p = kappa rho of the last density solve)."""
        if not self._fresh:
            self.refresh()
        D.pressure_of(self.kappa, self.rho, self.pr)
        return ParticleFrame(x=self.x.copy(), v=self.v.copy(), rho=self.rho.copy(), p=self.pr.copy(), id=self.id.copy())

    def state(self) -> dict:
        return {"x": self.x, "v": self.v, "id": self.id, "kappa": self.kappa, "kappa_v": self.kappa_v, "t": np.float64(self.t),
                "steps": np.int64(self.steps), "left_domain": np.int64(self.left_domain),
                "iterations": np.asarray(self.iterations, np.int64), "solve_error": np.asarray(self.solve_error),
                **self.flow_state()}

    def load_state(self, s: Mapping) -> None:
        self.x = np.ascontiguousarray(s["x"], np.float64)
        self.v = np.ascontiguousarray(s["v"], np.float64)
        self.id = np.ascontiguousarray(s["id"], np.int32)
        self.kappa = np.ascontiguousarray(s["kappa"], np.float64)
        self.kappa_v = np.ascontiguousarray(s["kappa_v"], np.float64)
        self.t = float(s["t"])
        self.steps = int(s["steps"])
        self.left_domain = int(s["left_domain"])
        self.load_flow_state(s)
        self.iterations = [int(k) for k in s["iterations"]]
        self.solve_error = [float(e) for e in s["solve_error"]]
        self._alloc()
        self._fresh = False

    def solver_stats(self) -> dict:
        n = max(self.steps, 1)
        return {"mean_density_iterations": self.iterations[0] / n, "mean_divergence_iterations": self.iterations[1] / n,
                "mean_density_solve_error": self.solve_error[0] / n,
                "mean_divergence_solve_error": self.solve_error[1] / n}


class DFSPHSimulate(Stage):
    kind = "simulate"
    name = "dfsph"
    version = "2"
    Params = DFSPHParams
    inputs = ("sdf",)
    reads = ("scene.units", "scene.domain", "scene.frames.count", "scene.frames.fps", "fluid", "effects")
    estimate_reads = ("walls",)  # check: walls[].motion
    extends = "scene.frames.count"  # a longer shot continues from the cached shorter run's last frame
    warm_up_run = True  # numba: a study compiles the kernels on a short run first (pipeline.study)
    outputs = ("particles",)
    description = "divergence-free SPH (Bender and Koschier 2017) with distance-function walls, numba"

    def frame_count(self, ctx: Context, params: Params, inputs: Mapping[str, Artifact]) -> int | None:
        return ctx.scene["scene"].frames.count

    def external_files(self, ctx: Context, params: Params) -> list:
        return emitter_files(ctx)  # the layers a USD mesh emitter composes

    def check(self, ctx: Context, params: Params) -> None:
        check_emitters(ctx, "simulate.dfsph")
        moving = moving_wall(ctx)
        if moving is not None:
            raise StageError(f"simulate.dfsph: walls.{moving} moves (motion); only simulate: {{use: sph}} and "
                             "{use: mps} move walls so far")

    def estimate(self, ctx: Context, params: Params) -> dict | None:
        return simulate_estimate(ctx, params.cfl, None, params.support)

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: DFSPHParams) -> None:
        set_threads(params.threads or getattr(ctx, "threads", None))
        setup = prepare(ctx, inputs, "simulate.dfsph")
        h = params.support * setup.spacing
        effects = compile_effects(setup.effects, meters_per_unit=setup.meters_per_unit, rho0=setup.density,
                                  l0=setup.spacing, h=h, table_samples=params.table_samples)
        solver = DFSPHSolver(setup.x, setup.v, np.arange(len(setup.x), dtype=np.int32), setup.sdf,
                             spacing=setup.spacing, rho0=setup.density, params=params, gravity=setup.gravity,
                             domain=setup.domain, effects=effects)
        drive(ctx, solver, setup, solver_name="dfsph", checkpoint_every=params.checkpoint_every)
