"""simulate.sph: weakly compressible SPH with distance-function walls (Harada et al. 2007).

``SPHSolver`` holds the state and steps it (used by the stage and the benchmark); ``SPHSimulate`` is
the stage; the set-up and frame loop shared with the other solvers are in driver.py."""
from __future__ import annotations

import math
from typing import Literal, Mapping

import numpy as np
from pydantic import Field, model_validator

from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import ParticleFrame
from stages.common.sdf import SDFGrid, wall_move_limit
from stages.common.sizes import simulate_estimate

from . import sph_kernels as K
from .driver import SolverBase, drive, effects_speed, moving_wall, prepare, scene_corners, set_threads
from .emitters import check_emitters, emitter_files
from .effects import EffectConstants, compile_effects, cohesion_coef
from .kernels import (lattice_mass, poly6_coef, rest_lattice, spiky_grad_coef, spiky_lattice_factor, visc_lap_coef,
                      visc_lattice_factor, wall_gradient_tables)
from .neighbours import CellGrid, neighbour_list, reorder
from .walls.maps import BrickWallMaps, make_walls
from .walls.spline import SplineWallMaps, spline_coefs, spline_lattice_mass
from .timestep import stable_dt, step_to, viscous_coefficient


class SPHParams(Params):
    support: float | None = Field(None, ge=1.5, le=4.0, description="kernel support radius h in units of the spacing "
                                  "l0; default 2.25 for the spline (the swayed tank rings within 3 % of its mode at "
                                  "2.25, 6 % sharp at 2), 2 for Poly6 / Spiky")
    kernel: Literal["poly6_spiky", "spline"] | None = Field(None, description="'spline' (the default): the cubic "
                                                     "spline for the density and its own gradient in the pair form "
                                                     "p_i / rho_i^2 + p_j / rho_j^2, the walls as its quadrature "
                                                     "(walls/spline.py): the pressure force is the derivative of the "
                                                     "compression energy, so fluid at rest settles (issue 17); "
                                                     "'poly6_spiky': Poly6 density, Spiky pressure gradient (Mueller "
                                                     "et al. 2003), the one gradient_correction, wall_gradient and "
                                                     "the mirrored wall pressure are fitted to, and the default with them")
    eos: Literal["linear", "tait"] = Field("linear", description="eq. 5 p = k (rho - rho0), k = c^2; or Tait, B = rho0 c^2 / 7")
    sound_speed: float | None = Field(None, gt=0, description="numerical speed of sound c, m/s; default 10 x the expected "
                                      "top speed (sqrt(2 g H) of the fluid column, or the emitters' speed; where the fluid starts over a drop, "
                                      "sqrt(v0^2 + 2 g H) from its top to the wall under it), plus wind and an attractor's speed")
    cfl: float = Field(0.4, gt=0, le=1.0, description="advective limit dt <= cfl l0 / v_max")
    time_step: float | None = Field(None, gt=0, description="a fixed time step, s, instead of the adaptive one "
                                    "(stability studies: a step above the stable one stops the run with a blow-up error); a frame's last two "
                                    "steps share what is left of it when that is under 1.5 steps (frames land on their "
                                    "times, no sliver step)")
    r_rep: float = Field(0.5, gt=0, le=0.5, description="eq. 16 wall repulsion distance, in units of l0; at most "
                         "0.5, where the first layer rests (1.0 pushed that layer off the walls: 4.7 x the energy)")
    clamp_pressure: bool = Field(True, description="clamp negative pressure to 0 (avoids free-surface clumping)")
    checkpoint_every: int = Field(10, ge=1, description="write a checkpoint every this many frames")
    threads: int | None = Field(None, ge=1, description="numba threads (fixed count = reproducible results)")
    artificial_viscosity: float = Field(0.05, ge=0, le=1, description="Monaghan alpha (dimensionless): "
                                        "dissipates WCSPH acoustic noise on approaching pairs, nu_art ~ alpha c h / 8")
    table_samples: int = Field(256, ge=16, description="samples of the Z_rho / Z_vis wall tables over [0, h]")
    neighbour_skin: float = Field(0.2, ge=0, le=1.0, description="Verlet skin, in units of l0: the neighbour list "
                                  "holds the pairs within h + skin and is rebuilt (with the cell sort) once "
                                  "particles may have closed in by the skin; 0 = rebuilt every step")
    gradient_correction: bool = Field(False, description="symmetric kernel-gradient correction of the pressure "
                                      "force (Bonet and Lok 1999): exact for a linear pressure on any packing")
    wall_gradient: bool = Field(False, description="the walls' share of the hydrostatic pressure gradient "
                                "(Adami et al. 2012 wall pressure p_w = p + rho g . (x_w - x)): support along side walls")
    wall_pressure: Literal["auto", "conservative", "mirrored"] = Field("auto", description="the walls' pressure "
                                 "force: -(p_i / rho_i^2) grad of the wall density (conservative: fluid at rest settles), "
                                 "or mirrored wall particles at the neighbours' mean pressure (the former form, which "
                                 "gradient_correction and wall_gradient are fitted to; it circulates at rest); auto: "
                                 "mirrored with those options, else conservative")
    correction_wall_fade: bool = Field(True, description="fade the correction out within h of a wall (none in the "
                                       "first row): the flat-wall tensor table undercounts edges and corners")
    correction_full: float = Field(0.97, gt=0.9, le=1, description="density ratio rho/rho0 from which the "
                                   "correction applies fully (linearly less below, none at 0.9: the free surface)")

    @model_validator(mode="after")
    def _spiky_options(self):
        spiky_only = [name for name in ("gradient_correction", "wall_gradient") if getattr(self, name)]
        if self.wall_pressure == "mirrored":
            spiky_only.append("wall_pressure: mirrored")
        if self.kernel is None:  # resolved once, so the cache key and every reader see the kernel that runs
            object.__setattr__(self, "kernel", "poly6_spiky" if spiky_only else "spline")
        elif self.kernel == "spline" and spiky_only:
            raise ValueError(f"{spiky_only[0]} is fitted to the Spiky gradient: set kernel: poly6_spiky with it")
        if self.support is None:
            object.__setattr__(self, "support", 2.25 if self.kernel == "spline" else 2.0)
        return self


# neighbour-list slots per particle to start with, at least (33 within h + skin = 2.2 l0 on the resting lattice,
# the particle itself included: Poly6 / Spiky's support and the default skin); a list starts at its kernel's
# lattice count + NEIGHBOUR_SLACK when that is more (81 within the spline's 2.45 l0) and grows when a build finds more
NEIGHBOUR_CAP = 48
NEIGHBOUR_SLACK = 8


class SPHSolver(SolverBase):
    """State (x, v, id in cell order) plus the per-step kernels; every buffer is reused."""

    stiffness_settings = "raise sound_speed, or leave it out (10 x the scene's expected speed)"
    nbr_cap: int | None = None  # neighbour-list slots per particle (None: sized from the rest lattice at the start)

    def __init__(self, x, v, ids, sdf: SDFGrid, *, spacing: float, rho0: float, params: SPHParams,
                 gravity=(0.0, 0.0, 0.0), mu: float | None = None, wall_viscosity: bool = True,
                 v_ref: float = 1.0, domain=None, effects: EffectConstants | None = None, bodies=()):
        """``effects`` (effects.compile_effects) selects the compiled force kernel; without it, ``mu``
        and ``wall_viscosity`` give the pressure(+viscosity) solver of issue 4. ``bodies``: the moving
        rigid walls, each (SDFGrid baked in its rest frame, motion with ``pose(t)`` and ``velocity(t)``
        as stages.common.motion.RigidMotion), all in SI; ``sdf`` holds the static walls only."""
        if effects is None:
            effects = EffectConstants(mu=mu, wall_viscosity=wall_viscosity)
        self.effects = effects
        mu, wall_viscosity = effects.mu, effects.wall_viscosity
        self.p = params
        self.l0 = float(spacing)
        self.h = params.support * self.l0
        self.rho0 = float(rho0)
        self.spline = params.kernel == "spline"
        self._spline_arg = (1.0,) if self.spline else None  # the kernels' compile-time switch (None: Poly6/Spiky)
        if self.spline:  # one kernel for the density and the pressure gradient, walls included
            self.mass = spline_lattice_mass(self.rho0, self.l0, self.h)
            self.walls = SplineWallMaps(sdf, self.l0, self.h, self.mass, self.rho0, params.table_samples)
            self.density_coef, self.pressure_coef = spline_coefs(self.h)
        else:
            self.mass = lattice_mass(self.rho0, self.l0, self.h)
            self.walls = BrickWallMaps(sdf, self.l0, self.h, self.mass, self.rho0, params.table_samples)
        self.fix_vis = self.walls.fix_vis if wall_viscosity else np.zeros_like(self.walls.fix_vis)
        self.inv_dr = self.walls.inv_dr
        if effects.adhesion_accel is not None and len(effects.adhesion_accel) != params.table_samples:
            raise ValueError("effects.adhesion_accel must be sampled like the wall tables (table_samples)")
        self.grad_norm = spiky_lattice_factor(self.rho0, self.l0, self.h, self.mass)
        if not self.spline:
            self.density_coef, self.pressure_coef = poly6_coef(self.h), spiky_grad_coef(self.h) / self.grad_norm
        self.fix_press = self.walls.fix_press / self.grad_norm  # the mirrored wall's table (wall_pressure)
        self.mirrored_wall = params.wall_pressure == "mirrored" or (
            params.wall_pressure == "auto" and (params.wall_gradient or params.gradient_correction))
        if bodies and self.mirrored_wall:
            raise ValueError("simulate.sph: moving walls need the conservative wall pressure (wall_pressure: "
                             "conservative, without gradient_correction or wall_gradient)")
        self.set_motions(bodies)
        maps = SplineWallMaps if self.spline else BrickWallMaps
        self.bodies = [(b, maps(b, self.l0, self.h, self.mass, self.rho0, params.table_samples)) for b, _ in bodies]
        self.wall_terms = make_walls(sdf, self.walls, self.bodies)
        self.wall_t = None
        if params.wall_gradient or params.gradient_correction:
            self.wall_t = wall_gradient_tables(self.l0, self.h, self.mass, self.rho0, self.grad_norm, params.table_samples)
        self.c = float(params.sound_speed or 10.0 * max(v_ref, 1e-3))
        self.stiffness = self.c ** 2 if params.eos == "linear" else self.rho0 * self.c ** 2 / 7.0
        self.eos = K.EOS_LINEAR if params.eos == "linear" else K.EOS_TAIT
        self.gravity = np.asarray(gravity, np.float64)
        # the eq. 9 sum's coefficient: mu over its Laplacian on the rest lattice (exact there at any support)
        self.mu = float(mu) / visc_lattice_factor(self.rho0, self.l0, self.h, self.mass) if mu is not None else 0.0
        self.nu = float(mu) / self.rho0 if mu is not None else 0.0  # the fluid's, for the viscous step limit
        self.sdf = sdf
        self.sdf_inv = 1.0 / sdf.spacing
        lo, hi = (sdf.origin, sdf.upper) if domain is None else domain
        self.domain = (np.asarray(lo, float), np.asarray(hi, float))
        self.skin = params.neighbour_skin * self.l0
        self._pose_bodies(0.0)
        self.grid = CellGrid(sdf.origin, sdf.upper, self.h + self.skin)
        self.x = np.array(x, np.float64)  # own copies: the sort reuses buffers
        self.v = np.array(v, np.float64)
        self.id = np.array(ids, np.int32)
        self.t = 0.0
        self.steps = 0
        self.left_domain = 0
        self._scratch: dict = {}
        self._alloc()

    def _alloc(self) -> None:
        n = len(self.x)
        self.rho = np.zeros(n)
        self.pr = np.zeros(n)
        self.d = np.zeros(n)
        self.nrm = np.zeros((n, 3))
        self.acc = np.zeros((n, 3))
        # the Verlet list: the pairs within h + skin at the last build (grown on overflow, never shrunk);
        # each density pass moves the pairs r < h to the front of the row, cnt_in of them
        if self.nbr_cap is None:
            _, r = rest_lattice(self.l0, self.h + self.skin)
            self.nbr_cap = max(NEIGHBOUR_CAP, int((r <= self.h + self.skin).sum()) + NEIGHBOUR_SLACK)  # self included
        self.nbr = np.zeros((n, self.nbr_cap), np.int32)
        self.cnt = np.zeros(n, np.int32)
        self.cnt_in = np.zeros(n, np.int32)
        self.travel = np.zeros(n)  # path length of each particle since the build
        self.stale = True  # no list for these arrays yet
        self.inv_rho = np.zeros(n)
        self.normals = np.zeros((n, 3)) if self.effects.tension_k is not None else None
        self.lcorr = np.zeros((n, 6)) if self.p.gradient_correction else None

    # -- one step -----------------------------------------------------------------------------
    def build_neighbours(self) -> None:
        """Sort the particles into cell order and list the pairs within h + skin."""
        order = self.grid.sort(self.x)
        self.x, self.v, self.id = reorder([self.x, self.v, self.id], order, self._scratch)
        g = self.grid
        while True:
            neighbour_list(self.x, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h + self.skin, self.nbr, self.cnt)
            most = int(self.cnt.max()) if len(self.cnt) else 0
            if most <= self.nbr.shape[1]:
                break
            # a compressed spot has more neighbours than the list holds: grow it and redo the pass
            # (the list does not depend on the capacity, so this stays deterministic)
            self.nbr_cap = most + NEIGHBOUR_SLACK
            self.nbr = None  # the old list freed first: the peak memory holds one list, not both
            self.nbr = np.zeros((len(self.x), self.nbr_cap), np.int32)
        self.travel[:] = 0.0
        self.stale = False

    def sort_and_density(self, rebuild: bool = False) -> None:
        # two particles have closed in by at most the sum of their path lengths since the build: while
        # that is below the skin, every pair r < h is still in the list
        built = rebuild or self.stale or 2.0 * K.max_of(self.travel) >= self.skin
        if built:
            self.build_neighbours()
        # after a build (the arrays reordered) every particle samples the SDF; between builds only those
        # within h of a wall by integrate's lower bound of their distance
        # (with moving walls every particle samples them: the distance bound holds for static walls only)
        K.density_verlet(self.x, self.nbr, self.cnt, self.cnt_in, self.h, self.density_coef, self.mass, self.rho0,
                         self.wall_terms, self.eos, self.stiffness, self.p.clamp_pressure, self.rho, self.pr, self.d,
                         self.nrm, self.inv_rho, built or bool(self.bodies), self._spline_arg)

    def effect_args(self) -> tuple:
        """(viscosity, tension, adhesion, friction, wind, attractor) for K.forces: None when absent."""
        e = self.effects
        vis = (self.mu, visc_lap_coef(self.h), self.fix_vis) if e.mu is not None else None
        ten = (e.tension_k, self.normals, cohesion_coef(self.h)) if e.tension_k is not None else None
        adh = (e.adhesion_accel,) if e.adhesion_accel is not None else None
        fri = (e.friction_rate,) if e.friction_rate is not None else None
        wind = (e.wind_velocity, e.wind_drag) if e.wind_velocity is not None else None
        att = (e.attractor_point, e.attractor_k, e.attractor_soft) if e.attractor_point is not None else None
        return vis, ten, adh, fri, wind, att

    def forces(self) -> None:
        g = self.grid
        grad_coef = spiky_grad_coef(self.h) / self.grad_norm
        if self.normals is not None:  # Akinci normals (Spiky): a pass after the density, only with tension
            K.surface_normals(self.x, self.rho, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, grad_coef, self.mass,
                              self.normals, (self.nbr, self.cnt_in))
        pressure = (self.pr, self.pressure_coef, self.p.artificial_viscosity * self.c * self.h)
        correction = None
        if self.lcorr is not None:
            K.gradient_correction(self.x, self.nbr, self.cnt_in, self.inv_rho, self.rho, self.rho0, self.h, grad_coef,
                                  self.mass, 0.9, self.p.correction_full, self.d, self.nrm, self.wall_t, self.inv_dr,
                                  self.p.correction_wall_fade, self.lcorr)
            correction = (self.lcorr,)
        K.forces(self.x, self.v, self.rho, self.d, self.nrm, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, self.mass,
                 self.rho0, self.wall_terms, self.gravity, self.acc, pressure, *self.effect_args(), (self.nbr, self.cnt_in), self.inv_rho, correction,
                 self.wall_t if self.p.wall_gradient else None,
                 (self.fix_press,) if self.mirrored_wall else None, self._spline_arg)

    def viscous_dt(self) -> float:
        return viscous_coefficient(self.h / self.l0) * self.l0 ** 2 / self.nu if self.nu > 0 else math.inf

    def stable_dt(self, dt_max: float) -> float:
        v2, a2 = K.max_speed2_accel2(self.v, self.acc)
        # a moving wall must not outrun the fluid's step either (it would tunnel through particles)
        v_max = max(math.sqrt(v2), self.wall_speed(self.t), self.wall_speed(self.t + dt_max))
        return stable_dt(l0=self.l0, h=self.h, v_max=v_max, a_max=math.sqrt(a2), cfl=self.p.cfl,
                         sound_speed=self.c, dt_viscous=self.viscous_dt(), dt_max=min(dt_max, self.effects.dt_limit))

    def step(self, t_end: float) -> float:
        """One step towards t_end (never past it); returns dt."""
        self.sort_and_density()
        self.forces()
        dt = step_to(self.t, t_end, self.p.time_step or self.stable_dt(t_end - self.t))
        t_new = t_end if dt >= t_end - self.t else self.t + dt
        self._pose_bodies(t_new)  # the push-out keeps the fluid out of the walls where they are at the step's end
        K.integrate(self.x, self.v, self.acc, dt, self.wall_terms, self.p.r_rep * self.l0, 0.5 * self.l0,
                    wall_move_limit(self.p.r_rep) * self.l0, self.travel, None if self.bodies else self.d)
        self.t = t_new
        self.steps += 1
        return dt

    def density_ratio(self, p: np.ndarray) -> np.ndarray:
        """rho / rho0 at pressure p: eq. 5 (linear) or Tait."""
        if self.eos == K.EOS_LINEAR:
            return 1.0 + p / (self.rho0 * self.stiffness)
        return (1.0 + p / self.stiffness) ** (1.0 / 7.0)

    def _resized(self) -> None:
        self._scratch.clear()
        self._alloc()

    def frame(self) -> ParticleFrame:
        """The current state with fresh density and pressure. Sorts the state and rebuilds the list, so
        that a run resumed from a checkpoint written after this (load_state: no list yet) builds the
        same list from the same sorted state and goes on bitwise as the uninterrupted run."""
        self.sort_and_density(rebuild=True)
        return ParticleFrame(x=self.x.copy(), v=self.v.copy(), rho=self.rho.copy(), p=self.pr.copy(), id=self.id.copy())

    def state(self) -> dict:
        return {"x": self.x, "v": self.v, "id": self.id, "t": np.float64(self.t), "steps": np.int64(self.steps),
                "left_domain": np.int64(self.left_domain), **self.flow_state()}

    def load_state(self, s: Mapping) -> None:
        self.x = np.ascontiguousarray(s["x"], np.float64)
        self.v = np.ascontiguousarray(s["v"], np.float64)
        self.id = np.ascontiguousarray(s["id"], np.int32)
        self.t = float(s["t"])
        self.steps = int(s["steps"])
        self.left_domain = int(s["left_domain"])
        self._pose_bodies(self.t)
        self.load_flow_state(s)
        self._scratch.clear()
        self._alloc()


def conservative_walls(params: SPHParams) -> None:
    if params.wall_gradient or params.gradient_correction or params.wall_pressure == "mirrored":
        raise StageError("simulate.sph: moving walls need the conservative wall pressure: leave wall_pressure, "
                         "gradient_correction and wall_gradient at their defaults")


class SPHSimulate(Stage):
    kind = "simulate"
    name = "sph"
    version = "4"
    Params = SPHParams
    inputs = ("sdf",)
    reads = ("scene.units", "scene.domain", "scene.frames.count", "scene.frames.fps", "fluid", "effects")
    estimate_reads = ("walls",)  # check: walls[].motion
    extends = "scene.frames.count"  # a longer shot continues from the cached shorter run's last frame
    warm_up_run = True  # numba: a study compiles the kernels on a short run first (pipeline.study)
    outputs = ("particles",)
    default = True
    description = "weakly compressible SPH with distance-function walls (Harada et al. 2007), numba"

    def frame_count(self, ctx: Context, params: Params, inputs: Mapping[str, Artifact]) -> int | None:
        return ctx.scene["scene"].frames.count

    def external_files(self, ctx: Context, params: Params) -> list:
        return emitter_files(ctx)  # the layers a USD mesh emitter composes

    def estimate(self, ctx: Context, params: Params) -> dict | None:
        return simulate_estimate(ctx, params.cfl, 10.0, params.support)

    def check(self, ctx: Context, params: SPHParams) -> None:
        check_emitters(ctx, "simulate.sph")
        if moving_wall(ctx) is not None:
            conservative_walls(params)

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: SPHParams) -> None:
        set_threads(params.threads or getattr(ctx, "threads", None))
        setup = prepare(ctx, inputs, "simulate.sph", moving_walls=True)
        if setup.bodies:  # animated in a USD file (walls[].motion was refused before anything ran)
            conservative_walls(params)
        h = params.support * setup.spacing
        effects = compile_effects(setup.effects, meters_per_unit=setup.meters_per_unit, rho0=setup.density,
                                  l0=setup.spacing, h=h, table_samples=params.table_samples)
        # the default sound speed is 10 x the expected speed, wind and an attractor's included (an attractor left it
        # at falling's 44 m/s while it pulled at 1e3 m/s: the tank's water compressed 280-fold), and a fluid's
        # landing where it starts over a drop
        v_ref = setup.v_land + effects_speed(effects, scene_corners(setup))
        solver = SPHSolver(setup.x, setup.v, np.arange(len(setup.x), dtype=np.int32), setup.sdf, spacing=setup.spacing,
                           rho0=setup.density, params=params, gravity=setup.gravity, v_ref=v_ref,
                           domain=setup.domain, effects=effects, bodies=setup.bodies)
        drive(ctx, solver, setup, solver_name="sph", checkpoint_every=params.checkpoint_every)
