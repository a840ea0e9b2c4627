"""Moving rigid walls in MPS (issue 18): each wall's MPS map baked once in its rest frame, sampled through its
pose (walls/mps.MPSWalls); the WCSPH checks of test_moving_walls.py with the MPS solver, water's viscosity
(mu = 0.001 Pa s) and its defaults:
- a body at its rest pose is the same wall as the static one; moved with the particles, the same again;
- sloshing: a tank swayed near its first natural frequency, then stopped, rings at f1 within 3 %;
- a paddle driven at constant speed into still water: no particle ever inside the paddle, and the fluid's
  energy gain stays below the paddle's work."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from stages.common.placement import rotation_xyz
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.simulate.mps import MPSParams, MPSSolver

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_moving_walls import Glide, Held, open_space, slab_sdf, sloshing_frequency  # noqa: E402

G = 9.81
MU = 0.001  # water


pytestmark = pytest.mark.usefixtures("one_numba_thread")  # (conftest.py)


class Turned:
    """A wall held turned by ``R`` about ``pivot`` (the RigidMotion interface)."""

    def __init__(self, R, pivot):
        self.R = np.asarray(R, float)
        self.pivot = np.asarray(pivot, float)

    def pose(self, t):
        return self.R.copy(), np.zeros(3)

    def velocity(self, t):
        return np.zeros(3), np.zeros(3)


def test_a_body_at_rest_is_the_static_wall_and_moves_with_its_pose():
    """A splashing block in a tank, one MPS step (prediction with viscosity, collision, number density, the
    Poisson solve, the corrected gradient, the projection): with the tank as the static wall, as a body at its
    rest pose over an empty static field, with the body and the particles translated by the same offset
    (velocities unchanged), and all turned (velocities and gravity too): the same number density, positions and
    velocities (turned back), to rounding."""
    l0 = 0.01
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.12, 0.08, 0.1])
    tank = grid_from_function(box_interior_sdf(lo, hi), lo, hi, 0.5 * l0)
    x = lattice([0.0, 0.0, 0.0], [0.06, 0.08, 0.06], l0)
    rng = np.random.default_rng(3)
    x = x + rng.uniform(-0.15, 0.15, x.shape) * l0
    v = rng.normal(0.0, 0.2, x.shape)
    kw = dict(spacing=l0, rho0=1000.0, params=MPSParams(time_step=1e-3), gravity=(0, 0, -G), mu=MU, v_ref=1.0)

    def one(sdf, x, bodies=()):
        s = MPSSolver(x, v, np.arange(len(x)), sdf, bodies=bodies, **kw)
        s.advance_to(1e-3)
        n = s.frame().rho
        order = np.argsort(s.id)
        return n[order], s.x[order], s.v[order], s.pr[order]

    n0, x0, v0, p0 = one(tank, x)
    assert (p0 > 0).sum() > 100  # a pressure field, not only free surface
    # turned about the tank's centre, with the particles, their velocities and gravity: the same state turned
    # (the vector and tensor wall sums turn with the body's pose)
    c = 0.5 * (lo + hi)
    R = rotation_xyz([20.0, -35.0, 50.0])
    space = open_space(c - 0.15, c + 0.15, 0.5 * l0)
    s = MPSSolver((x - c) @ R.T + c, v @ R.T, np.arange(len(x)), space, bodies=[(tank, Turned(R, c))],
                  **{**kw, "gravity": R @ [0.0, 0.0, -G]})
    s.advance_to(1e-3)
    n = s.frame().rho
    order = np.argsort(s.id)
    print("turned: max |dn| %.3g, |dx| %.3g, |dv| %.3g" % (np.abs(n[order] - n0).max(),
                                                           np.abs((s.x[order] - c) @ R + c - x0).max(),
                                                           np.abs(s.v[order] @ R - v0).max()))
    assert np.allclose(n[order], n0, rtol=1e-9, atol=0)
    assert np.abs((s.x[order] - c) @ R + c - x0).max() < 1e-9
    assert np.abs(s.v[order] @ R - v0).max() < 1e-6 * np.abs(v0).max()
    shift = np.array([0.031, -0.017, 0.023])
    for off in (np.zeros(3), shift):
        space = open_space(lo - 0.05 + np.minimum(off, 0), hi + 0.05 + np.maximum(off, 0), 0.5 * l0)
        n, x1, v1, p1 = one(space, x + off, [(tank, Held(off, pivot=0.5 * (lo + hi)))])
        print("max |dn| %.3g, |dx| %.3g, |dv| %.3g, |dp| %.3g" % (np.abs(n - n0).max(), np.abs(x1 - off - x0).max(),
                                                                   np.abs(v1 - v0).max(), np.abs(p1 - p0).max()))
        assert np.allclose(n, n0, rtol=1e-9, atol=0)
        assert np.abs(x1 - off - x0).max() < 1e-9
        assert np.abs(v1 - v0).max() < 1e-6 * np.abs(v0).max()


def test_sloshing_rings_at_the_first_natural_frequency():
    """test_moving_walls.sloshing_frequency with MPS: the same tank length and depth (f1 depends on those alone),
    half as wide (8 l0: the first mode is planar; MPS steps at 0.2 l0 / sqrt(2 g h), ~1600 steps with a Poisson
    solve each, so the full 0.2 m width takes ~100 s of CPU). On the mean of three starts 1e-4 l0 off the lattice,
    as the SPH test (one run's fit moves by ~1 % with such a perturbation: the exact lattice gave -2.7 % by the
    mode's velocity, -2.8 % at the wall; starts 0 and 1 -2.0 % and -1.7 %; by zero crossings, the full width:
    -0.6 %)."""
    runs = np.array([sloshing_frequency(width=0.1, solver=MPSSolver, params=MPSParams(), jitter_seed=seed)
                     for seed in range(3)])
    measured, at_wall, f1 = runs.mean(axis=0)
    print("MPS sloshing: %.4f Hz, at the wall %.4f Hz, f1 %.4f Hz (%+.2f %%, %+.2f %%)"
          % (measured, at_wall, f1, 100 * (measured / f1 - 1), 100 * (at_wall / f1 - 1)))
    assert abs(measured / f1 - 1.0) < 0.03, runs
    assert abs(at_wall / f1 - 1.0) < 0.03, runs


def test_a_paddle_pushes_water_without_entering_it_and_within_its_work():
    """Weightless water (a 6 x 8 x 8 l0 block) and a plate moving into it at U = 0.5 m/s: the plate's impulse on
    the fluid is the fluid's momentum (nothing else acts), so its work is U J_x; the fluid's kinetic energy gain
    never exceeds it, after any step (the wall is passive), and is a fair part of it (measured 0.80); the layer
    on the plate moves with it; no particle is ever found inside the plate (checked after every step, the
    plate where it stands then)."""
    l0 = 0.01
    U = 0.5
    plate_lo, plate_hi = np.array([-0.03, -0.01, -0.01]), np.array([-0.01, 0.09, 0.09])
    plate = slab_sdf(plate_lo, plate_hi, 0.5 * l0)
    x = lattice([0.0, 0.0, 0.0], [0.06, 0.08, 0.08], l0)
    space = open_space([-0.05, -0.03, -0.03], [0.3, 0.11, 0.11], 0.5 * l0)
    motion = Glide([U, 0.0, 0.0], pivot=0.5 * (plate_lo + plate_hi))
    s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), space, spacing=l0, rho0=1000.0, params=MPSParams(), mu=MU,
                  v_ref=U, bodies=[(plate, motion)])
    worst = np.inf
    work = ke = 0.0
    m = s.mass
    for f in range(1, 31):
        while s.t < f / 300.0:
            s.step(f / 300.0)
            _, T = motion.pose(s.t)
            d, _ = plate.sample(s.x - T)
            worst = min(worst, float(d.min()))
            assert len(s.x) == len(x)  # none lost
            # the fluid started at rest and only the plate acts on it: its momentum is the plate's impulse
            work = U * m * s.v[:, 0].sum()
            ke = 0.5 * m * (s.v ** 2).sum()
            assert ke <= work * (1 + 1e-9), (s.t, ke, work)
    print("MPS paddle: closest %.3g l0 to the plate, KE %.4g J, work %.4g J (%.2f)" % (worst / l0, ke, work, ke / work))
    assert worst > 0.0, worst
    assert 0.3 * work < ke, (ke, work)
    face = motion.pose(s.t)[1][0] + plate_hi[0]
    inner = np.all((s.x[:, 1:] > plate_lo[1:] + 2 * l0) & (s.x[:, 1:] < plate_hi[1:] - 2 * l0), axis=1)
    gap = (s.x[:, 0] - face) / l0
    held = inner & (gap < 0.75)  # the layer the plate holds at r_rep = l0 / 2 on its face
    behind = inner & (gap >= 0.75) & (gap < 1.5)  # the next one
    print("MPS paddle: vx / U of the layer on the face %.3f, of the next %.3f" % (s.v[held, 0].mean() / U,
                                                                                 s.v[behind, 0].mean() / U))
    assert held.sum() > 10 and abs(s.v[held, 0].mean() / U - 1.0) < 0.1
    # the block (6 l0 long, free all round) squeezes out sideways: the speed falls off ahead of the plate
    # (measured 0.73 U one spacing on), but the fluid there is pushed along
    assert behind.sum() > 10 and s.v[behind, 0].mean() > 0.5 * U


def _bake(tmp_path, scene):
    from pipeline.testing import run_stage
    from stages.mesh_import.trimesh_import import TrimeshImport
    from stages.sdf_bake.open3d_bake import Open3dBake
    w = run_stage(TrimeshImport, tmp_path / "walls", scene=scene, config_dir=tmp_path)
    return run_stage(Open3dBake, tmp_path / "sdf", scene=scene, inputs={"walls": w})


def test_the_mps_stage_moves_a_keyframed_wall_and_dfsph_refuses_it_in_one_line(tmp_path):
    """simulate.mps of a tank (centimetres, Y up) with a keyframed box pushed through its water: every frame's
    particles are outside the box where it stands at the frame's time and the water is stirred;
    simulate.dfsph refuses the scene with one StageError line."""
    from pipeline.stage import StageError
    from pipeline.testing import run_stage
    from stages.common.formats import load_particle_frame
    from stages.common.sdf import load_bodies
    from stages.simulate.dfsph import DFSPHSimulate
    from stages.simulate.mps import MPSSimulate

    keys = [{"time": 0.0, "translate": [0, 0, 0]}, {"time": 0.12, "translate": [6.0, 0, 0]}]  # 0.5 m/s
    scene = {"scene": {"name": "t", "units": {"meters_per_unit": 0.01, "up_axis": "Y"}, "frames": {"fps": 25, "count": 4}},
             "walls": [{"builtin": "box_tank", "size": [24, 24, 24], "center": [0, 0, 0]},
                       {"builtin": "box_tank", "size": [5, 10, 5], "center": [-5, 4, 0], "fluid": "outside",
                        "motion": {"keyframes": keys}}],
             "fluid": {"spacing": 2.5, "emitters": [{"box": {"min": [-12, 0, -12], "max": [12, 10, 12]}}]},
             "effects": {"gravity": {}, "viscosity": {"mu": MU}}}
    sdf = _bake(tmp_path, scene)
    (box, motion), = load_bodies(sdf)
    p = run_stage(MPSSimulate, tmp_path / "mps", scene=scene, params={"threads": 1}, inputs={"sdf": sdf})
    first = None
    moved = 0.0
    for f in range(4):
        fr = load_particle_frame(p, f)
        d, _ = box.sample(motion.to_rest(fr.x, f / 25.0))
        assert d.min() > 0.0, (f, d.min())
        x = np.full((fr.id.max() + 1, 3), np.nan)
        x[fr.id] = fr.x
        first = x if first is None else first
        n = min(len(x), len(first))
        moved = max(moved, float(np.nanmax(np.abs(x[:n] - first[:n]))))
    assert moved > 1.0  # cm: the box stirred the water
    with pytest.raises(StageError) as e:
        run_stage(DFSPHSimulate, tmp_path / "dfsph", scene=scene, inputs={"sdf": sdf})
    assert "moving walls" in str(e.value) and "\n" not in str(e.value)


def test_wall_reach_and_speed_bound_every_point_of_the_wall():
    """motion.reach / wall_speed (the time step's and the blow-up guard's wall speed): no point of the rest box
    is farther from the pivot than the reach, the farthest corner is at it, and no point of a turning,
    gliding box moves faster than the bound |v| + |omega| reach (against sampled points)."""
    from stages.common.motion import RigidMotion, reach, wall_speed
    lo, hi, pivot = np.array([-0.1, 0.2, 0.0]), np.array([0.3, 0.5, 0.1]), np.array([0.05, 0.3, 0.2])
    corners = np.array([[(lo, hi)[(c >> a) & 1][a] for a in range(3)] for c in range(8)])
    r = reach(lo, hi, pivot)
    assert r == pytest.approx(np.linalg.norm(corners - pivot, axis=1).max(), rel=1e-12)
    m = RigidMotion.from_keyframes([{"time": 0.0}, {"time": 0.5, "translate": [0.2, 0.0, -0.1], "rotate": [30, 0, 60]}],
                                   pivot)
    pts = np.random.default_rng(0).uniform(lo, hi, (200, 3))
    for t in (0.1, 0.3):
        v, w = m.velocity(t)
        x = m.to_world(pts, t)
        speed = np.linalg.norm(v + np.cross(w, x - (pivot + m.pose(t)[1])), axis=1)
        assert speed.max() <= wall_speed(m, r, t) * (1 + 1e-12)
