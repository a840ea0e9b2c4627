"""simulate.mps: moving particle semi-implicit (Koshizuka and Oka 1996) with distance-function walls.

``MPSSolver`` holds the state and steps it (used by the stage, the tests and the benchmark);
``MPSSimulate`` is the stage; the set-up and the frame loop shared with SPH are in driver.py, so the
particle cache, checkpoints, statistics and USD layer are identical in form.

One step (PHYSICS.md "MPS"): u* = u + dt (nu <lap u> + g), x* = x + dt u*; collision of close pairs;
n* at x* (fluid + wall maps); free surface n* < beta n0 -> p = 0; the pressure Poisson equation
-<lap p> + (alpha rho / dt^2) p = gamma (rho / dt^2) (n* - n0) / n0 - (1 - gamma) (rho / dt) <div u*>
whose rows also count the p_min gradient's repulsion for the pressure's change from the last step
(mps_kernels.build_poisson), by Jacobi-preconditioned CG (numba CSR, warm-started with the last
pressure); p < 0 -> 0;
u = u* - (dt / rho) <grad p> with the p_min form and the corrective matrix (Khayyer and Gotoh 2011:
exact for a linear pressure on any arrangement; without it the tank at rest settled into a packing
whose gradient tensor has zz part 1.09 and the pressure 6-9 % below rho g h); x = x* + dt (u - u*);
eq. 16 projection out of the walls.

Source term: 'mixed' (default, Tanaka and Masunaga 2010, gamma 0.01) or the 1996 density-invariance
source alone ('density', gamma 0.2); the density source alone left a tank at rest boiling (max speed
0.3-0.5 m/s after 1 s, bottom pressure 2-3 x rho g h), the mixed one settles. gamma 0.03 settled too,
but the density term's pull on the near-surface layers (n/n0 there is 0.99-1.01 at rest) left the
pressure 3-7 % below rho g h at 8 layers deep after 1.3 s, 1.5 % with 0.01; the dam break front and
the mean n/n0 (0.998 at 2 s) are the same with either.

Walls: MPSWallMaps (walls/mps.py), the wall sums of every wall within re on a grid, calibrated to
the flat-wall lattice tables; no wall particles. A moving rigid wall has its own map, baked once in its
rest frame and sampled through its pose (walls/mps.MPSWalls); its wall particles move with it (viscosity,
divergence and the eq. 16 projection take its velocity) and the step is limited by its speed.

At rest (issue 17; session 32, bench_rest's tank): calm for 0.2 s (mean 0.002-0.004 m/s), then motion at the
particle scale (at 0.3 s 85 % of the kinetic energy below 2 l0) grows in the bulk, e-folding in about 0.07 s,
to 0.033 m/s by 0.4 s, and decays slowly after (0.022 at 1.5 s). It scales with gravity as a Froude-scaled flow
(g / 4: onset at 0.4-0.5 s, 0.017 m/s), as the p_min gradient's repulsion does (its stiffness is (p_i - p_min)
/ rho l0^2 ~ 2 g / l0). Unchanged by: dt (cfl 0.1), CG to 1e-9, no collision, beta 0.95, re_laplacian 2.1, gamma
0.001 or 0.05, compressibility 0 or 5e-9, r_rep 0.3, the wall maps' edge excess of n removed, the start made an
exact balance (the gradient's hydrostatic residual on the lattice subtracted: +0.255 g in the layer under the
p = 0 surface, 0.12 g out of vertical edges), particle shifting (Lind et al. 2012, 0.01-0.05 l0^2 (d / n0)
sum (x_j - x_i) w / r^2 a step in the bulk). The plain gradient (p_j - p_i, corrected) ran away (mean 0.57 m/s
at 0.2 s). p_min taken over p_j - rho g . (x_j - x_i) (no hydrostatic stiffness): the jump gone (0.014 m/s at 1 s
against 0.026) but slow growth and single particles at 0.2-0.4 m/s (test_mps_pressure_output fails), not kept.
Session 33: the onset comes with the free-surface flag flickering (4 top-corner particles leave it at 0.17 s;
11,600 flips by 0.45 s, down to layer 13), but it is a symptom: keeping the bulk interior (the flag only where the
neighbourhood, walls included, is lopsided: l0 (d / n0) |sum (x_j - x_i) w / r^2 + G| > 0.1-0.2, 0 in the bulk
and 0.09-0.11 in edges and corners on the lattice, 0.5 in the top layer) or a hysteresis (off again only above
n0) left the run as it was (0.022 m/s at 1.5 s). Worse: no corrective matrix (0.097 at 1.5 s), SPH's symmetric
pair form p_i + p_j (the walls' first-moment error in edges times p_i: 1.25 g out of vertical edges 10 layers
deep; 0.05 m/s), the repulsion made pairwise symmetric ((p_j - p_i) + (k_i + k_j) / 2, k = p - p_min: 0.075 m/s).

Impacts (issue 17, session 34). The p_min gradient is the difference form plus a repulsion (p_i - p_min) m_i,
m_i the first moment of i's neighbourhood, walls included (about 0 when it is full). The Laplacian models the
difference form only, so where the neighbourhood is lopsided (a thin front hitting a wall, a cluster beside the
free surface) the solve asked for several times the pressure that stops a particle, and the repulsion threw it
out: the stability suite's dam break (and its kilometre copy) at 2.9 x the ballistic bound; the thin plate's
splash blew up in the tank's top corners (168 m/s). Each row now counts the repulsion's effect on the particle's
own divergence, (d / n0)^2 |m_i|^2, for the pressure's change from the last step: dam break 1.38 x, kilometres
1.40 x, thin plate 0.65 x (short suite); in the long suite no case above 1.14 x but the step 10-20 x the stable
one, which the guard stops (the thin plate 2.03 x before, the overlapping emitters 2.60 x). Sessions 16-17 tried
the walls' part alone (|G_i|^2): the paddle's face layer then fell to 0.88 U and the long thin plate reached 5.4 x. Counted for the whole pressure (p_min lagged on the
right), the rows lowered the steady pressure wherever m_i is the wall maps' error: 271 % density error in the 20
degree wedge's apex. Cost at rest (bench_rest's tank): the top two layers churn more (99th percentile 0.091 m/s
at 1.5 s against 0.053; mean 0.0256 against 0.021), the bulk as before, the pressure 2-8 layers down -2.0 % from
rho g h against +6.8 %.

At rest, session 35: one step linearised about a small resting tank (benchmarks/bench_rest_modes.py) amplifies 21
non-oscillating modes faster than 0.5 sqrt(g / l0), the fastest at 17.7 / s, vertical, in the top two layers (11.8 /
s with g / 4, 8.9 / s without gravity); WCSPH, calm, amplifies as fast, so this is not what keeps MPS moving.
Restarted at rest after 3 s (every velocity zeroed) the tank is back at 0.015 m/s within 0.1 s: the step keeps the
motion up at the disordered packing it reaches. That packing is denser at the same number density (the interior's n
/ n0 within 0.1 % of 1 while the surface sinks 4.3 mm by 1.5 s): n0 is the cubic lattice's 14.42 and FCC of the same
volume per particle gives 14.31. From that state with every velocity zeroed, one step accelerates the particles by
0.30 g on average, mostly the pressure the number-density source makes of the packing's per-particle n (about 4-5
rho g l0 above hydrostatic on average; gamma 0.001: 0.155 g, but the tank only 15 % calmer). Zeroing every velocity
after each step for 3,000 steps leaves 0.03 g (0.12 g in the top two layers) and the released tank is back at
0.012-0.015 m/s: there is no still state near the packings MPS reaches, most of all under the free surface. But the
surface is not the main source: with the top layer held fixed the rest moves at 0.018 m/s at 1.5 s (0.019 with the
side-wall band held), and without gravity the whole fluid only drifts up off the floor (2.6 mm/s, no growth). The
bulk's forces are nearly conservative (|K - K^T| / |K + K^T| of d v_new / d x: 0.034), and the compaction is not the
energy source either: with re_number_density 3.1 (the three lattices' n within 0.3 %) the tank is about as restless
(0.0232 m/s over 1-1.5 s, against 0.0259) while its centre of mass rises 0.78 mm. Per term of the step (over 1-1.5
s, per kg): gravity's g dt adds 27.3 mJ/kg net of the potential energy and the pressure removes 30.5, cancelling to
10 % of flows 70 times the tank's kinetic energy (viscosity 0.004, the walls' projection 0.33). The Laplacian is not
the divergence of the corrected gradient, so a converged solve still leaves a few % of g dt each step. Session 36
(benchmarks/rest_log.md): a projection closer to exact (defect correction, 2-8 passes) did not calm the tank, nor
did six other levers; the motion starts in the top corners and is kept up by the p_min repulsion under a
hydrostatic pressure on a disordered packing.

Stacked pairs (session 37). In a V's apex the eq. 16 projection moves every particle closer than r_rep to both
walls onto the line r_rep from both, so mirror-image particles land on one point (mps_kernels.part_stacked): such
pairs stayed 0-0.005 l0 apart with n / n0 1.5-1.7 and threw their neighbours faster than the ballistic bound
allows. Each step now parts pairs closer than R_MIN re after the projection. The fastest particle over every step,
in 35 runs of the stability suite's V troughs (10-30 degrees, the apex on and off the SDF's nodes, 5-30 frames):
7 runs above 2 x the bound and up to 9.5 x before, 1.64 x at most after.

Effects: gravity and viscosity (with its no-slip wall term) only; a scene declaring any other effect
is rejected with a StageError that names them.

The reported density is rho0 n_i / n0 (the number density ratio), the support h = 2 l0 and the mass
the SPH lattice mass, so surface extraction treats MPS particles exactly like SPH particles. The reported
pressure is each particle's mean over the frame's steps, weighted by their length (MPSSolver.frame: one
step's pressure swings from step to step, and a frame of it depended on the frame rate)."""
from __future__ import annotations

import math
from typing import Literal, Mapping

import numpy as np
from pydantic import Field

from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import ParticleFrame
from stages.common.sdf import SDFGrid
from stages.common.sizes import simulate_estimate

from . import mps_kernels as K
from .driver import SolverBase, drive, prepare, set_threads
from .emitters import check_emitters, emitter_files
from .kernels import lattice_mass
from .walls.mps import MPSWallMaps, build_tables, lattice_constants, make_mps_walls
from .neighbours import CellGrid, reorder
from .timestep import REFERENCE_SPACING, stable_dt, step_to

DIM = 3


class MPSParams(Params):
    re_number_density: float = Field(2.1, ge=1.5, le=4.0, description="influence radius re of the number "
                                     "density and the gradient, in units of l0")
    re_laplacian: float = Field(3.1, ge=1.5, le=4.0, description="influence radius re of the Laplacian (viscosity "
                                "and the pressure Poisson equation), in units of l0")
    beta: float = Field(0.97, gt=0.5, lt=1.0, description="free surface where n* < beta n0 (p = 0 there)")
    source: Literal["mixed", "density"] = Field("mixed", description="Poisson source: 'density' gamma (rho / dt^2) "
                                                "(n* - n0) / n0 (the 1996 form); 'mixed' adds (1 - gamma) (rho / dt) "
                                                "<div u*> (Tanaka and Masunaga 2010: much smoother pressure)")
    relaxation: float | None = Field(None, gt=0, le=1.0, description="gamma, the weight of the number-density source; "
                                     "default 0.2 for 'density', 0.01 for 'mixed'")
    compressibility: float = Field(0.45e-9, ge=0, description="alpha, 1/Pa: (alpha rho / dt^2) p on the diagonal "
                                   "(conditioning; keeps clusters with no free-surface particle solvable), at spacings "
                                   "up to 2 cm; x (2 cm / spacing) above, so its weight against the Laplacian, "
                                   "alpha rho l0^2 / dt^2, stays a 2 cm scene's under Froude scaling")
    gradient_correction: float = Field(0.5, ge=0, le=1.0, description="the corrective matrix on the pressure "
                                       "gradient (Khayyer and Gotoh 2011) where its tensor's determinant exceeds this "
                                       "(1 on the cubic lattice); 0 turns it off (the plain 1996 gradient)")
    collision_distance: float = Field(0.5, ge=0, le=1.0, description="pairs closer than this (in l0) collide")
    restitution: float = Field(0.2, ge=0, le=1.0, description="restitution of the close-pair collision")
    cfl: float = Field(0.2, gt=0, le=0.3, description="dt <= cfl l0 / max(v_max, v_ref)")
    time_step: float | None = Field(None, gt=0, description="a fixed time step, s, instead of the adaptive one "
                                    "(stability studies: a step above the stable one stops the run with a blow-up error); a frame's last two "
                                    "steps share what is left of it when that is under 1.5 steps (frames land on their "
                                    "times, no sliver step)")
    r_rep: float = Field(0.5, gt=0, le=1.0, description="eq. 16 wall projection distance, in units of l0")
    cg_tolerance: float = Field(1e-6, gt=0, lt=1, description="CG stops at |r| <= tol |b|")
    cg_max_iterations: int = Field(2000, ge=1, description="CG iteration cap per step")
    skin: float = Field(0.5, ge=0.2, le=2.0, description="neighbour-list margin beyond the largest re, in l0 "
                        "(must exceed the relative motion of a pair within one step, 2 cfl l0)")
    checkpoint_every: int = Field(10, ge=1, description="write a checkpoint every this many frames")
    threads: int | None = Field(None, ge=1, description="numba threads (fixed count = reproducible results)")
    table_samples: int = Field(256, ge=16, description="samples of the wall tables over [0, max re]")


class MPSSolver(SolverBase):
    """State (x, v, id, p in cell order) plus the per-step kernels; buffers are reused and grow only
    when the particle or pair count does."""

    stiffness_settings = "lower compressibility (default 4.5e-10 1/Pa) or leave relaxation out"
    carried = ("pr", "p_sum", "p_time")  # p_sum, p_time: the frame's pressure (frame())

    def __init__(self, x, v, ids, sdf: SDFGrid, *, spacing: float, rho0: float, params: MPSParams,
                 gravity=(0.0, 0.0, 0.0), mu: float | None = None, wall_viscosity: bool = True,
                 v_ref: float = 1.0, domain=None, bodies=()):
        """``bodies``: the moving rigid walls, each (SDFGrid baked in its rest frame, motion with ``pose(t)``,
        ``velocity(t)`` and ``pivot`` as stages.common.motion.RigidMotion), all in SI; ``sdf`` holds the static
        walls only."""
        self.p = params
        self.l0 = float(spacing)
        self.rho0 = float(rho0)
        self.h = 2.0 * self.l0  # reported support for the surface (see module docstring)
        self.mass = lattice_mass(self.rho0, self.l0, self.h)
        self.c = 0.0
        self.re_n = params.re_number_density * self.l0
        self.re_l = params.re_laplacian * self.l0
        self.n0, _ = lattice_constants(self.l0, self.re_n)
        self.n0_l, self.lam = lattice_constants(self.l0, self.re_l)
        self.lap_coef = 2.0 * DIM / (self.lam * self.n0_l)
        self.grad_coef = DIM / self.n0
        self.tables = build_tables(self.l0, self.re_n, self.re_l, params.table_samples)
        self.walls = MPSWallMaps(sdf, self.l0, self.re_n, self.re_l, self.tables)
        self.set_motions(bodies)
        self.wall_terms = make_mps_walls(sdf, self.walls, [(b, MPSWallMaps(b, self.l0, self.re_n, self.re_l, self.tables))
                                                           for b, _ in bodies])
        self._pose_bodies(0.0)
        self.gravity = np.asarray(gravity, np.float64)
        self.g_dt = np.zeros(3)
        self.mu = float(mu) if mu is not None else None
        self.wall_viscosity = bool(wall_viscosity)
        self.v_ref = float(max(v_ref, 1e-3))
        self.sdf = sdf
        self.sdf_inv = 1.0 / sdf.spacing
        lo, hi = (sdf.origin, sdf.upper) if domain is None else domain
        self.domain = (np.asarray(lo, float), np.asarray(hi, float))
        self.list_radius = max(self.re_n, self.re_l) + params.skin * self.l0
        self.grid = CellGrid(sdf.origin, sdf.upper, self.list_radius)
        self.x = np.array(x, np.float64)
        self.v = np.array(v, np.float64)
        self.id = np.array(ids, np.int32)
        self.pr = np.zeros(len(self.x))
        self.p_sum = np.zeros(len(self.x))  # sum of p dt since the last frame()
        self.p_time = np.zeros(len(self.x))  # and of dt
        self.t = 0.0
        self.steps = 0
        self.left_domain = 0
        self.cg_iterations = 0  # total over all steps
        self.last_cg_iterations = 0
        self._scratch: dict = {}
        self._alloc()

    def _alloc(self) -> None:
        n = len(self.x)
        self.d = np.zeros(n)
        self.nrm = np.zeros((n, 3))
        self.n = np.zeros(n)
        self.div = np.zeros(n)
        self.moment2 = np.zeros(n)  # (d / n0)^2 |first moment|^2 (divergence(); the repulsion rows)
        self.xs = np.zeros((n, 3))
        self.vs = np.zeros((n, 3))
        self.xb = np.zeros((n, 3))
        self.vb = np.zeros((n, 3))
        self.counts = np.zeros(n, np.int64)
        self.offsets = np.zeros(n + 1, np.int64)
        self.nbr = getattr(self, "nbr", np.zeros(0, np.int32))
        self.dirichlet = np.zeros(n, np.bool_)
        self.row_counts = np.zeros(n, np.int64)
        self.row_off = np.zeros(n + 1, np.int64)
        self.cols = getattr(self, "cols", np.zeros(0, np.int32))
        self.vals = getattr(self, "vals", np.zeros(0))
        self.diag = np.zeros(n)
        self.b = np.zeros(n)
        self.cg = [np.zeros(n) for _ in range(4)]  # r, z, search direction, A p
        self.partial = np.zeros(K.CG_BLOCKS)
        self.partial2 = np.zeros((K.CG_BLOCKS, 2))

    # -- one step -----------------------------------------------------------------------------
    def sort_and_neighbours(self) -> None:
        """Put the state in cell order and build the neighbour list at the current positions."""
        order = self.grid.sort(self.x)
        self.x, self.v, self.id, self.pr, self.p_sum, self.p_time = reorder(
            [self.x, self.v, self.id, self.pr, self.p_sum, self.p_time], order, self._scratch)
        g = self.grid
        args = (self.x, g.starts, g.lo, 1.0 / g.cell, g.dims, self.list_radius)
        K.count_neighbours(*args, self.counts)
        total = K.prefix_sum(self.counts, self.offsets)
        if total > len(self.nbr):
            self.nbr = np.zeros(int(total * 1.25) + 16, np.int32)
        K.fill_neighbours(*args, self.offsets, self.nbr)

    def _walls(self, x) -> None:
        K.wall_distance(x, self.wall_terms, self.d, self.nrm)

    def number_density(self, x) -> None:
        self._walls(x)
        K.number_density(x, self.offsets, self.nbr, self.re_n, self.d, self.wall_terms, self.n)

    def stable_dt(self, dt_max: float) -> float:
        v = math.sqrt(K.max_speed2(self.v))
        # a moving wall must not outrun the fluid's step either (it would tunnel through particles)
        v_max = max(v, self.v_ref, self.wall_speed(self.t), self.wall_speed(self.t + dt_max))
        return stable_dt(l0=self.l0, h=self.l0, v_max=v_max, a_max=0.0, cfl=self.p.cfl,
                         sound_speed=None, dt_viscous=self.viscous_dt(), dt_max=dt_max)

    def viscous_dt(self) -> float:
        # 0.125 l0^2 / nu: a quarter to an eighth of the MPS Laplacian's own limit on the lattice (0.49-1.0 l0^2 / nu
        # at re 2.1-3.1 l0, by timestep.viscous_coefficient's Fourier sum with MPS's weight)
        return 0.125 * self.l0 ** 2 * self.rho0 / self.mu if self.mu else math.inf

    def solve_pressure(self, dt: float) -> int:
        rho = self.rho0
        K.mark_free_surface(self.n, self.p.beta * self.n0, self.dirichlet)
        mixed = self.p.source == "mixed"
        gamma = self.p.relaxation or (0.01 if mixed else 0.2)
        src = gamma * rho / dt ** 2
        div_coef = -(1.0 - gamma) * rho / dt if mixed else 0.0
        # the divergence pass also gives each row's first moment (the repulsion rows), so it runs for either source
        np.multiply(self.gravity, dt, out=self.g_dt)
        K.divergence(self.xs, self.vs, self.offsets, self.nbr, self.re_n, self.grad_coef, self.d, self.wall_terms,
                     self.g_dt, self.div, self.moment2)
        # Froude-scaled above the reference spacing: at water's alpha a kilometre-wide dam break kept 0.77 of
        # its energy against the metre one's 0.96, the term's weight grown 10,000 x (the fronts agreed)
        alpha = self.p.compressibility * min(1.0, REFERENCE_SPACING / self.l0)
        diag_extra = alpha * rho / dt ** 2
        while True:
            # self.pr still holds the last step's pressure (the warm start): the repulsion rows' reference
            nnz = K.build_poisson(self.xs, self.offsets, self.nbr, self.re_l, self.lap_coef, self.dirichlet, self.n,
                                  self.n0, src, self.div, div_coef, diag_extra, self.moment2, self.pr, self.d,
                                  self.wall_terms, self.gravity, rho, self.row_counts, self.row_off, self.cols, self.vals,
                                  self.diag, self.b)
            if nnz >= 0:
                break
            need = int(self.row_off[-1] * 1.25) + 16
            self.cols = np.zeros(need, np.int32)
            self.vals = np.zeros(need)
        r, z, pd, q = self.cg
        it = K.pcg(self.row_off, self.cols, self.vals, self.diag, self.b, self.pr, r, z, pd, q, self.partial,
                   self.partial2, self.p.cg_tolerance, self.p.cg_max_iterations)
        K.clamp_negative(self.pr)
        return it

    def unconverged(self) -> str | None:
        cap = self.p.cg_max_iterations
        if self.last_cg_iterations < cap:
            return None
        return (f"the pressure solve stopped at cg_max_iterations ({cap}) short of cg_tolerance "
                f"({self.p.cg_tolerance:g}): raise cg_max_iterations")

    def step(self, t_end: float) -> float:
        """One step towards t_end (never past it); returns dt."""
        self.sort_and_neighbours()
        dt = step_to(self.t, t_end, self.p.time_step or self.stable_dt(t_end - self.t))
        t_new = t_end if dt >= t_end - self.t else self.t + dt
        if self.mu is not None:  # the moving walls where they are at the step's start
            self._walls(self.x)
            K.predict_viscosity(self.x, self.v, self.offsets, self.nbr, self.re_l, self.lap_coef, self.mu / self.rho0,
                                self.d, self.wall_terms, self.wall_viscosity, self.gravity, dt, self.xs, self.vs)
        else:
            K.predict(self.x, self.v, self.gravity, dt, self.xs, self.vs)
        # the predicted positions x* are those at the step's end: so are the walls from here on
        self._pose_bodies(t_new)
        if self.p.collision_distance > 0:
            K.collide(self.xs, self.vs, self.offsets, self.nbr, self.p.collision_distance * self.l0,
                      self.p.restitution, dt, self.xb, self.vb)
            self.xs, self.xb = self.xb, self.xs
            self.vs, self.vb = self.vb, self.vs
        self.number_density(self.xs)
        self.last_cg_iterations = self.solve_pressure(dt)
        self.cg_iterations += self.last_cg_iterations
        # the corrected state goes into the start-of-step buffers (x, v are no longer needed)
        K.correct(self.xs, self.vs, self.pr, self.offsets, self.nbr, self.re_n, self.grad_coef, self.d, self.wall_terms,
                  self.gravity, self.rho0, self.dirichlet, self.p.gradient_correction, dt, self.x, self.v)
        K.project_out_of_walls(self.x, self.v, self.wall_terms, self.p.r_rep * self.l0, 0.5 * self.l0)
        K.part_stacked(self.x, self.v, self.id, self.offsets, self.nbr, K.R_MIN * self.re_n, self.wall_terms,
                       self.p.r_rep * self.l0, 0.5 * self.l0, self.xb)  # xb is free until the next step's collision
        self.x, self.xb = self.xb, self.x
        self.p_sum += dt * self.pr
        self.p_time += dt
        self.t = t_new
        self.steps += 1
        return dt

    def _resized(self) -> None:
        self._scratch.clear()
        self._alloc()

    def frame(self) -> ParticleFrame:
        """The current state; density rho0 n / n0 at the current positions; the pressure is each particle's
        mean over the steps since the last frame (weighted by their length; the last solved pressure where
        there was no step), and the mean starts again. One step's pressure is no frame's: at rest it goes
        10-40 % up and down from step to step (anti-correlated, lag-one autocorrelation -0.4), so frames
        spaced by an even number of equal steps caught the same phase every time (1.1-1.5 rho g h), and a
        frame's end shortened the step the frame was written after and shifted its pressure (0.6-0.9, or
        1.5 after a sliver), where the mean over every step is 0.98-1.0. The mean is the pressure the motion
        from the last frame to this one felt: dt-weighted, a step shortened to land on the frame's time
        counts for its length. (Sorts the state, as a step would.)"""
        self.sort_and_neighbours()
        self.number_density(self.x)
        rho = self.rho0 * self.n / self.n0
        stepped = self.p_time > 0.0
        p = np.where(stepped, self.p_sum / np.where(stepped, self.p_time, 1.0), self.pr)
        self.p_sum[:] = 0.0
        self.p_time[:] = 0.0
        return ParticleFrame(x=self.x.copy(), v=self.v.copy(), rho=rho, p=p, id=self.id.copy())

    def state(self) -> dict:
        return {"x": self.x, "v": self.v, "id": self.id, "p": self.pr, "p_sum": self.p_sum, "p_time": self.p_time,
                "t": np.float64(self.t),
                "steps": np.int64(self.steps), "left_domain": np.int64(self.left_domain),
                "cg_iterations": np.int64(self.cg_iterations), **self.flow_state()}

    def load_state(self, s: Mapping) -> None:
        self.x = np.ascontiguousarray(s["x"], np.float64)
        self.v = np.ascontiguousarray(s["v"], np.float64)
        self.id = np.ascontiguousarray(s["id"], np.int32)
        self.pr = np.ascontiguousarray(s["p"], np.float64)
        # a checkpoint from before the frame-mean pressure: saved right after a frame, so nothing summed yet
        self.p_sum = np.ascontiguousarray(s["p_sum"], np.float64) if "p_sum" in s else np.zeros(len(self.pr))
        self.p_time = np.ascontiguousarray(s["p_time"], np.float64) if "p_time" in s else np.zeros(len(self.pr))
        self.t = float(s["t"])
        self.steps = int(s["steps"])
        self.left_domain = int(s["left_domain"])
        self._pose_bodies(self.t)
        self.load_flow_state(s)
        self.cg_iterations = int(s["cg_iterations"])
        self._scratch.clear()
        self._alloc()


SUPPORTED_EFFECTS = ("gravity", "viscosity")


def check_effects(effects) -> None:
    """StageError naming the scene's effects that MPS does not implement."""
    other = [e for e in effects.enabled() if e not in SUPPORTED_EFFECTS]
    if other:
        raise StageError(f"simulate.mps: {'effects' if len(other) > 1 else 'effect'} {', '.join(other)} "
                         f"{'are' if len(other) > 1 else 'is'} not supported by MPS (it supports "
                         f"{', '.join(SUPPORTED_EFFECTS)}); remove them from 'effects' or use simulate: {{use: sph}}")


class MPSSimulate(Stage):
    kind = "simulate"
    name = "mps"
    # 6: pairs the wall projection stacks are parted; 5: the PPE counts the p_min repulsion (impacts); 4: a frame's
    # pressure is its mean over the frame's steps
    version = "6"
    Params = MPSParams
    inputs = ("sdf",)
    reads = ("scene.units", "scene.domain", "scene.frames.count", "scene.frames.fps", "fluid", "effects")
    extends = "scene.frames.count"  # a longer shot continues from the cached shorter run's last frame
    warm_up_run = True  # numba: a study compiles the kernels on a short run first (pipeline.study)
    outputs = ("particles",)
    default = False
    description = "moving particle semi-implicit (Koshizuka and Oka 1996) with distance-function walls, numba CG"

    def frame_count(self, ctx: Context, params: Params, inputs: Mapping[str, Artifact]) -> int | None:
        return ctx.scene["scene"].frames.count

    def external_files(self, ctx: Context, params: Params) -> list:
        return emitter_files(ctx)  # the layers a USD mesh emitter composes

    def check(self, ctx: Context, params: Params) -> None:
        check_emitters(ctx, "simulate.mps")
        check_effects(ctx.scene["effects"])

    def estimate(self, ctx: Context, params: Params) -> dict | None:
        return simulate_estimate(ctx, params.cfl, None, 2.0)

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: MPSParams) -> None:
        set_threads(params.threads or getattr(ctx, "threads", None))
        check_effects(ctx.scene["effects"])
        setup = prepare(ctx, inputs, "simulate.mps", moving_walls=True)
        visc = setup.effects.viscosity
        solver = MPSSolver(setup.x, setup.v, np.arange(len(setup.x), dtype=np.int32), setup.sdf, spacing=setup.spacing,
                           rho0=setup.density, params=params, gravity=setup.gravity,
                           mu=visc.mu if visc is not None else None,
                           wall_viscosity=bool(visc.wall) if visc is not None else False, v_ref=setup.v_ref,
                           domain=setup.domain, bodies=setup.bodies)
        drive(ctx, solver, setup, solver_name="mps", checkpoint_every=params.checkpoint_every)
        ctx.log.info("mps: %d steps, %.1f CG iterations per step", solver.steps,
                     solver.cg_iterations / max(solver.steps, 1))
