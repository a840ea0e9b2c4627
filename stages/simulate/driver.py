"""What every simulate implementation shares around its solver: the scene set-up (emit, drop particles
inside walls, gravity in scene units, reference speed) and the frame loop (advance, drop escaped
particles, write frames, checkpoints, statistics, meta.json and the USD points layer).

A solver is any object with the ``Solver`` members below; SPH, DFSPH and MPS plug in the same way, so
their caches, checkpoints and statistics are identical in form.

Solvers work in SI units: the equations mix lengths with densities in kg/m^3, viscosities in Pa s and
gravity in m/s^2, so a scene in centimetres (meters_per_unit 0.01) is converted to metres here
(positions, velocities, the SDF, the spacing) and the frames back to scene units when written."""
from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Protocol

import numba as nb
import numpy as np

from pipeline.errors import PipelineError
from pipeline.stage import Artifact, Context, StageError
from stages.common.formats import ParticleFrame, ParticleMeta, local_origin
from stages.common.motion import reach, top_wall_speed, wall_speed
from stages.common.sdf import SDFGrid, body_walls, load_bodies, posed_field
from stages.common.usd_points import write_points_layer
from stages.common.wall_hints import box_text, no_fluid_hint, read_wall_boxes, units_hint

from .effects import WATER_GAMMA
from .emitters import drop_inside_walls, drop_overlaps, emit
from .inflow import Inflow, Sink, from_config, in_sinks, inflow_blocked
from .kernels import count_blown
from .walls.maps import set_pose
from .output import iter_frames, latest_checkpoint, restore_frames, save_checkpoint, write_frame


class Solver(Protocol):
    x: np.ndarray  # (N, 3) positions
    d: np.ndarray  # (N,) SDF wall distance of each particle at the last frame()
    l0: float
    rho0: float
    mass: float
    h: float
    c: float  # speed of sound (0 for incompressible solvers)
    t: float
    steps: int
    left_domain: int

    def advance_to(self, t_end: float) -> int: ...
    def density_ratio(self, p: np.ndarray) -> np.ndarray | None:
        """rho / rho0 at pressure p by the solver's equation of state; None for an incompressible solver
        (hydrostatic_start then leaves the positions as emitted)."""
        return None

    def remove_escaped(self) -> int: ...
    def frame(self) -> ParticleFrame: ...
    def state(self) -> dict: ...
    def load_state(self, s: Mapping) -> None: ...



# Blow-up detection (SolverBase.advance_to): no particle of a scene can be faster than its ballistic
# bound (driver.ballistic_speed: the emitters' top speed plus the free fall over the scene's height, plus
# what wind and an attractor can add) unless the solver created energy or pressure concentrated it (Ritter's
# dam-break front runs at 1.41 x sqrt(2 g H)); SPEED_LIMIT times that (100 x the largest specific
# energy the scene can give) is a blow-up, not a splash. (MPS's few spurious impact particles reach 3.2 x in the
# stability suite's dam break and 5.2 x pouring onto the dragon, in runs that otherwise end well; real
# blow-ups reach 50-350 x, so the limit sits between.) Unless the fluid's energy says otherwise: pressure can
# focus energy without bound where a void closes in a sharp concave corner (Rayleigh's collapse; water poured
# into a cone closed at its apex throws one or two particles into the apex at 6-10 x the bound at 1 cm spacing,
# 1.4-3.2 x at 2 cm; DFSPH's and MPS's 0.7 cm runs, 12-14 x, were stopped as blow-ups). So a particle above the
# limit stops the run only if the fluid's energy (kinetic + gravitational) has risen since the frame began by
# more than half the fast particles' kinetic energy: a solver making energy, not pressure moving it
# (Guard.focused). A step below DT_FLOOR x l0 / v_bound
# (a particle at the bound crossing a thousandth of the spacing) means an acceleration of about a million
# g at the default spacing: the adaptive step is collapsing towards zero and the run would never end.
# At a frame's end no particle is deeper than INSIDE_DEPTH x l0 inside a static wall: the eq. 16 projection
# keeps particles r_rep outside every step, so one that deep has gone through (a step far above the stable one
# let MPS particles pass the tank's walls with no speed or step limit noticing).
SPEED_LIMIT = 10.0
DT_FLOOR = 1e-3
SLOW_STEPS = 10.0  # an effect or the viscosity needing steps this many times shorter than the flow's is said
STEP_SPLIT = 2.0  # timestep.step_to may halve a step at a frame's end (no sliver): a limit known before the run
# must stay this far above the floor
INSIDE_DEPTH = 0.25
# A frame whose mean compression (rho / rho0 - 1 where above 1, over its particles) exceeds this is said where the
# run ends: the defaults keep a dam break's worst frame at 0.2-0.4 % (WCSPH's stiffness is set for about 1 % at
# the fastest particle); MPS with compressibility 1e-6 reached 2 % with peaks of 16 %, and nothing was said.
COMPRESSION_LIMIT = 0.01


class BlowUp(FloatingPointError):
    """The solver diverged; ``driver.drive`` turns it into a one-line SimulationDiverged (exit 1)."""

    def __init__(self, what: str, t: float, count: int, cause: str) -> None:
        super().__init__(f"{what} at t = {t:.5g} s ({count} particles); likely cause: {cause}")
        self.what, self.t, self.count, self.cause = what, t, count, cause


class SimulationDiverged(PipelineError):
    """A run stopped by the blow-up detection: one line, exit 1 (a failed run, not a malformed file)."""

    exit_code = 1


def specific_energy(x: np.ndarray, v: np.ndarray, g: np.ndarray) -> float:
    """The sum of 1/2 v^2 - g . x over the particles (J/kg): kinetic + gravitational, from the level x = 0."""
    return float(0.5 * np.einsum("ij,ij->", v, v) - np.sum(x @ g))


def mechanical_energy(solver: "SolverBase", g: np.ndarray, base: float) -> float:
    """The fluid's energy per unit mass (J/kg, summed over particles): 1/2 v^2 + g h, h the height above the
    level where -g . x = ``base``."""
    return specific_energy(solver.x, solver.v, g) - base * len(solver.x)


def flowed_energy(solver: "SolverBase", g: np.ndarray, base: float, since: tuple[float, int] = (0.0, 0)) -> float:
    """What inflows brought minus what sinks and the domain's edge took since ``since`` (an earlier
    ``solver.flowed``), in ``mechanical_energy``'s terms."""
    energy, count = solver.flowed
    return (energy - since[0]) - base * (count - since[1])


@dataclass
class Guard:
    """The blow-up limits of one scene (SI): a speed and a time step floor. With ``gravity`` (and ``base``, -g . x
    at the scene's lowest point), a particle above the speed limit is a blow-up only if the fluid's energy rose
    with it (``focused``); without, always (the strict limit)."""
    v_bound: float  # the ballistic speed bound, m/s
    l0: float
    gravity: np.ndarray | None = None
    base: float = 0.0
    focus_steps: int = 0  # steps with particles above the limit that the energy showed to be pressure focusing
    focus_peak: tuple = (0.0, 0.0, 0)  # the fastest of them: (speed / v_bound, t, particles above the limit)
    # the fluid's energy and what had flowed in and out (SolverBase.flowed) where the current advance (a frame)
    # began (start_frame)
    _e_ref: float | None = field(default=None, init=False, repr=False)
    _flowed_ref: tuple = field(default=(0.0, 0), init=False, repr=False)

    @classmethod
    def with_energy(cls, v_bound: float, l0: float, gravity: np.ndarray, corners: np.ndarray) -> "Guard":
        """The guard with its energy test, the potential taken from the lowest of the scene box's ``corners``."""
        g = np.asarray(gravity, np.float64)
        return cls(v_bound=v_bound, l0=l0, gravity=g, base=float(np.min(-(corners @ g))))

    @property
    def v_limit(self) -> float:
        return SPEED_LIMIT * self.v_bound

    @property
    def dt_floor(self) -> float:
        return DT_FLOOR * self.l0 / self.v_bound

    def check(self, solver: "SolverBase", dt: float, last_of_frame: bool) -> None:
        if not (dt > 0.0 and math.isfinite(dt)) or (dt < self.dt_floor and not last_of_frame):
            raise BlowUp(f"the time step fell to {dt:.3g} s, below the floor {self.dt_floor:.3g} s", solver.t,
                         len(solver.x), self._cause(solver, dt))
        bad, fast = count_blown(solver.x, solver.v, self.v_limit ** 2)
        if bad:
            raise BlowUp("non-finite positions or velocities", solver.t, bad, self._cause(solver, dt))
        if fast:
            v2 = np.einsum("ij,ij->i", solver.v, solver.v)
            vmax = float(np.sqrt(v2.max()))
            if not self.focused(solver, v2, vmax, fast):
                raise BlowUp(f"speed {vmax:.3g} m/s above {SPEED_LIMIT:g} x the scene's ballistic bound "
                             f"{self.v_bound:.3g} m/s", solver.t, fast, self._cause(solver, dt))
        sdf = getattr(solver, "sdf", None)
        if last_of_frame and sdf is not None:
            # a point outside the grid reads its border: a particle through a wall and out of the grid counts too
            deep = int((sdf.sample(solver.x)[0] < -INSIDE_DEPTH * self.l0).sum())
            if deep:
                raise BlowUp(f"particles more than {INSIDE_DEPTH:g} spacings inside a wall or through it", solver.t,
                             deep, self._cause(solver, dt))

    def start_frame(self, solver: "SolverBase") -> None:
        """The reference for ``focused``: the fluid's energy where an advance to a frame's time begins."""
        if self.gravity is not None:
            self._e_ref, self._flowed_ref = mechanical_energy(solver, self.gravity, self.base), solver.flowed

    def focused(self, solver: "SolverBase", v2: np.ndarray, vmax: float, fast: int) -> bool:
        """Whether the particles above the speed limit are pressure focusing the fluid's energy rather than a
        blow-up: the fluid's energy has not risen since the frame began by more than half their kinetic energy
        (a solver making energy puts it into them; a closing void takes it from the fluid around it). What inflows
        brought and sinks took is booked (SolverBase.flowed); energy given by moving walls, wind or an attractor
        counts as a rise: those scenes are held to the strict limit unless the rest of the fluid lost as much. No
        reference (a check outside an advance) leaves the strict limit."""
        if self.gravity is None or self._e_ref is None:
            return False
        fast_energy = 0.5 * float(v2[v2 > self.v_limit ** 2].sum())
        rise = (mechanical_energy(solver, self.gravity, self.base) - self._e_ref
                - flowed_energy(solver, self.gravity, self.base, self._flowed_ref))
        if rise > 0.5 * fast_energy:
            return False
        self.focus_steps += 1
        ratio = vmax / self.v_bound
        if ratio > self.focus_peak[0]:
            self.focus_peak = (ratio, solver.t, fast)
        return True

    def state(self) -> dict:
        """What a resumed run needs to report the whole shot's focusing (checkpoint entries)."""
        return {"guard_focus_steps": np.int64(self.focus_steps), "guard_focus_peak": np.asarray(self.focus_peak, float)}

    def load_state(self, s: Mapping) -> None:
        if "guard_focus_steps" in s:  # older checkpoints: none
            self.focus_steps = int(s["guard_focus_steps"])
            ratio, t, n = (float(v) for v in s["guard_focus_peak"])
            self.focus_peak = (ratio, t, int(n))

    def _cause(self, solver: "SolverBase", dt: float) -> str:
        """The likeliest parameter to change, from the last step against the scene's scales."""
        c = float(getattr(solver, "c", 0.0) or 0.0)
        advective = self.l0 / self.v_bound  # a particle at the bound crosses one spacing
        if c > 0 and dt > 0.4 * self.l0 / c:
            return (f"the time step ({dt:.3g} s) is above the acoustic limit 0.4 l0 / c = {0.4 * self.l0 / c:.3g} s "
                    f"(speed of sound {c:.3g} m/s): lower the time step or the cfl")
        if dt > 0.5 * advective:
            return (f"the time step ({dt:.3g} s) lets a particle at the bound cross {dt / advective:.2g} spacings: "
                    "lower the time step or the cfl")
        effects = getattr(solver, "effects", None)
        if effects is not None and effects.dt_limit < 10 * self.dt_floor:
            return f"{effects.dt_limit_by} needs steps of {effects.dt_limit:.3g} s: lower it"
        viscous = getattr(solver, "viscous_dt", lambda: math.inf)()  # SolverBase's; inf from other solvers
        if viscous < 10 * self.dt_floor:
            return (f"the viscosity (effects.viscosity.mu) needs steps of {viscous:.3g} s at spacing {self.l0:.3g} m: "
                    "lower it or coarsen the spacing")
        unsolved = getattr(solver, "unconverged", lambda: None)()  # SolverBase's; None from other solvers
        if unsolved:
            return unsolved
        what = f"the stiffness (speed of sound {c:.3g} m/s)" if c > 0 else "the pressure solve"
        return (f"{what} or the spacing ({self.l0:.3g} m) against the walls: particles pushed into each other or "
                "into a wall faster than the step can follow; try a smaller cfl, a finer spacing or a finer wall "
                "(SDF) resolution")


class SolverBase:
    """The stepping every solver shares. A solver sets ``x``, ``v``, ``id``, ``t``, ``domain`` and
    ``left_domain``, defines ``step(t_end)`` and ``_resized()`` (rebuild its per-particle buffers), and
    names in ``carried`` its per-particle arrays besides x, v and id that live across steps. With a
    ``guard`` (set by ``drive``), every step is checked for a blow-up (BlowUp).

    Inflows and sinks (inflow.py, attached by ``attach_flows``): before each step the layers due are
    emitted (appended to the arrays: a copy per layer, not per step), after it the particles in a sink
    are removed. Their counters are part of the state (``flow_state``), so a resumed run goes on bitwise."""
    carried: tuple[str, ...] = ()
    guard: Guard | None = None
    stiffness_settings = "its stiffness"  # what to change when the fluid compresses (drive's COMPRESSION_LIMIT)
    inflows: tuple = ()
    sinks: tuple = ()
    sunk = 0  # particles removed by the sinks
    # what inflows brought minus what sinks and the domain's edge took: (their specific_energy, their count); the
    # energy checks book it (flowed_energy)
    flowed: tuple[float, int] = (0.0, 0)
    log: logging.Logger | None = None
    # moving walls: their motions (RigidMotion's pose(t), velocity(t), pivot; SI) and reach from the pivot;
    # a solver with them keeps a walls bundle ``wall_terms`` with a ``pose`` array (walls.maps.set_pose)
    motions: tuple = ()
    body_reach: tuple = ()

    def viscous_dt(self) -> float:
        """The viscosity's step limit (s; inf without viscosity): the explicit viscosity sum's stability limit."""
        return math.inf

    def unconverged(self) -> str | None:
        """The last step's pressure solve, where it stopped at its iteration cap short of its tolerance: what the
        blow-up report names as the likely cause (Guard._cause), with the setting to change; else None."""
        return None

    def set_motions(self, bodies) -> None:
        """The motions of ``bodies`` ((SDFGrid in its rest frame, motion) per moving wall) and their reach."""
        self.motions = tuple(m for _, m in bodies)
        self.body_reach = tuple(reach(b.origin, b.upper, m.pivot) for b, m in bodies)

    def _pose_bodies(self, t: float) -> None:
        for k, motion in enumerate(self.motions):
            R, T = motion.pose(t)
            v, w = motion.velocity(t)
            set_pose(self.wall_terms, k, R, T, motion.pivot, v, w)

    def wall_speed(self, t: float) -> float:
        """The fastest any moving wall point goes at time t (0 without moving walls): a step must not let a
        wall outrun the fluid (it would tunnel through particles)."""
        return max((wall_speed(m, r, t) for m, r in zip(self.motions, self.body_reach)), default=0.0)

    def advance_to(self, t_end: float) -> int:
        n = 0
        if self.guard is not None:
            self.guard.start_frame(self)
        while self.t < t_end:
            if self.inflows:
                self.emit_inflow()
            if len(self.x) == 0:  # nothing to step (yet, or any more): on to the next layer's time
                self.t = min(t_end, self._next_layer_time())
                continue
            try:
                dt = self.step(t_end)
            except BlowUp:
                raise
            except FloatingPointError as e:  # a solver's own divergence check (dfsph: dt not finite)
                raise BlowUp(str(e), self.t, len(self.x), "the time step or the stiffness") from e
            n += 1
            if self.sinks:
                self.drain_sinks()
            if self.guard is not None:
                self.guard.check(self, dt, last_of_frame=self.t >= t_end)
        return n

    # -- inflows and sinks -------------------------------------------------------------------------
    def attach_flows(self, inflows, sinks, log: logging.Logger | None = None) -> None:
        """Give the solver the scene's inflows and sinks (inflow.py, SI); new ids continue after the
        largest id so far."""
        self.inflows, self.sinks, self.log = tuple(inflows), tuple(sinks), log
        self.next_id = int(self.id.max()) + 1 if len(self.id) else 0
        self.inflow_layers = np.zeros(len(self.inflows), np.int64)  # layers due so far, per inflow
        self.inflow_skipped = np.zeros(len(self.inflows), np.int64)  # of them, not emitted: blocked
        self.inflow_particles = 0
        self.sunk = 0
        self.flowed = (0.0, 0)

    def _book(self, x: np.ndarray, v: np.ndarray, sign: int) -> None:
        """Count particles entering (sign 1) or leaving (-1) the fluid in ``flowed``."""
        e = specific_energy(x, v, self.gravity)
        self.flowed = (self.flowed[0] + sign * e, self.flowed[1] + sign * len(x))

    def flow_state(self) -> dict:
        """The inflow and sink counters, for the checkpoints (every solver's ``state``)."""
        next_id = getattr(self, "next_id", int(self.id.max()) + 1 if len(self.id) else 0)
        return {"next_id": np.int64(next_id), "sunk": np.int64(self.sunk),
                "flowed": np.asarray(self.flowed, np.float64),
                "inflow_layers": np.asarray(getattr(self, "inflow_layers", ()), np.int64),
                "inflow_skipped": np.asarray(getattr(self, "inflow_skipped", ()), np.int64),
                "inflow_particles": np.int64(getattr(self, "inflow_particles", 0))}

    def load_flow_state(self, s: Mapping) -> None:
        if "next_id" not in s:  # a checkpoint written before inflows existed
            return
        self.next_id = int(s["next_id"])
        self.sunk = int(s["sunk"])
        self.inflow_layers = np.array(s["inflow_layers"], np.int64)
        self.inflow_skipped = np.array(s["inflow_skipped"], np.int64)
        self.inflow_particles = int(s["inflow_particles"])
        if "flowed" in s:  # older checkpoints: booked from the resumed frame on
            self.flowed = (float(s["flowed"][0]), int(s["flowed"][1]))

    def _next_layer_time(self) -> float:
        if not self.inflows:
            return math.inf
        times = [jet.layer_time(int(k)) for jet, k in zip(self.inflows, self.inflow_layers)
                 if jet.layer_time(int(k)) < jet.end]
        return min(times, default=math.inf)

    def emit_inflow(self) -> int:
        """Emit every layer due by self.t (inflow.py); a layer that would land on the fluid (the jet is
        blocked: the last layer still at the nozzle, a puddle under it; ``inflow_blocked``) is skipped and
        counted. Returns the particles added."""
        xs, vs = [], []
        for i, jet in enumerate(self.inflows):
            while jet.due(int(self.inflow_layers[i]), self.t):
                k = int(self.inflow_layers[i])
                self.inflow_layers[i] += 1
                x, v = jet.layer(k, self.t, self.gravity)
                if inflow_blocked(x, [self.x, *xs], jet):
                    if self.inflow_skipped[i] == 0 and self.log is not None:
                        self.log.warning("inflow %d blocked at t = %.4g s: a layer would land on the fluid and is "
                                         "skipped (counted in the statistics as inflow_skipped_layers)", i, self.t)
                    self.inflow_skipped[i] += 1
                    continue
                xs.append(x)
                vs.append(v)
        if not xs:
            return 0
        x, v = np.concatenate(xs), np.concatenate(vs)
        n = len(x)
        self._book(x, v, 1)
        self.x = np.concatenate([self.x, x])
        self.v = np.concatenate([self.v, v])
        self.id = np.concatenate([self.id, np.arange(self.next_id, self.next_id + n, dtype=self.id.dtype)])
        for name in self.carried:  # new particles start with zero (a warm start from nothing)
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, np.zeros((n,) + a.shape[1:], a.dtype)]))
        self.next_id += n
        self.inflow_particles += n
        self._resized()
        return n

    def drain_sinks(self) -> int:
        """Remove the particles whose centre is in a sink (counted in ``sunk``)."""
        inside = in_sinks(self.x, self.sinks)
        gone = int(inside.sum())
        if gone:
            self._book(self.x[inside], self.v[inside], -1)
            self._keep(~inside)
            self.sunk += gone
        return gone

    def _keep(self, keep: np.ndarray) -> None:
        for name in ("x", "v", "id") + self.carried:
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[keep]))
        self._resized()

    def density_ratio(self, p: np.ndarray) -> np.ndarray | None:
        """rho / rho0 at pressure p by the solver's equation of state; None for an incompressible solver
        (hydrostatic_start then leaves the positions as emitted)."""
        return None

    def remove_escaped(self) -> int:
        """Drop particles outside the domain (counted in ``left_domain``); non-finite ones are a
        blow-up, caught by the guard before this."""
        lo, hi = self.domain
        keep = np.all((self.x >= lo) & (self.x <= hi) & np.isfinite(self.x), axis=1)
        gone = int(len(keep) - keep.sum())
        if gone:
            out = ~keep & np.all(np.isfinite(self.x) & np.isfinite(self.v), axis=1)
            self._book(self.x[out], self.v[out], -1)
            self._keep(keep)
            self.left_domain += gone
        return gone


def hydrostatic_start(solver: SolverBase) -> None:
    """Compress the fluid at rest to its hydrostatic state (PHYSICS.md "Water at rest"): without it a
    weakly compressible column starts at rho0 with no pressure, falls under gravity by its compression
    and rings acoustically for seconds (water's viscosity barely damps it). Each vertical lattice column
    of particles at rest is compressed towards its lowest particle so that the density follows
    p = rho0 g d, d the depth below the column's top (its top particle + l0 / 2). Moving particles (jets)
    and incompressible solvers are left as they are, and so is fluid that nothing holds up: a column is cut
    where it has a gap of more than a spacing, and a piece is compressed only if a wall lies within a spacing
    below its lowest particle (a block released in mid-air compressed this way expanded 44 % as it fell)."""
    g = float(np.linalg.norm(solver.gravity))
    if g == 0.0 or len(solver.x) == 0 or solver.density_ratio(np.zeros(1)) is None:
        return
    up = -np.asarray(solver.gravity, float) / g
    rest = np.flatnonzero(~np.any(solver.v != 0.0, axis=1))
    if len(rest) == 0:
        return
    x = solver.x[rest]
    height = x @ up
    flat = x - np.outer(height, up)  # the position in the plane normal to gravity
    key = np.round(flat / (0.25 * solver.l0)).astype(np.int64)
    _, column = np.unique(key, axis=0, return_inverse=True)
    column = column.ravel()
    order = np.lexsort((height, column))
    starts = np.flatnonzero(np.r_[True, column[order][1:] != column[order][:-1]])
    ends = np.r_[starts[1:], len(order)]
    new_height = height.copy()
    # each piece of a column between gaps: (first, end) in order
    gap = np.flatnonzero(np.diff(height[order]) > 1.5 * solver.l0) + 1
    cuts = np.union1d(starts, gap)
    starts, ends = cuts, np.r_[cuts[1:], len(order)]
    held = wall_distance(solver, x[order[starts]] - solver.l0 * up) <= 0.1 * solver.l0
    for a, b in zip(starts[held], ends[held]):
        idx = order[a:b]  # one piece of a column, bottom to top
        hz = height[idx]
        top = hz[-1] + 0.5 * solver.l0
        mid = 0.5 * (hz[1:] + hz[:-1])  # each gap's mid-height: the gap shrinks by its density ratio
        shrink = 1.0 / solver.density_ratio(solver.rho0 * g * (top - mid))
        new_height[idx[1:]] = hz[0] + np.cumsum(np.diff(hz) * shrink)
    solver.x[rest] += np.outer(new_height - height, up)


def wall_distance(solver: SolverBase, points: np.ndarray) -> np.ndarray:
    """The distance from ``points`` to the nearest wall, static or moving (where it stands at t = 0)."""
    d, _ = solver.sdf.sample(points)
    for (grid, *_), motion in zip(getattr(solver, "bodies", ()), getattr(solver, "motions", ())):
        r, tr = motion.pose(0.0)  # the point in the wall's rest frame: R^T (x - pivot - T) + pivot
        d = np.minimum(d, grid.sample((points - motion.pivot - tr) @ r + motion.pivot)[0])
    return d


SETTLE_RATE = 30.0  # velocities zeroed this many times a simulated second while settling


def settle_intervals(seconds: float) -> int:
    return max(1, round(seconds * SETTLE_RATE))


def settle(solver: SolverBase, seconds: float, progress=None, log=None, spacing: float = 0.0) -> None:
    """Let a fluid that starts at rest settle before t = 0: ``seconds`` of the solver's own steps with every
    velocity set to zero 30 times a second (kinetic damping of the start, not of the shot), then the clock
    and the step count back at the start. The start lattice is not the method's resting packing: left alone it
    creeps into it during the shot (bench_rest's tank: 0.0033 m/s at 1.5 s); settled for 1.5 s first, 0.0019
    m/s (README, Water at rest)."""
    t0, steps0 = solver.t, solver.steps
    before = solver.frame()
    n = settle_intervals(seconds)
    for k in range(1, n + 1):
        solver.advance_to(t0 + seconds * k / n)
        solver.v[:] = 0.0
        if progress is not None:
            progress.advance()
    if log is not None:
        log.info("settled for %.3g s before t = 0 (%d steps)", seconds, solver.steps - steps0)
        # a column or a drop is not at rest: settling let it fall, and the shot started from a puddle without
        # a word (a dam break's column 10 cm high began the shot 5.7 cm high)
        after = solver.frame()
        if len(before.id) and spacing:
            start = before.x[np.argsort(before.id)][np.searchsorted(np.sort(before.id), after.id)]
            moved = np.linalg.norm(after.x - start, axis=1) / spacing
            share = float(np.mean(moved > 1.0))
            if share > 0.01:
                log.warning("fluid.settle is for water at rest: while settling %.0f %% of the particles moved more "
                            "than a spacing (up to %.3g l0), so the shot starts from where they fell, not from the "
                            "emitters' shape; set fluid.settle: 0 for water that is meant to move",
                            100.0 * share, moved.max())
    solver.t, solver.steps = t0, steps0


def ballistic_speed(setup: "Setup", effects=None) -> float:
    """The fastest a particle of the scene can move without the solver creating energy (m/s): the
    emitters' and inflows' top speed, plus the free fall from the top of the fluid (or of an inflow's disc) to
    the bottom of the domain (the walls' box without one), plus the wind's speed and an attractor's escape
    speed sqrt(2 k / s)."""
    v0 = max([float(np.linalg.norm(setup.v, axis=1).max()) if len(setup.v) else 0.0]
             + [jet.top_speed() for jet in setup.inflows])
    g = float(np.linalg.norm(setup.gravity))
    height = max(_fluid_top(setup) - float((scene_corners(setup) @ setup.up).min()), setup.spacing)
    bound = v0 + math.sqrt(2.0 * g * height) + 2.0 * wall_speed_bound(setup.bodies)
    if effects is not None:
        bound += (capillary_speed(setup.effects, setup.density, setup.spacing)
                  + effects_speed(effects, scene_corners(setup)))
    return max(bound, math.sqrt(9.81 * setup.spacing))  # a scene without gravity or motion: never zero


def effects_speed(effects, corners: np.ndarray) -> float:
    """The speed wind and an attractor can give a particle within the scene's box (``corners``; m/s): the wind's
    speed where it has a drag (with drag 0 it moves nothing), plus what the attractor's potential drops across the
    box, sqrt(2 |k| (1 / r_near' - 1 / r_far')), r' = sqrt(r^2 + s^2) (its escape speed sqrt(2 |k| / s) when the
    point is in the box; a point far outside gives little: 1e12 at 1,000 km, 1 m/s^2 over a 3 m tank, was taken as 3.5e6
    m/s, not 2.4)."""
    speed = 0.0
    if getattr(effects, "wind_velocity", None) is not None and (effects.wind_drag or 0.0) > 0.0:
        speed += float(np.linalg.norm(effects.wind_velocity))
    if getattr(effects, "attractor_point", None) is not None and effects.attractor_k:
        p, s = effects.attractor_point, effects.attractor_soft
        near = float(np.linalg.norm(np.clip(p, corners.min(axis=0), corners.max(axis=0)) - p))
        far = float(np.linalg.norm(corners - p, axis=1).max())
        drop = abs(effects.attractor_k) * max(1.0 / math.hypot(near, s) - 1.0 / math.hypot(far, s), 0.0)
        speed += math.sqrt(2.0 * drop)
    return speed


def capillary_speed(effects, rho0: float, l0: float) -> float:
    """The speed surface tension and wall adhesion can give a particle (m/s): a lattice corner's surface
    energy (three faces of l0^2 at gamma) turned into its kinetic energy, sqrt(6 gamma / (rho0 l0)); 0.9 m/s
    for water at 0.5 mm, 0.1 m/s at 4 cm. Without it a droplet in zero gravity had a bound of sqrt(g l0)
    and a sound speed of 0.01 m/s."""
    if effects is None:
        return 0.0
    gamma = effects.surface_tension.gamma if effects.surface_tension is not None else 0.0
    if effects.wall_adhesion is not None:  # adhesion pulls like the fluid's own cohesion times beta
        gamma += effects.wall_adhesion.beta * (gamma or WATER_GAMMA)
    return math.sqrt(6.0 * gamma / (rho0 * l0))


def wall_speed_bound(bodies) -> float:
    """The fastest a point of a moving wall goes over its whole motion (m/s): its pivot's speed plus its
    angular speed times its reach from the pivot, at every key and between (a wall can fling the fluid at
    twice its own speed, an elastic bounce; ballistic_speed takes that)."""
    return max((top_wall_speed(m, reach(sdf.origin, sdf.upper, m.pivot)) for sdf, m in bodies), default=0.0)


def scene_corners(setup: "Setup") -> np.ndarray:
    """The 8 corners of the scene's box: its domain, or the walls' (SDF) box without one."""
    lo = setup.domain[0] if setup.domain is not None else setup.sdf.origin
    hi = setup.domain[1] if setup.domain is not None else setup.sdf.upper
    return np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])


# a wall this many spacings under the fluid's lowest particle is a drop it falls down (a fluid resting on a floor starts
# half a spacing above it, and its sound speed stays its column's)
FALL = 2.0


def floor_below(walls: SDFGrid, x: np.ndarray, up: np.ndarray, samples: int = 4096) -> float:
    """The lowest wall under the fluid at ``x``, along ``up`` (a grid axis): for up to ``samples`` particles (evenly
    through the array), the highest node of the walls' grid in the particle's column, at or below it, that is within
    0.3 node spacings of a wall or inside one; the grid's bottom where none is. On the nodes, so the same scene in
    other units or with the other up axis finds the same floor (tests/stability/test_blowup.py, m Z-up and cm Y-up)."""
    axis = int(np.argmax(np.abs(up)))
    dist = np.moveaxis(walls.dist, axis, -1)  # (columns a, columns b, nodes along up)
    rel = (np.asarray(x, np.float64)[:: max(1, len(x) // samples)] - walls.origin) / walls.spacing
    across = [a for a in range(3) if a != axis]
    ia = np.clip(np.rint(rel[:, across[0]]).astype(np.int64), 0, dist.shape[0] - 1)
    ib = np.clip(np.rint(rel[:, across[1]]).astype(np.int64), 0, dist.shape[1] - 1)
    below = np.clip(np.floor(rel[:, axis]).astype(np.int64), -1, dist.shape[2] - 1)
    k = np.arange(dist.shape[2])
    wall = (dist[ia, ib, :] < 0.3 * walls.spacing) & (k[None, :] <= below[:, None])
    top_wall = np.where(wall.any(axis=1), dist.shape[2] - 1 - np.argmax(wall[:, ::-1], axis=1), 0)
    return float(walls.origin[axis] + walls.spacing * top_wall.min())


def _fluid_top(setup: "Setup") -> float:
    """The highest point of the fluid at the start or of an inflow's disc, along up."""
    tops = [float((setup.x @ setup.up).max())] if len(setup.x) else []
    tops += [float((jet.swept_points() @ setup.up).max()) for jet in setup.inflows]
    return max(tops)


@dataclass
class Setup:
    """The scene as a solver needs it, in SI units (metres, seconds, kg)."""
    x: np.ndarray
    v: np.ndarray
    sdf: SDFGrid
    spacing: float
    density: float
    gravity: np.ndarray  # acceleration vector, m/s^2 (zero without the gravity effect)
    up: np.ndarray
    v_ref: float  # expected top speed: sqrt(2 g H) of the fluid column, or the emitters' speed
    v_land: float  # and the speed the fluid lands at where it starts over a drop (WCSPH's stiffness; below v_ref none)
    domain: tuple[np.ndarray, np.ndarray] | None
    effects: Any  # pipeline.scene.Effects
    meters_per_unit: float  # of the scene: frames are written back in scene units
    dropped: int = 0  # emitted particles dropped because they started inside a wall
    dropped_outside: int = 0  # ... or outside the domain
    bodies: list = field(default_factory=list)  # moving walls: (SDFGrid in its rest frame, RigidMotion), SI
    inflows: list[Inflow] = field(default_factory=list)  # inflow.py, SI
    sinks: list[Sink] = field(default_factory=list)
    settle: float = 0.0  # seconds of settling before t = 0 (fluid.settle)


def up_vector(up_axis: str) -> np.ndarray:
    return np.array([0.0, 1.0, 0.0]) if up_axis == "Y" else np.array([0.0, 0.0, 1.0])


def set_threads(threads: int | None) -> None:
    if threads:
        nb.set_num_threads(min(int(threads), nb.config.NUMBA_NUM_THREADS))


def moving_wall(ctx: Context) -> int | None:
    """The first of the config's walls with a ``motion`` (plan time: the stage's ``estimate_reads`` hold
    "walls"); walls animated in a USD file show only once imported (``prepare``)."""
    return next((i for i, w in enumerate(ctx.scene["walls"] or ()) if w.motion is not None), None)


def prepare(ctx: Context, inputs: Mapping[str, Artifact], who: str, moving_walls: bool = False) -> Setup:
    """Emit the fluid, drop the particles inside walls and resolve gravity; ``who`` names the stage
    in errors. ``moving_walls``: whether the solver takes moving walls (a scene with them is refused
    otherwise, in one line)."""
    scene = ctx.scene["scene"]
    fluid = ctx.scene["fluid"]
    effects = ctx.scene["effects"]
    if fluid is None:
        raise StageError(f"{who}: the scene has no 'fluid' section (spacing and emitters)")
    sdf = SDFGrid.load(inputs["sdf"].path)
    l0 = fluid.spacing
    mpu = scene.units.meters_per_unit
    up = up_vector(scene.units.up_axis)
    bodies = load_bodies(inputs["sdf"].path)
    if bodies and not moving_walls:
        raise StageError(f"{who}: the scene has moving walls (walls[].motion or animated USD prims); only "
                         "simulate: {use: sph} and {use: mps} move walls so far")
    x, v = emit(fluid.emitters, l0, ctx.resolve, mpu, ctx.log, scene.units.up_axis)
    x, v, _ = drop_overlaps(x, v, l0, ctx.log)
    # the moving walls where they stand at t = 0 count like the static ones
    emitted, x_emitted = len(x), x
    counts: dict = {}
    walls_at_start = posed_field(sdf, bodies, 0.0)
    x, v, dropped = drop_inside_walls(x, v, walls_at_start, l0, ctx.log, counts=counts, progress=ctx.progress)
    # what the fluid falls to (with an inflow, the fall to the domain's bottom counts anyway)
    floor = floor_below(walls_at_start, x, up) if len(x) and effects.gravity is not None and not fluid.inflow else None
    if len(x) == 0 and not fluid.inflow:
        if emitted == 0:
            why = f"every emitter is smaller than fluid.spacing ({l0:g}) or empty"
        elif counts["outside"] == emitted:
            why = (f"all {emitted} lie outside the simulation domain, {box_text(sdf.origin, sdf.upper)} (the walls' "
                   "box, or scene.domain)") + units_hint(sdf.origin, sdf.upper, x_emitted.min(axis=0),
                                                         x_emitted.max(axis=0), "the domain")
        else:
            # the walls whose solid holds the emitters, and their size against the emitters' (units)
            why = (f"{counts['in_wall']} of {emitted} lie inside a wall or within l0 / 2 of one"
                   + (f" and {counts['outside']} outside the domain" if counts["outside"] else "")
                   + no_fluid_hint(read_wall_boxes(inputs["sdf"].path), x_emitted))
        raise StageError(f"{who}: the emitters produced no particles in the fluid region: {why}")
    if mpu != 1.0:  # scene units -> metres
        x, v, l0 = x * mpu, v * mpu, l0 * mpu
        floor = floor * mpu if floor is not None else None
        # the distances scaled in float64 and rounded once: float32 times float32(mpu) rounds twice, and that
        # ulp tipped a particle near a wall in millimetres into another path (tests/test_moving_walls_units.py)
        to_si = lambda g: SDFGrid(origin=g.origin * mpu, spacing=g.spacing * mpu,  # noqa: E731
                                  dist=(g.dist.astype(np.float64) * mpu).astype(np.float32), band=g.band * mpu)
        sdf = to_si(sdf)
        bodies = [(to_si(b), m.scaled(mpu)) for b, m in bodies]
    domain = None
    if scene.domain is not None:
        domain = (np.asarray(scene.domain.min, float) * mpu, np.asarray(scene.domain.max, float) * mpu)
    inflows, sinks = from_config(fluid, mpu, dict(zip(body_walls(inputs["sdf"].path), (m for _, m in bodies))))
    for i, jet in enumerate(inflows):
        _clear_of_walls(jet, i, sdf, bodies, domain, l0, who, ctx.log)
    _warn_idle_flows(inflows, sinks, x, (scene.frames.count - 1) / scene.frames.fps, sdf, l0, ctx.log)
    gravity = np.zeros(3)
    v_emit = float(np.linalg.norm(v, axis=1).max()) if len(v) else 0.0
    v_ref = max([v_emit] + [jet.top_speed() for jet in inflows])
    v_land = 0.0
    if effects.gravity is not None:
        g = effects.gravity.g
        gravity = -g * up
        heights = [x @ up] + [jet.swept_points() @ up for jet in inflows]
        if inflows:  # a jet falls to the bottom of the domain
            lo, hi = domain if domain is not None else (sdf.origin, sdf.upper)
            heights.append(np.array([min(lo @ up, hi @ up)]))
        h = np.concatenate(heights)
        height = float(h.max() - h.min()) + l0
        # the fastest a particle gets falling from the top: a jet's speed adds (energy) to the free fall
        v_top = max([jet.top_speed() for jet in inflows], default=0.0)
        v_ref = max(v_ref, math.sqrt(v_top ** 2 + 2.0 * g * height))
        if floor is not None and floor < h.min() - FALL * l0:
            # fluid released over a drop lands at sqrt(v0^2 + 2 g H), H from its top to the wall under it: its own
            # thickness alone gave the open bowl's slab a sound speed of 9.7 m/s for a 2.6 m/s landing, 63 % compressed
            v_land = math.sqrt(max(v_emit, v_top) ** 2 + 2.0 * g * (float(h.max()) - floor + l0))
    v_ref = max(v_ref, capillary_speed(effects, fluid.density, l0))  # a droplet's own sound speed
    if fluid.settle > 0 and bodies:
        # the config refuses settling with emitter velocities, jets, sinks and walls[].motion (scene.py); walls
        # animated in a USD file are known only here
        raise StageError(f"{who}: fluid.settle is for a fluid among walls at rest, but the scene has walls animated "
                         "in their USD file; set fluid.settle to 0")
    return Setup(x=x, v=v, sdf=sdf, spacing=l0, density=fluid.density, gravity=gravity, up=up, v_ref=v_ref,
                 v_land=max(v_land, v_ref),
                 domain=domain, effects=effects, meters_per_unit=mpu, dropped=counts["in_wall"],
                 dropped_outside=counts["outside"], inflows=inflows, sinks=sinks,
                 bodies=bodies, settle=fluid.settle)


def _clear_of_walls(jet: Inflow, i: int, sdf: SDFGrid, bodies, domain, l0: float, who: str,
                    log: logging.Logger) -> None:
    """Keep the disc points of an inflow at least l0 / 2 from a wall (the moving ones where they stand at
    the jet's start) and inside the SDF grid and the domain (as drop_inside_walls does for the emitters);
    an inflow with none left is a user error. A nozzle on a moving wall keeps its clearance from that wall."""
    p = jet.disc_points(jet.start)
    d, _ = sdf.sample(p)
    for grid, motion in bodies:
        d = np.minimum(d, grid.sample(motion.to_rest(p, jet.start))[0])
    lo, hi = (sdf.origin, sdf.upper) if domain is None else (np.maximum(domain[0], sdf.origin),
                                                              np.minimum(domain[1], sdf.upper))
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    jet.keep = (d >= (0.5 - 1e-3) * l0) & inside
    if not jet.keep.any():
        where = (f"outside the simulation domain, {box_text(lo, hi)} (scene.domain sets it; without it, the walls' "
                 "box and a margin)") if not inside.any() else "inside or within 0.5 l0 of a wall"
        raise StageError(f"{who}: fluid.inflow.{i}: its disc (centre {np.round(jet.center, 6).tolist()}) lies {where}")
    if not jet.keep.all():
        log.warning("inflow %d: %d of its %d disc particles are inside or within 0.5 l0 of a wall or outside the "
                    "domain and are not emitted (the jet emits that much less than pi r^2 v)", i,
                    int((~jet.keep).sum()), len(jet.keep))


def _warn_idle_flows(inflows, sinks, x: np.ndarray, shot_seconds: float, sdf: SDFGrid, l0: float,
                     log: logging.Logger) -> None:
    """Flows set up so they cannot do their job, which ran silently: a jet that starts at or after the
    shot's last frame, a jet facing a (static) wall within two spacings of its disc, a sink that already
    holds emitted particles (removed in the first step)."""
    for i, jet in enumerate(inflows):
        if jet.start >= shot_seconds:
            log.warning("inflow %d starts at %.4g s, at or after the shot's last frame (%.4g s): it emits nothing",
                        i, jet.start, shot_seconds)
        elif min(jet.end, shot_seconds) < jet.layer_time(0):
            log.warning("inflow %d runs %.3g s, less than the %.3g s its first layer needs (half of l0 / speed "
                        "after its start): it emits nothing", i, min(jet.end, shot_seconds) - jet.start,
                        jet.layer_time(0) - jet.start)
        centre, direction = jet.frame_at(jet.start)
        d, _ = sdf.sample(centre + np.outer([1.0, 2.0], direction * l0))
        if (d < 0).any():
            log.warning("inflow %d points into a wall: the wall is within 2 spacings in front of its disc, where "
                        "its jet stops", i)
        for k, sink in enumerate(sinks):
            if in_sinks(centre[None], [sink])[0]:
                log.warning("inflow %d's nozzle is inside sink %d: its water is removed as it enters", i, k)
    for k, sink in enumerate(sinks):
        # particles keep half a spacing from walls: a sink with no point that far from one removes nothing (a
        # drain box under a closed floor said 'sunk: 0' at the end, and nothing before)
        lo, hi = np.maximum(sink.lo, sdf.origin), np.minimum(sink.hi, sdf.upper)
        axes = [np.linspace(a, b, max(2, min(24, int(np.ceil((b - a) / (0.25 * l0))) + 1))) for a, b in zip(lo, hi)]
        probe = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) if (hi > lo).all() else np.zeros((0, 3))
        if not len(probe) or sdf.sample(probe)[0].max() < 0.45 * l0:
            log.warning("sink %d can remove nothing: no point of it is in the fluid region half a spacing from a "
                        "wall, where particles can be (a drain goes below an opening in the floor, not under a "
                        "closed one)", k)
    if sinks and len(x):
        held = int(in_sinks(x, sinks).sum())
        if held:
            # a drain under the water takes its few at once (the shipped tap_drain: 16 of 7,200, normal); a sink over
            # much of the emitted water is the mistake worth a warning (50 of 125)
            (log.warning if held >= 0.01 * len(x) else log.info)(
                "%d of the %d emitted particles start inside a sink (fluid.sinks) and are removed before frame 0",
                held, len(x))


def to_scene_units(fr: ParticleFrame, mpu: float) -> ParticleFrame:
    """A solver's frame (SI) in the scene's length unit; density and pressure stay SI."""
    if mpu == 1.0:
        return fr
    return ParticleFrame(x=fr.x / mpu, v=fr.v / mpu, rho=fr.rho, p=fr.p, id=fr.id)


_LIST_STATS = ("density_error_mean", "density_error_max", "inside_wall", "extent_min", "extent_max")


def drive(ctx: Context, solver: Solver, setup: Setup, *, solver_name: str, checkpoint_every: int) -> dict:
    """Run the frame loop of ``solver`` and write the particle cache; returns the statistics."""
    scene = ctx.scene["scene"]
    count = scene.frames.count
    fps = scene.frames.fps
    ckpt_dir = getattr(ctx, "checkpoint_dir", None)
    ckpt_dir = Path(ckpt_dir) if ckpt_dir is not None else None
    stats: dict = {"emitted": int(len(setup.x) + setup.dropped + setup.dropped_outside),
                   "dropped_in_wall": setup.dropped, "dropped_outside_domain": setup.dropped_outside, "escaped": 0,
                   "density_error_mean": [],
                   "density_error_max": [], "inside_wall": [], "extent_min": [], "extent_max": [],
                   "wall_seconds": 0.0}
    earlier = getattr(ctx, "resume_from", None)
    earlier = Path(earlier) if earlier is not None else None
    resumed, source = latest_checkpoint(ckpt_dir, count, earlier), ckpt_dir
    if resumed is None and earlier is not None:
        # the cached entry of a shorter run of this shot (Stage.extends): continue from its last frame
        source = earlier
        resumed = latest_checkpoint(source, count)
    progress = ctx.progress(f"simulating ({solver_name})", count)
    solver.attach_flows(setup.inflows, setup.sinks, ctx.log)
    solver.guard = Guard.with_energy(ballistic_speed(setup, getattr(solver, "effects", None)), setup.spacing,
                                     setup.gravity, scene_corners(setup))
    effects = getattr(solver, "effects", None)
    own = ballistic_speed(setup)  # falling, the emitters and the walls: no effect's
    # (surface tension's speed is the scene's own too: a droplet in zero gravity is no misuse)
    if solver.guard.v_bound > 10.0 * (own + capillary_speed(setup.effects, setup.density, setup.spacing)):
        # an attractor of strength 1e9 in a 0.4 m tank: escape speed 4.5e5 m/s, steps of 1e-7 s, a run of hours
        # that looked hung
        ctx.log.warning("the effects (wind, attractor) allow speeds up to %.3g m/s, %.0f x what falling and the "
                        "emitters give (%.3g m/s): the time steps shrink as much and the run takes that much longer; "
                        "check their strength", solver.guard.v_bound, solver.guard.v_bound / own, own)
    # the least step a limit known before the run may ask for: step_to splits a frame's last step into halves,
    # and a half below the floor is a blow-up (DFSPH at mu 1e5 needed 2.8e-5 s against a floor of 1.6e-5 s and
    # stopped at its first frame's end)
    least = STEP_SPLIT * solver.guard.dt_floor

    def where(dt: float) -> str:
        return "below" if dt < solver.guard.dt_floor else f"within {STEP_SPLIT:g} x of"

    def near_floor(dt: float) -> str:
        return (f"{where(dt)} this scene's floor of {solver.guard.dt_floor:.3g} s (a blow-up; a frame's last steps are "
                "split)")

    mu = float(setup.effects.viscosity.mu) if setup.effects.viscosity is not None else 0.0
    viscous_dt = solver.viscous_dt()
    if viscous_dt < least:
        # the viscous step limit (solver.viscous_dt) is known now: said before the run, not as a blow-up after it
        raise StageError(f"simulate.{solver_name}: effects.viscosity.mu ({mu:g} Pa s) needs time steps of "
                         f"{viscous_dt:.3g} s, {near_floor(viscous_dt)}: lower it (water 0.001, honey about 10) or "
                         "coarsen the spacing")
    g = float(setup.effects.gravity.g) if setup.effects.gravity is not None else 0.0
    if g > 50.0:  # 981 in a centimetre scene: gravity is in m/s^2 in every unit
        ctx.log.warning("effects.gravity.g is %g m/s^2, %.0f x Earth's: gravity is given in m/s^2 in every unit "
                        "(981 is Earth's in cm/s^2)", g, g / 9.81)
    if effects is not None and effects.dt_limit < least:
        # the run would stop at its first step with "the time step fell below the floor": say which setting
        raise StageError(f"simulate.{solver_name}: {effects.dt_limit_by} needs time steps of {effects.dt_limit:.3g} s, "
                         f"{near_floor(effects.dt_limit)}: lower it")
    # a rate that shortens every step far below the flow's own, said before the run: a wall friction of 2e4 1/s
    # (a unit slip) ran 28 x the steps, the fluid all but frozen, in silence (surface tension's capillary limit is
    # the physics of a small drop, and its absurd values are refused)
    flow_dt = 0.4 * setup.spacing / solver.guard.v_bound  # cfl 0.4 at the ballistic bound
    for need, by in ((viscous_dt, f"effects.viscosity.mu ({mu:g} Pa s)"),
                     (effects.dt_limit if effects is not None else math.inf, getattr(effects, "dt_limit_by", ""))):
        if need < flow_dt / SLOW_STEPS and not by.startswith("effects.surface_tension"):
            ctx.log.warning("simulate.%s: %s needs time steps of %.3g s, %.0f x shorter than the flow's own (about "
                            "%.3g s at its ballistic speed bound %.3g m/s): the run takes that many more steps; "
                            "check its value and units", solver_name, by, need, flow_dt / need, flow_dt,
                            solver.guard.v_bound)
    params = getattr(solver, "p", None)
    c = getattr(params, "sound_speed", None)  # a user's (the default is 10 x the expected speed)
    if c is not None and c < 3.0 * solver.guard.v_bound:
        # WCSPH's density error grows as (v / c)^2: a column at 0.2 x the default flattened to 0.24 of its height
        ctx.log.warning("simulate.%s: sound_speed %.3g m/s is %.2g x the scene's ballistic speed bound %.3g m/s: "
                        "the fluid compresses by about (v / c)^2, %.0f %% at that speed (the default, 10 x the "
                        "expected speed, keeps it near 1 %%)", solver_name, c, c / solver.guard.v_bound,
                        solver.guard.v_bound, 100 * min((solver.guard.v_bound / c) ** 2, 99.0))
    for field in ("time_step", "dt_max"):  # a user's fixed step (sph, mps) or largest step (dfsph)
        dt = getattr(params, field, None)
        if dt is not None and dt < least:
            # it stopped at the first step as a blow-up whose advice (a smaller cfl) made it worse
            raise StageError(f"simulate.{solver_name}: {field} {dt:g} s is {where(dt)} this scene's time-step floor of "
                             f"{solver.guard.dt_floor:.3g} s (1e-3 spacings at its ballistic speed bound "
                             f"{solver.guard.v_bound:.3g} m/s), where a run counts as blown up (a frame's last steps "
                             f"are split): raise it, or leave it out for the solver's own step")
    if resumed is not None:
        start, state = resumed
        solver.load_state(state)
        solver.guard.load_state(state)
        stats = _stats_from(state, stats)
        restore_frames(source, ctx.out_dir, start, earlier)
        ctx.log.info("resumed from the checkpoint at frame %d", start)
        progress.advance(start + 1)
    else:
        start = 0
        hydrostatic_start(solver)
        if setup.settle > 0:
            try:
                settle(solver, setup.settle, ctx.progress(f"settling ({solver_name})", settle_intervals(setup.settle)),
                       ctx.log, setup.spacing)
            except BlowUp as e:
                raise SimulationDiverged(_blow_up_line(e, 0, solver, solver_name, ckpt_dir) + " while settling") from e
        if solver.sinks:  # frame 0 holds no particle the first step would remove (it published them, then a hole)
            solver.drain_sinks()
        f0 = to_scene_units(solver.frame(), setup.meters_per_unit)
        write_frame(ctx.out_dir, 0, f0, ckpt_dir, setup.spacing / setup.meters_per_unit)
        _frame_stats(stats, f0, solver)
        progress.advance()
    if start + 1 < count:
        ctx.warm_up(lambda: _warm_up(solver, fps))
    lo, hi = setup.domain if setup.domain is not None else (setup.sdf.origin, setup.sdf.upper)
    domain_box = (np.asarray(lo) / setup.meters_per_unit, np.asarray(hi) / setup.meters_per_unit)  # scene units
    budget = EnergyBudget(setup, solver)
    if resumed is not None:
        budget.load_state(resumed[1])
    t0 = time.perf_counter()
    for f in range(start + 1, count):
        try:
            solver.advance_to(f / fps)
        except BlowUp as e:
            raise SimulationDiverged(_blow_up_line(e, f, solver, solver_name, ckpt_dir)) from e
        gone = solver.remove_escaped()
        if gone:
            stats["escaped"] += gone
            ctx.log.warning("frame %d: %d particles left the simulation domain, %s, and were removed%s", f, gone,
                            box_text(*domain_box), "" if scene.domain is not None else
                            " (the walls' box and a margin: scene.domain gives the fluid more room)")
        budget.check(solver, f, ctx.log)
        fr = to_scene_units(solver.frame(), setup.meters_per_unit)
        write_frame(ctx.out_dir, f, fr, ckpt_dir, setup.spacing / setup.meters_per_unit)
        _frame_stats(stats, fr, solver)
        if ckpt_dir is not None and (f % checkpoint_every == 0) and f < count - 1:
            stats["wall_seconds"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            save_checkpoint(ckpt_dir, f, {**solver.state(), **_stats_to(stats), **solver.guard.state(),
                                           **budget.state()})
        progress.advance()
    stats["wall_seconds"] += time.perf_counter() - t0
    kept = stats["emitted"] - stats["dropped_in_wall"] - stats["dropped_outside_domain"]
    entered = kept + solver.inflow_particles
    if stats["escaped"]:  # said frame by frame above; once more where the run ends, with the share
        # of all that entered the shot: with a jet the emitters' count alone gave 377 'of the 600 emitted' when
        # every one of them was the jet's
        ctx.log.warning("%d of the %d particles in the shot (%d from the emitters, %d from inflows) left the "
                        "simulation domain and were removed%s", stats["escaped"], entered, kept,
                        solver.inflow_particles, "" if scene.domain is not None else
                        " (set scene.domain to keep fluid thrown out of the walls' box)")
    guard = solver.guard
    if guard.focus_steps:  # let through as pressure focusing (Guard.focused): said once, where the run ends
        ratio, t_peak, n_fast = guard.focus_peak
        ctx.log.warning("%d steps had particles faster than %g x the ballistic bound (%.3g m/s) while the fluid's "
                        "energy did not rise: pressure focusing it, not a blow-up (the fastest %.1f x, %d particles, "
                        "at t = %.4g s: a void closing in a sharp concave corner, or a jet); check those frames",
                        guard.focus_steps, SPEED_LIMIT, guard.v_bound, ratio, n_fast, t_peak)
        stats["focused"] = {"steps": guard.focus_steps, "peak_over_bound": ratio, "t": t_peak, "particles": n_fast}
    compression = stats["density_error_mean"]
    if compression and max(compression) > COMPRESSION_LIMIT:
        worst = int(np.argmax(compression))
        ctx.log.warning("simulate.%s: the water is compressed by %.1f %% on average at frame %d (%.0f %% at most), "
                        "where a liquid keeps under %.0f %%: %s", solver_name, 100 * compression[worst], worst,
                        100 * stats["density_error_max"][worst], 100 * COMPRESSION_LIMIT,
                        type(solver).stiffness_settings)
    if budget.said is not None:
        stats["energy_rise"] = {"frame": budget.said[0], "rise": budget.said[1]}
    if solver.inflows or solver.sinks or stats["escaped"]:  # the water's budget, in the log as in meta.json
        ctx.log.info("water: %d from the emitters + %d from inflows - %d sunk - %d escaped = %d at the end", kept,
                     solver.inflow_particles, solver.sunk, stats["escaped"], len(solver.x))
    for i, n in enumerate(solver.inflow_skipped):
        if n:
            ctx.log.warning("inflow %d: %d of its %d layers were skipped (blocked by the fluid at the nozzle)", i, n,
                            solver.inflow_layers[i])
    # the final state in the entry itself, so a longer shot can continue from it
    save_checkpoint(ctx.out_dir, count - 1, {**solver.state(), **_stats_to(stats), **guard.state(), **budget.state()})
    sim_seconds = (count - 1) / fps
    stats.update(steps=solver.steps, left_domain=solver.left_domain, sound_speed=solver.c,
                 mean_dt=sim_seconds / max(solver.steps, 1), particles=int(len(solver.x)), sunk=solver.sunk,
                 inflow_particles=solver.inflow_particles, inflow_layers=solver.inflow_layers.tolist(),
                 inflow_skipped_layers=solver.inflow_skipped.tolist())
    # scalar summaries, so `pipeline study` can put accuracy against cost
    stats["summary"] = {
        "density_error_mean": float(np.mean(stats["density_error_mean"][1:] or [0.0])),
        "density_error_max": float(np.max(stats["density_error_max"] or [0.0])),
        "inside_wall_max": int(np.max(stats["inside_wall"] or [0])),
        "wall_seconds_per_simulated_second": stats["wall_seconds"] / sim_seconds if sim_seconds > 0 else 0.0,
        "ms_per_step": 1e3 * stats["wall_seconds"] / max(solver.steps, 1),
    }
    mpu = setup.meters_per_unit
    meta = ParticleMeta(spacing=setup.spacing / mpu, mass=solver.mass, density=setup.density, support=solver.h / mpu, fps=fps,
                        frame_count=count, up_axis=scene.units.up_axis, meters_per_unit=setup.meters_per_unit,
                        solver=solver_name, stats=stats, gravity=float(np.linalg.norm(setup.gravity)))
    meta.save(ctx.out_dir)
    write_points_layer(ctx.out_dir / "particles.usdc", iter_frames(ctx.out_dir, count), spacing=setup.spacing / mpu,
                       up_axis=scene.units.up_axis, meters_per_unit=setup.meters_per_unit, fps=fps, count=count,
                       origin=local_origin(setup.sdf.origin / mpu, setup.sdf.upper / mpu, setup.spacing / mpu))
    return stats


def _warm_up(solver: SolverBase, fps: float) -> None:
    """One throw-away step and frame on a copy of the solver: numba compiles the stepping kernels for
    this run's types here, outside the stage's recorded cost (Context.warm_up), so a study charges each
    variant its simulation, not the compiler (the first of a process paid seconds of it)."""
    twin = copy.deepcopy(solver)
    twin.log = None
    if len(twin.x) == 0:  # a scene filled by an inflow: start from its first layer
        twin.t = twin._next_layer_time()
        if not math.isfinite(twin.t) or twin.emit_inflow() == 0:
            return
    try:
        dt = twin.step(twin.t + 1.0 / fps)
        twin.guard.check(twin, dt, last_of_frame=True)
        twin.remove_escaped()
        twin.frame()
    except FloatingPointError:
        pass  # the real run reports a blow-up in its own words
    del twin


class EnergyBudget:
    """The fluid's energy (kinetic + gravitational above its lowest start point, with inflows the scene's floor)
    against its start plus what inflows brought and sinks took (SolverBase.flowed), in a scene where nothing else gives or
    takes energy (no moving wall, wind, attractor, surface tension or adhesion): it can only fall. A rise of more
    than RISE of that is energy the method made, said once (DFSPH with one column of particles in a pipe 2.5
    spacings wide: +90 %, the top particle above its release height, and nothing said: the blow-up guard's bound
    is 10 x the ballistic speed) and kept in ``said`` (frame, rise) for meta.json's stats. The reference and
    ``said`` go into checkpoints, so a resumed run or a longer shot continuing a shorter one is judged against
    the shot's start."""

    RISE = 0.10

    def __init__(self, setup: Setup, solver: "SolverBase") -> None:
        e = setup.effects
        driven = (setup.bodies or e.wind is not None or e.attractor is not None or e.surface_tension is not None
                  or e.wall_adhesion is not None)
        self.g = np.asarray(setup.gravity, np.float64)
        # the level energy is measured from: the lowest start point, or with inflows the scene box's floor (their
        # fluid falls to it; from the nozzle, the reference was the jet's kinetic energy alone, and small)
        heights = -((scene_corners(setup) if setup.inflows else solver.x) @ self.g)
        self.watch = not driven and len(heights) > 0  # False: nothing to watch (driven, or no fluid at all)
        self.base = float(heights.min()) if self.watch else 0.0
        self.start = self.energy(solver) if self.watch else 0.0
        self.flowed = solver.flowed  # where the shot's booking starts
        self.said: tuple[int, float] | None = None

    def state(self) -> dict:
        """Checkpoint entries (said: NaN for none)."""
        frame, rise = self.said or (np.nan, np.nan)
        return {"budget_ref": np.asarray([self.watch, self.start, self.base, *self.flowed], np.float64),
                "budget_said": np.asarray([frame, rise], np.float64)}

    def load_state(self, s: Mapping) -> None:
        if "budget_ref" in s:  # older checkpoints: judged from the resumed frame, as before
            watch, self.start, self.base, flowed_e, flowed_n = (float(v) for v in s["budget_ref"])
            self.watch, self.flowed = bool(watch), (flowed_e, int(flowed_n))
            frame, rise = s["budget_said"]
            self.said = None if math.isnan(frame) else (int(frame), float(rise))

    def energy(self, solver: "SolverBase") -> float:
        """Per unit mass (J/kg, summed over particles): 1/2 v^2 + g h, h above ``base``."""
        return mechanical_energy(solver, self.g, self.base)

    def check(self, solver: "SolverBase", frame: int, log) -> None:
        if not self.watch or self.said is not None:
            return
        ref = self.start + flowed_energy(solver, self.g, self.base, self.flowed)
        now = self.energy(solver)
        if ref > 0.0 and now > (1.0 + self.RISE) * ref:
            self.said = (frame, now / ref - 1.0)
            log.warning("frame %d: the fluid's energy (kinetic + gravitational) is %.0f %% above the start's%s, with "
                        "nothing in the scene to give it: energy the method made (%s); check the frames, or try a "
                        "finer spacing or another solver", frame, 100.0 * self.said[1],
                        " and what the inflows brought" if solver.inflows else "", self.causes(solver))

    @staticmethod
    def causes(solver: "SolverBase") -> str:
        """What is known to make energy: said for every solver, a U-tube 6 spacings wide was told to look for a
        passage narrower than 3 (DFSPH's own churn, which grows with a finer spacing there: session 46's tester)."""
        known = "a passage narrower than about 3 spacings, a time step too long"
        if hasattr(solver, "kappa_v"):
            return known + ", or DFSPH's churn in slow or still water (README, Water at rest): try simulate: {use: sph}"
        return known + "?"


def _blow_up_line(e: BlowUp, frame: int, solver: Solver, solver_name: str, ckpt_dir: Path | None) -> str:
    """The one-line report of a blow-up; the solver's state is saved beside the checkpoints (a name
    the resume never picks up) for inspection."""
    where = "no checkpoint folder to save the state in"
    if ckpt_dir is not None:
        ckpt_dir.mkdir(parents=True, exist_ok=True)
        path = ckpt_dir / f"blowup_{frame:05d}.npz"
        np.savez(path, **solver.state())
        where = f"state saved in {path}"
    return f"the {solver_name} run blew up during frame {frame}: {e} ({where})"


def _frame_stats(stats: dict, fr: ParticleFrame, solver: Solver) -> None:
    err = np.maximum(fr.rho / solver.rho0 - 1.0, 0.0)
    stats["density_error_mean"].append(float(err.mean()) if len(err) else 0.0)
    stats["density_error_max"].append(float(err.max()) if len(err) else 0.0)
    stats["inside_wall"].append(int((solver.d < -0.01 * solver.l0).sum()))
    # the fluid's bounding box per frame: a dam break's surge front is extent_max along the flow
    stats["extent_min"].append(fr.x.min(axis=0).tolist() if len(fr.x) else [0.0, 0.0, 0.0])
    stats["extent_max"].append(fr.x.max(axis=0).tolist() if len(fr.x) else [0.0, 0.0, 0.0])


def _stats_to(stats: dict) -> dict:
    out = {f"stat_{k}": np.asarray(stats[k]) for k in _LIST_STATS}
    out.update(stat_dropped_in_wall=np.int64(stats["dropped_in_wall"]), stat_emitted=np.int64(stats["emitted"]),
               stat_dropped_outside_domain=np.int64(stats["dropped_outside_domain"]),
               stat_escaped=np.int64(stats["escaped"]),
               stat_wall_seconds=np.float64(stats["wall_seconds"]))
    return out


def _stats_from(state: dict, stats: dict) -> dict:
    stats = dict(stats)
    for k in _LIST_STATS:
        stats[k] = state[f"stat_{k}"].tolist()
    stats["dropped_in_wall"] = int(state["stat_dropped_in_wall"])
    stats["dropped_outside_domain"] = int(state.get("stat_dropped_outside_domain", 0))  # older checkpoints: none
    stats["escaped"] = int(state.get("stat_escaped", 0))
    stats["emitted"] = int(state["stat_emitted"])
    stats["wall_seconds"] = float(state["stat_wall_seconds"])
    return stats
