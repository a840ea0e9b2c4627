"""The stability suite (issue 17): hard cases each solver must survive without blowing up, leaking
through walls or creating energy. ``run_case`` runs one (case, solver) and measures what the table
shows; test_stability.py asserts on the short runs, and

    make stability        (python tests/stability/stability_cases.py --long)

runs the long version and prints the table: case, solver, steps, max density error, particles
inside walls, escaped, max speed / the scene's ballistic bound (at the samples, and its peak over every
step), energy at the end / at the start, wall time.

Cases are built in SI as the pipeline hands them to a solver (driver.prepare: emitted lattice, the
particles within l0/2 of a wall dropped; driver.drive: the hydrostatic start, the blow-up guard)."""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from stages.common.sdf import SDFGrid, box_interior_sdf, grid_from_function  # noqa: E402
from stages.simulate.driver import BlowUp, Guard, SPEED_LIMIT, hydrostatic_start  # noqa: E402
from stages.simulate.emitters import drop_inside_walls, drop_overlaps, lattice  # noqa: E402

G = 9.81
RHO0 = 1000.0
MU = 0.001  # water
SOLVERS = ("sph", "sph_poly6", "dfsph", "mps")  # sph: the cubic spline (the default); sph_poly6: kernel: poly6_spiky


@dataclass
class Scene:
    """A case in SI: particles, walls, and what it expects."""
    x: np.ndarray
    v: np.ndarray
    sdf: SDFGrid
    l0: float
    gravity: np.ndarray
    mu: float = MU
    params: dict = field(default_factory=dict)  # per-solver parameter overrides {solver: {...}}
    expect_blowup: bool = False  # the case asks for a step far above the stable one
    below: float | None = None  # the thin plate's top: particles that start above may not end below it
    dropped: int = 0

    @property
    def v_bound(self) -> float:
        """The ballistic bound as driver.ballistic_speed computes it for a pipeline run."""
        from stages.simulate.driver import ballistic_speed
        up = -self.gravity / max(np.linalg.norm(self.gravity), 1e-30)
        if not np.any(self.gravity):
            up = np.array([0.0, 0.0, 1.0])
        return ballistic_speed(_SetupView(self, up))


@dataclass
class _SetupView:
    """What ballistic_speed reads of a driver.Setup."""
    scene: Scene
    up: np.ndarray

    def __getattr__(self, name):
        s = self.scene
        return {"v": s.v, "x": s.x, "gravity": s.gravity, "domain": None, "sdf": s.sdf, "spacing": s.l0, "inflows": [],
                "bodies": [], "effects": None, "density": 1000.0}[name]


class _Quiet:
    def warning(self, *a, **k):
        pass

    info = warning


def _walls(fn, lo, hi, l0) -> SDFGrid:
    return grid_from_function(fn, lo, hi, 0.5 * l0)


def _emit(x, v, sdf, l0):
    x, v, _ = drop_overlaps(x, v, l0, _Quiet())
    x, v, dropped = drop_inside_walls(x, v, sdf, l0, _Quiet())
    return x, v, dropped


def _scene(x, sdf, l0, v=None, gravity=(0, 0, -G), **kw) -> Scene:
    v = np.zeros_like(x) if v is None else np.broadcast_to(np.asarray(v, float), x.shape).copy()
    x, v, dropped = _emit(x, v, sdf, l0)
    return Scene(x=x, v=v, sdf=sdf, l0=l0, gravity=np.asarray(gravity, float), dropped=dropped, **kw)


# -- the cases (CI size; ``scale`` multiplies every length for the unit cases) ---------------------
def rest(scale=1.0, l0=0.025):
    """bench_rest.py's tank (0.3 x 0.2 m, 0.25 m deep) at a CI spacing."""
    lo, hi = np.zeros(3), np.array([0.3, 0.2, 0.35]) * scale
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0 * scale)
    return _scene(lattice(lo, [0.3 * scale, 0.2 * scale, 0.25 * scale], l0 * scale), sdf, l0 * scale)


def rest_cylinder(l0=0.025):
    """Water at rest in a cylindrical tank (radius 0.12 m, filled 0.2 m deep): a curved side wall, off the SDF's
    nodes nearly everywhere (sdf_bake can put a box tank's flat walls on them, not a curved one)."""
    lo, hi = np.zeros(3), np.array([0.3, 0.3, 0.35])
    centre = np.array([0.15, 0.15])

    def fn(p):
        r = np.hypot(p[:, 0] - centre[0], p[:, 1] - centre[1])
        return np.minimum(np.minimum(0.12 - r, p[:, 2]), hi[2] - p[:, 2])

    return _scene(lattice(lo, [0.3, 0.3, 0.2], l0), _walls(fn, lo, hi, l0), l0)


def rest_bowl(l0=0.025):
    """Water at rest in a hemispherical bowl (radius 0.15 m, filled 0.2 m deep, its rim a cylinder): a wall
    curved in both directions and sloping where the free surface meets it."""
    lo, hi = np.zeros(3), np.array([0.3, 0.3, 0.35])
    centre = np.array([0.15, 0.15, 0.15])

    def fn(p):
        q = p - centre
        rim = np.minimum(0.15 - np.hypot(q[:, 0], q[:, 1]), hi[2] - p[:, 2])
        return np.where(q[:, 2] < 0, 0.15 - np.linalg.norm(q, axis=1), rim)

    return _scene(lattice(lo, [0.3, 0.3, 0.2], l0), _walls(fn, lo, hi, l0), l0)


def dam_break(scale=1.0, l0=0.02):
    """A 0.1 x 0.1 x 0.2 m column released against the far wall of a 0.4 m tank."""
    lo, hi = np.zeros(3), np.array([0.4, 0.1, 0.3]) * scale
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0 * scale)
    return _scene(lattice(lo, np.array([0.1, 0.1, 0.2]) * scale, l0 * scale), sdf, l0 * scale)


def jet(l0=0.02):
    """A 0.08 m block at 10 m/s into the wall of a 0.5 m tank (no gravity needed to hit hard)."""
    lo, hi = np.zeros(3), np.array([0.5, 0.12, 0.2])
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0)
    x = lattice([0.3, 0.02, 0.0], [0.38, 0.10, 0.08], l0)
    return _scene(x, sdf, l0, v=(10.0, 0.0, 0.0))


def thin_plate(l0=0.02):
    """A block falling 0.1 m onto a horizontal plate 0.2 l0 thick spanning the tank at z = 0.1 m."""
    lo, hi = np.zeros(3), np.array([0.2, 0.2, 0.4])
    zp, half = 0.1, 0.1 * l0
    box = box_interior_sdf(lo, hi)

    def fn(p):
        return np.minimum(box(p), np.abs(p[:, 2] - zp) - half)

    sdf = _walls(fn, lo, hi, l0)
    x = lattice([0.04, 0.04, 0.2], [0.16, 0.16, 0.28], l0)
    return _scene(x, sdf, l0, below=zp)


def wedge(l0=0.02, angle_deg=20.0, apex_x=0.15):
    """A V trough of ``angle_deg`` opening (apex line along y at x = ``apex_x``, z = 0; the default 0.15 lies on
    an SDF node plane): water poured into it meets a sharp concave corner (the ridge below is the convex one)."""
    lo, hi = np.zeros(3), np.array([0.3, 0.1, 0.45])
    half = math.radians(0.5 * angle_deg)
    box = box_interior_sdf(lo, hi)
    n1 = np.array([math.cos(half), 0.0, math.sin(half)])  # inward normals of the two planes
    n2 = np.array([-math.cos(half), 0.0, math.sin(half)])
    apex = np.array([apex_x, 0.0, 0.0])

    def fn(p):
        q = p - apex
        return np.minimum(box(p), np.minimum(q @ n1, q @ n2))

    sdf = _walls(fn, lo, hi, l0)
    x = lattice([apex_x - 0.06, 0.0, 0.25], [apex_x + 0.06, 0.1, 0.37], l0)
    return _scene(x, sdf, l0)


def ridge(l0=0.02, angle_deg=20.0, apex_x=0.15):
    """A knife-edge ridge of ``angle_deg`` (its edge along y at x = ``apex_x``, z = 0.15 m) on the floor: water
    dropped onto the edge splits around a sharp convex corner (the fluid's region is not convex), as it does over
    a blade, a fin or a roof's ridge."""
    lo, hi = np.zeros(3), np.array([0.3, 0.1, 0.45])
    half = math.radians(0.5 * angle_deg)
    box = box_interior_sdf(lo, hi)
    apex = np.array([apex_x, 0.15])
    down = [np.array([math.sin(half), -math.cos(half)]), np.array([-math.sin(half), -math.cos(half)])]  # the faces

    def fn(p):
        q = p[:, [0, 2]] - apex
        d = np.full(len(p), np.inf)
        for e in down:  # the distance to each face (a half-line from the edge down), exact past the edge too
            s = np.maximum(q @ e, 0.0)[:, None]
            d = np.minimum(d, np.linalg.norm(q - s * e, axis=1))
        normals = [np.array([-e[1], e[0]]) * (1 if e[0] > 0 else -1) for e in down]  # outward, away from the solid
        inside = np.all([q @ m < 0 for m in normals], axis=0)
        return np.minimum(box(p), np.where(inside, -d, d))

    sdf = _walls(fn, lo, hi, l0)
    x = lattice([apex_x - 0.06, 0.0, 0.25], [apex_x + 0.06, 0.1, 0.37], l0)
    return _scene(x, sdf, l0)


def cone(l0=0.02, angle_deg=40.0, apex=(0.15, 0.15)):
    """A cone closed at its apex (``angle_deg`` opening, its axis vertical through ``apex`` in x, y, the apex on
    the floor, on an SDF node at 2 cm): water poured into it converges on a sharp concave point."""
    lo, hi = np.zeros(3), np.array([0.3, 0.3, 0.45])
    half = math.radians(0.5 * angle_deg)
    box = box_interior_sdf(lo, hi)
    line = np.array([math.sin(half), math.cos(half)])  # the surface's meridian, (r, z) from the apex
    inward = np.array([-math.cos(half), math.sin(half)])

    def fn(p):
        q = np.stack([np.hypot(p[:, 0] - apex[0], p[:, 1] - apex[1]), p[:, 2]], axis=1)
        d = np.where(q @ line < 0, -np.linalg.norm(q, axis=1), q @ inward)
        return np.minimum(box(p), d)

    sdf = _walls(fn, lo, hi, l0)
    r = 0.25 * math.tan(half)  # the block fits the cone where it starts
    x = lattice([apex[0] - r, apex[1] - r, 0.25], [apex[0] + r, apex[1] + r, 0.37], l0)
    return _scene(x, sdf, l0)


def slot(l0=0.02, width=1.5):
    """A column of water in a slot 1.5 spacings wide (one particle across after the wall gap)."""
    lo, hi = np.zeros(3), np.array([width * l0, 0.1, 0.3])
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0)
    x = lattice([0.0, 0.0, 0.0], [2 * l0, 0.1, 0.2], l0)
    x[:, 0] = 0.5 * width * l0  # centred in the slot
    x = np.unique(np.round(x, 9), axis=0)
    return _scene(x, sdf, l0)


def start_in_wall(l0=0.02):
    """An emitter box overlapping the floor and a side wall, with a row exactly on the wall: the
    pipeline drops those within l0/2 of a wall; the rest must start clear."""
    lo, hi = np.zeros(3), np.array([0.2, 0.1, 0.3])
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0)
    x = lattice([-0.05, -0.03, -0.05], [0.1, 0.13, 0.15], l0) + 0.5 * l0  # rows on x, y, z = 0 and beyond
    return _scene(x, sdf, l0)


def overlapping_emitters(l0=0.02):
    """Two emitter boxes overlapping by half: the overlap holds two particles at the same point."""
    lo, hi = np.zeros(3), np.array([0.3, 0.1, 0.3])
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0)
    a = lattice([0.0, 0.0, 0.0], [0.12, 0.1, 0.12], l0)
    b = lattice([0.06, 0.0, 0.0], [0.18, 0.1, 0.12], l0)
    return _scene(np.vstack([a, b]), sdf, l0)


def one_particle(l0=0.02):
    lo, hi = np.zeros(3), np.array([0.2, 0.2, 0.3])
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0)
    return _scene(np.array([[0.1, 0.1, 0.2]]), sdf, l0)


def two_particles(l0=0.02):
    lo, hi = np.zeros(3), np.array([0.2, 0.2, 0.3])
    sdf = _walls(box_interior_sdf(lo, hi), lo, hi, l0)
    return _scene(np.array([[0.1, 0.1, 0.2], [0.1 + 0.7 * l0, 0.1, 0.2 + 0.7 * l0]]), sdf, l0)


def huge_time_step(l0=0.02):
    """The dam break with a fixed step 20 x above the stable one (DFSPH: its largest step raised to
    a frame and cfl 1): a blow-up must stop the run, never end in silent loss."""
    s = dam_break(l0=l0)
    s.params = {"sph": {"time_step": 0.005}, "mps": {"time_step": 0.02}, "dfsph": {"dt_max": 0.04, "cfl": 1.0}}
    s.expect_blowup = True
    return s


def extreme_viscosity(l0=0.02):
    """The dam break in a fluid 100,000 x as viscous as water (mu = 100 Pa s, about a heavy tar)."""
    s = dam_break(l0=l0)
    s.mu = 100.0
    return s


def millimetres():
    """The dam break 100 x smaller (4 mm tank, 0.2 mm spacing): the same flow at its own scale."""
    return dam_break(scale=0.01)


def kilometres():
    """The dam break 10,000 x larger (a 4 km tank, 200 m spacing)."""
    return dam_break(scale=1e4)


def _tank_mesh(size, cells: int):
    """A closed box tank's surface (0 to ``size``), each face a grid of ``cells`` x ``cells`` quads (two
    triangles each), as a modelling tool exports it."""
    import trimesh
    box = trimesh.creation.box(extents=size)
    box.apply_translation(0.5 * np.asarray(size, float))
    verts, faces = box.vertices, box.faces
    for _ in range(int(math.log2(cells))):
        verts, faces = trimesh.remesh.subdivide(verts, faces)
    return np.asarray(verts), np.asarray(faces)


def _mesh_scene(verts, faces, x, l0) -> Scene:
    """The fluid ``x`` inside the tank mesh, its walls through the pipeline's mesh_import (clean-up) and
    sdf_bake (sign by ray voting, the default) stages, as a pipeline run reads an exported model."""
    import tempfile

    import trimesh

    from pipeline.testing import run_stage
    from stages.mesh_import.trimesh_import import TrimeshImport
    from stages.sdf_bake.open3d_bake import Open3dBake

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        trimesh.Trimesh(verts, faces, process=False).export(tmp / "tank.ply")
        lo, hi = x.min(axis=0), x.max(axis=0)
        scene = {"scene": {"name": "mesh_case"}, "walls": [{"file": "tank.ply", "fluid": "inside"}],
                 "fluid": {"spacing": l0, "emitters": [{"box": {"min": lo.tolist(), "max": hi.tolist()}}]}}
        walls = run_stage(TrimeshImport, tmp / "walls", scene=scene, config_dir=tmp)
        sdf = SDFGrid.load(run_stage(Open3dBake, tmp / "sdf", scene=scene, inputs={"walls": walls}))
    return _scene(x, sdf, l0)


def cracked_tank(l0=0.02):
    """The dam break in a tank model that is not watertight: a triangle missing in the far wall where the
    surge hits (0.6 x 1.9 spacings) and one in the floor (2.5 x 0.6): the slivers a scan or a boolean leaves."""
    size = [0.4, 0.1, 0.3]
    verts, faces = _tank_mesh(size, 8)
    centres = verts[faces].mean(axis=1)
    holes = [int(np.argmin(np.linalg.norm(centres - c, axis=1))) for c in ([0.4, 0.05, 0.05], [0.3, 0.05, 0.0])]
    faces = np.delete(faces, holes, axis=0)
    return _mesh_scene(verts, faces, lattice(np.zeros(3), [0.1, 0.1, 0.2], l0), l0)


def dirty_tank(l0=0.02):
    """The dam break in a tank model with every face duplicated (one copy reversed), zero-area faces (a
    repeated vertex and three collinear ones) and unwelded vertices, as exports often are."""
    size = [0.4, 0.1, 0.3]
    verts, faces = _tank_mesh(size, 4)
    soup = verts[faces].reshape(-1, 3)  # unwelded: every triangle its own three vertices
    tri = np.arange(len(soup)).reshape(-1, 3)
    dup = tri[:, ::-1] + len(soup)  # the same faces again, wound the other way
    soup = np.vstack([soup, soup, [[0.2, 0.05, 0.0], [0.25, 0.05, 0.0], [0.3, 0.05, 0.0]]])
    n = len(soup)
    degenerate = np.array([[0, 0, 1], [n - 3, n - 2, n - 1]])
    return _mesh_scene(soup, np.vstack([tri, dup, degenerate]), lattice(np.zeros(3), [0.1, 0.1, 0.2], l0), l0)


CASES: dict[str, Callable[[], Scene]] = {
    "rest": rest, "rest_cylinder": rest_cylinder, "rest_bowl": rest_bowl, "dam_break": dam_break, "jet_10ms": jet,
    "thin_plate": thin_plate, "wedge_20deg": wedge, "ridge_20deg": ridge, "cone_40deg": cone, "slot_1.5l0": slot,
    "start_in_wall": start_in_wall, "overlapping_emitters": overlapping_emitters, "one_particle": one_particle,
    "two_particles": two_particles, "huge_time_step": huge_time_step, "extreme_viscosity": extreme_viscosity,
    "millimetres": millimetres, "kilometres": kilometres, "cracked_tank": cracked_tank, "dirty_tank": dirty_tank,
}
RESTING = ("rest", "rest_cylinder", "rest_bowl")  # judged at rest (test_stability.assert_at_rest)
# simulated seconds of the short (CI) and long runs; the resting tank's long run is 20,000 steps
# the scaled dam breaks run the same number of steps: times scale with sqrt(length)
# the resting tanks run 3 s in CI as well: the start's transient takes about a second to decay (0.3 s measured the
# transient, 0.03 m/s for every solver), and the verdict is over the last half second (test_stability.py)
SHORT = {"rest": 3.0, "rest_cylinder": 3.0, "rest_bowl": 3.0, "dam_break": 0.3, "jet_10ms": 0.05, "thin_plate": 0.3,
         "wedge_20deg": 0.3, "ridge_20deg": 0.3, "cone_40deg": 0.3, "slot_1.5l0": 0.2, "start_in_wall": 0.2,
         "overlapping_emitters": 0.2, "one_particle": 0.3, "two_particles": 0.3, "huge_time_step": 0.2,
         "extreme_viscosity": 0.1, "millimetres": 0.03, "kilometres": 30.0, "cracked_tank": 0.3, "dirty_tank": 0.3}
LONG = {"rest_cylinder": 6.0, "rest_bowl": 6.0, "dam_break": 2.0, "jet_10ms": 0.3, "thin_plate": 1.0,
        "wedge_20deg": 1.5, "ridge_20deg": 1.5, "cone_40deg": 1.5, "slot_1.5l0": 1.0, "start_in_wall": 1.0,
        "overlapping_emitters": 1.0, "one_particle": 1.0, "two_particles": 1.0, "huge_time_step": 0.5,
        "extreme_viscosity": 0.5, "millimetres": 0.2, "kilometres": 200.0, "cracked_tank": 2.0, "dirty_tank": 2.0}
REST_LONG_STEPS = 20000
# the long resting tank advances a 30 fps frame at a time, as the pipeline does, so every solver takes its own
# steps (1 ms advances held DFSPH and MPS to steps of 0.5 ms, a tenth and a quarter of theirs: not what a user runs)
REST_LONG_FRAME = 1.0 / 30.0
SAMPLES = 10  # measurements per run
# the resting tanks' speed is averaged over windows: sampled every 0.1 s in CI
SAMPLES_OF = dict.fromkeys(RESTING, 30)
# issue 17's goal at bench_rest's spacing: a mean speed below 0.005 m/s at l0 = 1.25 cm; speeds of the same motion
# scale as sqrt(g l0) (Froude), so a tank at another spacing is held to 0.005 sqrt(l0 / 1.25 cm)
REST_FLOOR, REST_FLOOR_SPACING = 0.005, 0.0125


def rest_floor(l0: float) -> float:
    """The resting tank's mean-speed floor, m/s, at spacing l0 (m)."""
    return REST_FLOOR * math.sqrt(l0 / REST_FLOOR_SPACING)


def rest_summary(r) -> dict:
    """The resting tank's verdict figures from a Result: the mean speed averaged over the run's last sixth (late)
    and over its third to its half (early: 1-1.5 s of the CI run), the floor at its spacing, and the free surface's
    change over the whole run and its range over the second half, in l0."""
    t_end = r.speeds[-1][0]
    early = (t_end / 3, t_end / 2)
    half = [h for t, h in r.surfaces if t >= t_end / 2 - 1e-9]
    return {"late": float(np.mean([v for t, v in r.speeds if t > t_end * 5 / 6 - 1e-9])),
            "early": float(np.mean([v for t, v in r.speeds if early[0] - 1e-9 <= t <= early[1] + 1e-9])),
            "early_window": early, "floor": rest_floor(r.l0), "drift": r.surface_drift,
            "drift_second_half": max(half) - min(half)}


def make_solver(name: str, s: Scene):
    ids = np.arange(len(s.x))
    g = s.gravity
    params = s.params.get(name, {})
    vref = s.v_bound
    if name in ("sph", "sph_poly6"):
        from stages.simulate.sph import SPHParams, SPHSolver
        if name == "sph_poly6":
            params = {**s.params.get("sph", {}), "kernel": "poly6_spiky"}
        sol = SPHSolver(s.x, s.v, ids, s.sdf, spacing=s.l0, rho0=RHO0, params=SPHParams(**params), gravity=g,
                        mu=s.mu, v_ref=vref)
    elif name == "dfsph":
        from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
        sol = DFSPHSolver(s.x, s.v, ids, s.sdf, spacing=s.l0, rho0=RHO0, params=DFSPHParams(**params), gravity=g,
                          mu=s.mu)
    elif name == "mps":
        from stages.simulate.mps import MPSParams, MPSSolver
        sol = MPSSolver(s.x, s.v, ids, s.sdf, spacing=s.l0, rho0=RHO0, params=MPSParams(**params), gravity=g,
                        mu=s.mu, v_ref=vref)
    else:
        raise ValueError(name)
    hydrostatic_start(sol)
    # the guard as driver.drive sets it (its energy test included)
    sol.guard = PeakGuard.with_energy(s.v_bound, s.l0, s.gravity, np.array(_corners(s.sdf)))
    return sol


class PeakGuard(Guard):
    """The blow-up guard, also keeping the fastest particle's speed over every step: a spike between two samples
    is a spike (before session 37 the MPS wedge's reached up to 9.5 x the bound within a step, unseen at the
    samples)."""
    peak = 0.0

    def check(self, solver, dt: float, last_of_frame: bool) -> None:
        super().check(solver, dt, last_of_frame)
        if len(solver.v):
            self.peak = max(self.peak, float(np.sqrt(np.einsum("ij,ij->i", solver.v, solver.v).max())))


def energy(sol, s: Scene, floor: float) -> tuple[float, float]:
    """(total kinetic + potential energy, J; the largest specific energy of one particle, J/kg), the
    potential from the lowest wall point."""
    gn = float(np.linalg.norm(s.gravity))
    up = -s.gravity / gn if gn else np.array([0.0, 0.0, 1.0])
    spec = 0.5 * np.einsum("ij,ij->i", sol.v, sol.v) + gn * (sol.x @ up - floor)
    return float(sol.mass * spec.sum()), float(spec.max()) if len(spec) else 0.0


@dataclass
class Result:
    case: str
    solver: str
    steps: int = 0
    density_error_max: float = 0.0
    inside_walls: int = 0
    escaped: int = 0
    through_plate: int = 0
    speed_ratio: float = 0.0  # the fastest particle at the samples / the bound
    peak_ratio: float = 0.0  # the fastest particle over every step / the bound
    energy_ratio: float = 1.0
    wall_seconds: float = 0.0
    blowup: str | None = None
    particles: int = 0
    mean_speed_end: float = 0.0
    surface_drift: float = 0.0  # the free surface's height change over the run / l0 (rest only)
    front: float = 0.0  # the fluid's largest x at the end over the walls' length along x (the surge front)
    speeds: list = field(default_factory=list)  # (t, mean speed) per sample
    surfaces: list = field(default_factory=list)  # (t, free-surface height / l0) per sample
    l0: float = 0.0  # the scene's spacing, m

    def row(self) -> str:
        status = ("BLOW-UP CAUGHT" if self.blowup else "ok")
        return (f"{self.case:<21}{self.solver:<7}{self.steps:>7}{100 * self.density_error_max:>9.2f}%"
                f"{self.inside_walls:>7}{self.escaped:>8}{self.speed_ratio:>9.2f}{self.peak_ratio:>7.2f}"
                f"{self.energy_ratio:>9.3f}{self.wall_seconds:>8.1f}{self.mean_speed_end:>9.4f}  {status}")


HEADER = (f"{'case':<21}{'solver':<7}{'steps':>7}{'max drho':>10}{'inside':>7}{'escaped':>8}{'v/bound':>9}"
          f"{'peak':>7}{'E end/0':>9}{'wall s':>8}{'v mean':>9}")


def _surface(x, up, l0) -> float:
    h = x @ up
    return float(h[h > h.max() - 0.5 * l0].mean()) if len(h) else 0.0


def run_case(case: str, solver: str, long: bool = False) -> Result:
    s = CASES[case]()
    res = Result(case, solver, particles=len(s.x), l0=s.l0)
    sol = make_solver(solver, s)
    gn = float(np.linalg.norm(s.gravity))
    up = -s.gravity / gn if gn else np.array([0.0, 0.0, 1.0])
    floor = float(min((c @ up) for c in _corners(s.sdf)))
    e0, _ = energy(sol, s, floor)
    surf0 = _surface(sol.x, up, s.l0)
    above = sol.x[:, 2] > s.below if s.below is not None else None
    ids_above = set(sol.id[above].tolist()) if above is not None else set()
    t0 = time.perf_counter()
    rest_steps = case == "rest" and long
    t_end = SHORT[case] if not long else LONG.get(case, 0.0)
    samples = SAMPLES_OF.get(case, SAMPLES)
    k = 0
    try:
        while True:
            k += 1
            if rest_steps:
                target = REST_LONG_STEPS * k // samples
                while sol.steps < target:
                    sol.advance_to(sol.t + REST_LONG_FRAME)
            else:
                sol.advance_to(t_end * k / samples)
            _measure(res, sol, s, up)
            if (rest_steps and sol.steps >= REST_LONG_STEPS) or (not rest_steps and k >= samples):
                break
    except BlowUp as e:
        res.blowup = str(e)
    res.wall_seconds = time.perf_counter() - t0
    res.steps = sol.steps
    res.peak_ratio = sol.guard.peak / s.v_bound
    if res.blowup is None:
        e1, _ = energy(sol, s, floor)
        res.energy_ratio = e1 / e0 if e0 > 0 else 0.0
        res.escaped += int(sol.left_domain)
        if s.below is not None:
            z = dict(zip(sol.id.tolist(), sol.x[:, 2].tolist()))
            res.through_plate = sum(1 for i in ids_above if i in z and z[i] < s.below)
        res.surface_drift = (_surface(sol.x, up, s.l0) - surf0) / s.l0
        if len(sol.x):
            lo, hi = s.sdf.origin[0] + s.sdf.spacing, s.sdf.upper[0] - s.sdf.spacing  # grid_from_function pads one cell
            res.front = float((sol.x[:, 0].max() - lo) / (hi - lo))
    return res


def _corners(sdf: SDFGrid):
    lo, hi = sdf.origin, sdf.upper
    return [np.array([a, b, c]) for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])]


def _measure(res: Result, sol, s: Scene, up) -> None:
    f = sol.frame()
    sol.remove_escaped()
    if len(f.x) == 0:
        return
    if len(f.rho):
        res.density_error_max = max(res.density_error_max, float(np.max(f.rho / RHO0 - 1.0)))
    res.inside_walls = max(res.inside_walls, int((sol.d < -0.01 * s.l0).sum()))
    sp = np.linalg.norm(f.v, axis=1)
    res.speed_ratio = max(res.speed_ratio, float(sp.max()) / s.v_bound)
    res.mean_speed_end = float(sp.mean())
    res.speeds.append((sol.t, float(sp.mean())))
    res.surfaces.append((sol.t, _surface(f.x, up, s.l0) / s.l0))


def main() -> None:
    ap = argparse.ArgumentParser(description="the stability suite's table")
    ap.add_argument("--long", action="store_true")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--solvers", default=",".join(SOLVERS))
    a = ap.parse_args()
    import numba as nb
    nb.set_num_threads(min(2, nb.config.NUMBA_NUM_THREADS))
    print(f"speed limit of the blow-up guard: {SPEED_LIMIT:g} x the ballistic bound")
    print(HEADER, flush=True)
    for case in a.cases.split(","):
        for solver in a.solvers.split(","):
            r = run_case(case, solver, long=a.long)
            print(r.row(), flush=True)
            if case in RESTING and r.blowup is None:
                f = rest_summary(r)
                print(f"    mean speed over {f['early_window'][0]:.2g}-{f['early_window'][1]:.2g} s {f['early']:.4f}, over the "
                      f"last sixth {f['late']:.4f} m/s (floor {f['floor']:.4f}); free surface {f['drift']:+.3f} l0, "
                      f"{f['drift_second_half']:.3f} l0 over the second half", flush=True)
            if r.blowup:
                print(f"    {r.blowup}", flush=True)


if __name__ == "__main__":
    main()
