"""Sizes of a run from the config alone (before any stage runs), for the stages' ``estimate`` hooks:
particle counts of the emitters, the box the SDF grid covers, and the simulation's step count and
memory. Estimates, not promises: mesh emitters, and the bounds of walls read from files when
scene.domain is not set, are unknown until loaded."""
from __future__ import annotations

import math

import numpy as np

# memory per particle of the solvers' arrays, neighbour lists and wall maps (README: under 1 KB per
# particle measured for WCSPH at 20k-100k); bytes per SDF node while baking (float32 distance, the
# sign and exact-distance work arrays)
BYTES_PER_PARTICLE = 1024
BYTES_PER_SDF_NODE = 24
# a size within this many spacings of a whole number of them counts as that number
LATTICE_SLACK = 1e-4


def lattice_counts(lo, hi, l0: float) -> np.ndarray:
    """Lattice points per axis in the box [lo, hi): its size in whole spacings."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    # sizes typed to 6-7 digits after a unit conversion are a whole number of spacings to 1e-6 of it (a box of
    # 8 spacings in feet read 7.999994 and lost a layer, 23 % of the water); the tolerance also grows with the
    # coordinates: (hi - lo) of a box 1e7 m off the origin is off by ~1e-9 m, which dropped a whole row there
    slack = LATTICE_SLACK + 16 * np.finfo(float).eps * np.maximum(np.abs(lo), np.abs(hi)) / l0
    return np.floor((hi - lo) / l0 + slack).astype(int)


def emitted_particles(fluid, shot_seconds: float = 0.0) -> float | None:
    """Particles the emitters make on the l0 lattice (before those inside walls are dropped), plus what
    the inflows emit over a shot of ``shot_seconds`` (pi r^2 v per second); None when a mesh emitter
    makes it unknown."""
    if fluid is None:
        return None
    l0 = fluid.spacing
    n = 0.0
    for jet in fluid.inflow:
        seconds = max(min(jet.end if jet.end is not None else shot_seconds, shot_seconds) - jet.start, 0.0)
        n += math.pi * jet.radius ** 2 * jet.speed * seconds / l0 ** 3
    for em in fluid.emitters:
        if hasattr(em, "box"):
            # as the emitters count it (a spacing of 0.0066666667 m, 2/3 cm typed to 8 digits, lost a row along each
            # axis here without the lattice's slack: 1,525 particles planned for 2,232)
            n += float(np.prod(lattice_counts(em.box.min, em.box.max, l0).astype(float)))
        elif hasattr(em, "sphere"):
            n += 4.0 / 3.0 * math.pi * (em.sphere.radius / l0) ** 3
        else:
            return None
    return n


def _fluid_extent(fluid) -> float:
    ext = [float(np.max(np.asarray(em.box.max) - np.asarray(em.box.min))) if hasattr(em, "box") else 2 * em.sphere.radius
           for em in fluid.emitters]
    return max(ext, default=fluid.spacing)


def scene_box(scene) -> tuple[np.ndarray, np.ndarray] | None:
    """scene.domain, the box the SDF grid and the simulation cover; None when the walls' bounds decide
    (they are known only once mesh_import has run)."""
    if scene.domain is not None:
        return np.asarray(scene.domain.min, float), np.asarray(scene.domain.max, float)
    return None


def sdf_estimate(lo: np.ndarray, hi: np.ndarray, h: float) -> tuple[tuple[int, int, int], dict]:
    """The SDF node grid of spacing ``h`` from ``lo`` covering ``hi``: its shape (sdf_bake bakes this one),
    and its nodes and memory while baking. The tolerance keeps a box that is a whole number of spacings from
    gaining a row by rounding ((1.1 + 0.1) / 0.025 = 48.00000000000001), so the grid is the same in any unit."""
    shape = tuple(int(k) for k in np.ceil((np.asarray(hi, np.float64) - lo) / h - 1e-9) + 1)
    nodes = float(np.prod(np.asarray(shape, np.float64)))
    return shape, {"sdf_nodes": nodes, "memory_bytes": nodes * BYTES_PER_SDF_NODE}


def simulate_estimate(ctx, cfl: float, sound_factor: float | None, support: float = 2.0) -> dict | None:
    """Particles, steps and memory of a simulation. The step follows the solvers' limits: dt = cfl l0 /
    (v + c) with the reference speed v = sqrt(2 g H) (+ the fastest emitter) and the sound speed
    c = sound_factor v (weakly compressible; None for incompressible solvers), over count / fps seconds and the
    fluid's settling time.
    The SDF grid read by the solver is counted too (cell 0.5 l0, as sdf_bake's default)."""
    scene, fluid, effects = ctx.scene["scene"], ctx.scene["fluid"], ctx.scene.get("effects")
    n = emitted_particles(fluid, scene.frames.count / scene.frames.fps)
    if n is None:
        return None
    out: dict = {"particles": n, "memory_bytes": n * BYTES_PER_PARTICLE * (support / 2.0) ** 3}
    box = scene_box(scene)
    if box is not None:
        out["memory_bytes"] += float(np.prod(np.ceil((box[1] - box[0]) / (0.5 * fluid.spacing)) + 1)) * 4
    mpu = scene.units.meters_per_unit
    v = max([float(np.linalg.norm(em.velocity)) for em in fluid.emitters] + [jet.speed for jet in fluid.inflow],
            default=0.0) * mpu
    if effects is not None and effects.gravity is not None:
        height = float(np.max(box[1] - box[0])) if box is not None else _fluid_extent(fluid)
        v = max(v, math.sqrt(2.0 * effects.gravity.g * height * mpu))
    if v > 0:
        speed = v * (1.0 + (sound_factor or 0.0))
        dt = cfl * fluid.spacing * mpu / speed
        # the settling before t = 0 steps too (water_at_rest: ~800 steps said, 7,114 taken)
        out["steps"] = (scene.frames.count / scene.frames.fps + (getattr(fluid, "settle", 0.0) or 0.0)) / dt
    return out
