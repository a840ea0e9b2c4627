"""Continuous emitters (inflow) and sinks, in SI units; the stepping that uses them is in
driver.SolverBase (emit_inflow, drain_sinks), so every solver gets them.

An inflow is a round jet: the particles of the l0 lattice in the disc of radius r around the emitter's
centre, in the plane normal to its direction, emitted layer by layer at speed v. The disc holds
N_disc particles, whose area N_disc l0^2 is not exactly pi r^2; so a layer (N_disc l0^3 of fluid) is
emitted every T = N_disc l0^3 / (pi r^2 v) seconds, which makes the VOLUME rate exactly pi r^2 v (the
layers are then v T ~ l0 apart along the jet). Layer k stands for the fluid that crosses the emitter
plane during [t0 + k T, t0 + (k + 1) T]; it is emitted when that slab's centre crosses the plane, at
t_k = t0 + (k + 0.5) T, for every t_k < t1. The number of layers by time t is then round((t - t0) / T)
(never more than half a layer from the exact volume, and no drift: t_k is computed from k, not summed).
A layer due during a step is emitted at the step's start time t >= t_k where it would be by then:
x = centre + v (t - t_k) n + g (t - t_k)^2 / 2 (and its velocity v n + g (t - t_k)).

A nozzle on a moving wall (``attach``) carries its disc rigidly with the wall: layer k leaves the disc where
the wall has it at t_k, along the turned direction n(t_k), each point with v n(t_k) + the wall's velocity
there (u = v_pivot + omega x (p - pivot)). The volume per layer is unchanged (the jet's speed relative to the
nozzle is v), so the volume rate stays pi r^2 v."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from stages.common.motion import top_wall_speed


def disc_lattice(radius: float, l0: float) -> np.ndarray:
    """(N_disc, 2) in-plane offsets: the l0 lattice points (one on the axis) within ``radius``."""
    m = int(math.floor(radius / l0 + 1e-9))
    i, j = np.meshgrid(np.arange(-m, m + 1), np.arange(-m, m + 1), indexing="ij")
    ij = np.stack([i.ravel(), j.ravel()], axis=1).astype(np.float64) * l0
    return ij[np.einsum("ij,ij->i", ij, ij) <= radius * radius * (1.0 + 1e-9)]


def plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane normal to ``n``: for an axis-aligned jet, the lattice axes
    (so its layers line up with the fluid's lattice)."""
    a = np.zeros(3)
    a[int(np.argmin(np.abs(n)))] = 1.0  # the world axis least along n
    e1 = a - (a @ n) * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


@dataclass
class Inflow:
    """One jet in SI units. ``keep`` marks the disc points that are clear of the walls (and inside the
    domain); the layer period counts the whole disc, so a jet partly cut by a wall emits less than
    pi r^2 v (prepare warns)."""
    center: np.ndarray
    direction: np.ndarray  # unit
    radius: float
    speed: float
    start: float
    end: float  # math.inf: the end of the shot
    l0: float
    motion: object = None  # the RigidMotion (SI) of the wall the nozzle rides on; center/direction at rest

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, np.float64)
        self.direction = np.asarray(self.direction, np.float64) / np.linalg.norm(self.direction)
        self.disc = disc_lattice(self.radius, self.l0)
        self.keep = np.ones(len(self.disc), bool)
        # the volume rate pi r^2 v exactly (module docstring): not the disc's lattice area
        self.period = len(self.disc) * self.l0 ** 3 / (math.pi * self.radius ** 2 * self.speed)
        e1, e2 = plane_axes(self.direction)
        # the disc at rest; a moving nozzle turns it with the wall (not plane_axes of the turned direction,
        # whose axes jump when the direction passes between world axes)
        self.rest_disc = self.center + np.outer(self.disc[:, 0], e1) + np.outer(self.disc[:, 1], e2)
        # a layer is blocked where landing it packs it denser than the free jet packs its own layers (one
        # period behind the last: layers N_disc l0^3 / (pi r^2) apart), or than the fluid at rest spacing
        # (inflow_blocked)
        self.max_crowding = max(1.0, crowding(self.rest_disc, [self.rest_disc + self.speed * self.period
                                                               * self.direction], self.l0)) + 0.02

    def frame_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The emitter's centre and direction at time t (carried by the wall it is attached to)."""
        if self.motion is None:
            return self.center, self.direction
        r, tr = self.motion.pose(t)
        return r @ (self.center - self.motion.pivot) + self.motion.pivot + tr, r @ self.direction

    def wall_velocity(self, points: np.ndarray, t: float) -> np.ndarray:
        """The attached wall's velocity (N, 3) at world ``points`` at time t (zero for a fixed nozzle)."""
        if self.motion is None:
            return np.zeros_like(points)
        _, tr = self.motion.pose(t)
        v, w = self.motion.velocity(t)
        return v + np.cross(w, points - (self.motion.pivot + tr))

    def layer_time(self, k: int) -> float:
        return self.start + (k + 0.5) * self.period

    def due(self, k: int, t: float) -> bool:
        """Is layer k due by time t (and before the jet's end)?"""
        tk = self.layer_time(k)
        return tk <= t and tk < self.end

    def disc_points(self, t: float) -> np.ndarray:
        """The disc's lattice points in space at time t (all of them, walls or not)."""
        if self.motion is None:
            return self.rest_disc
        r, tr = self.motion.pose(t)
        return (self.rest_disc - self.motion.pivot) @ r.T + self.motion.pivot + tr

    def layer(self, k: int, t: float, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities at time t of layer k (emitted at its time t_k <= t)."""
        tk = self.layer_time(k)
        tau = t - tk
        _, n = self.frame_at(tk)
        p = self.disc_points(tk)[self.keep]
        u = self.wall_velocity(p, tk)  # zero for a fixed nozzle: then bitwise the fixed jet's arithmetic
        x = p + (self.speed * tau) * n + tau * u + (0.5 * tau * tau) * gravity
        v = self.speed * n + u + tau * gravity
        return np.ascontiguousarray(x), np.ascontiguousarray(v)

    def motion_times(self) -> np.ndarray:
        """The start and, for a moving nozzle, its wall's keys and the midpoints between them (the wall's
        v and omega are constant over a segment)."""
        ts = [self.start]
        if self.motion is not None:
            keys = np.asarray(self.motion.times, float)
            ts += [*keys, *(0.5 * (keys[:-1] + keys[1:]))]
        return np.array(ts)

    def swept_points(self) -> np.ndarray:
        """The disc at motion_times: where the jet can start from (the scene's height bounds)."""
        return np.concatenate([self.disc_points(t) for t in self.motion_times()])

    def top_speed(self) -> float:
        """A bound on the speed a particle leaves the nozzle with: v plus |v_pivot| + |omega| times the disc's
        reach from the pivot (which the rigid motion keeps) on each segment of the attached wall's motion."""
        if self.motion is None:
            return self.speed
        reach = float(np.linalg.norm(self.rest_disc - self.motion.pivot, axis=1).max())
        return self.speed + top_wall_speed(self.motion, reach)

    @property
    def volume_rate(self) -> float:
        return math.pi * self.radius ** 2 * self.speed


def inflow_blocked(layer: np.ndarray, fluid: list[np.ndarray], jet: Inflow) -> bool:
    """Would ``layer`` land on the ``fluid`` (the particles, and the layers emitted before it in this
    step)? Where it lands denser than the jet's ``max_crowding`` (a
    nozzle half a spacing above a puddle, its layer in the puddle's hollows 0.9 l0 from the nearest
    particle): the first step's pressure would throw it and the puddle out at several times the jet's
    speed (3 x the jet's 0.5 m/s, 3.7 x its specific energy, under a nozzle 0.55 l0 above resting water)."""
    return crowding(layer, fluid, jet.l0) > jet.max_crowding


@dataclass
class Sink:
    """An axis-aligned box (SI) removing the particles whose centre enters it."""
    lo: np.ndarray
    hi: np.ndarray


def in_sinks(x: np.ndarray, sinks) -> np.ndarray:
    """Which particles are in a sink: one numba pass (checked every step: numpy's took 1.5 ms at 20k particles)."""
    lo = np.array([s.lo for s in sinks], np.float64).reshape(-1, 3)
    hi = np.array([s.hi for s in sinks], np.float64).reshape(-1, 3)
    out = np.zeros(len(x), np.bool_)
    _in_boxes(x, lo, hi, out)
    return out


@nb.njit(cache=True, parallel=True)
def _in_boxes(x, lo, hi, out):
    for i in nb.prange(x.shape[0]):
        for b in range(lo.shape[0]):
            if (lo[b, 0] <= x[i, 0] <= hi[b, 0] and lo[b, 1] <= x[i, 1] <= hi[b, 1]
                    and lo[b, 2] <= x[i, 2] <= hi[b, 2]):
                out[i] = True
                break


def _spline(r: np.ndarray) -> np.ndarray:
    """The cubic spline of support 1 (unnormalised: 1 at r = 0)."""
    return np.where(r < 0.5, 6.0 * (r ** 3 - r ** 2) + 1.0, np.where(r < 1.0, 2.0 * (1.0 - r) ** 3, 0.0))


def _lattice_sum() -> float:
    g = np.arange(-2, 3, dtype=np.float64)
    return float(_spline(np.linalg.norm(np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3), axis=1) / 2.0).sum())


LATTICE_SUM = _lattice_sum()  # the number density of the l0 lattice, support 2 l0


def crowding(new: np.ndarray, others: list[np.ndarray], l0: float) -> float:
    """The largest number density among the points of ``new`` (a cubic spline of support 2 l0 over the
    points of ``new`` and of each array in ``others``), relative to the l0 lattice's: 1 is fluid at rest
    spacing, a free layer about 0.7. Only the points in the bounding box of ``new`` (grown by 2 l0) are
    summed: O(N) once, no copy of the fluid, then a small k-d tree."""
    if len(new) == 0:
        return 0.0
    from scipy.spatial import cKDTree
    reach = 2.0 * l0
    lo, hi = new.min(axis=0) - reach, new.max(axis=0) + reach
    pts = np.concatenate([new] + [x[np.all((x >= lo) & (x <= hi), axis=1)] for x in others])
    tree = cKDTree(pts)
    dist = tree.sparse_distance_matrix(cKDTree(new), reach, output_type="coo_matrix")
    sums = np.zeros(len(new))  # (each point's own zero distance is among the pairs)
    np.add.at(sums, dist.col, _spline(dist.data / reach))
    return float(sums.max() / LATTICE_SUM)


def from_config(fluid, meters_per_unit: float, motions: dict | None = None) -> tuple[list[Inflow], list[Sink]]:
    """The scene's inflows and sinks (pipeline.scene.Inflow / Sink, scene units) in SI. ``motions``: the
    moving walls' RigidMotion (SI) by their index in walls; an inflow attached to a wall not in it stands still."""
    m = meters_per_unit
    motions = motions or {}
    inflows = [Inflow(center=np.asarray(j.center, float) * m, direction=np.asarray(j.direction, float),
                      radius=j.radius * m, speed=j.speed * m, start=j.start,
                      end=j.end if j.end is not None else math.inf, l0=fluid.spacing * m,
                      motion=motions.get(j.attach) if j.attach is not None else None) for j in fluid.inflow]
    # a sink's faces 1e-6 l0 out: a lattice row on a face (a box written to the spacing) is inside in every unit
    # (at the bound itself, the scale's rounding decided: 96 of 108 removed in centimetres, 80 + 10 in metres)
    slack = SINK_SLACK * fluid.spacing * m
    sinks = [Sink(lo=np.asarray(s.box.min, float) * m - slack, hi=np.asarray(s.box.max, float) * m + slack)
             for s in fluid.sinks]
    return inflows, sinks


SINK_SLACK = 1e-6  # l0: far above a unit change's rounding (1e-15 l0), far below any motion
