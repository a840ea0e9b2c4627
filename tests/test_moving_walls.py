"""Moving rigid walls in WCSPH (issue 18): a wall baked once in its rest frame, sampled through its pose.

Physics checks with water's viscosity (mu = 0.001 Pa s) and the solver's defaults:
- a body at its rest pose is the same wall as the static one; moved with the particles, the same again;
- sloshing: a tank swayed near its first natural frequency, then stopped, rings at
  f1 = (1/2 pi) sqrt(g k tanh(k h)), k = pi / L (linear theory) within 3 %;
- a paddle driven at constant speed into still water: no particle ever inside the paddle or the tank, and
  the fluid's energy gain stays below the paddle's work U J (J its impulse on the fluid = the momentum the
  fluid gains in a weightless scene with no other wall)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.common.sdf import SDFGrid, box_interior_sdf, grid_from_function
from stages.simulate.driver import hydrostatic_start
from stages.simulate.emitters import lattice
from stages.simulate.sph import SPHParams, SPHSolver
from stages.simulate.validation import damped_frequency, sloshing_f1

G = 9.81
MU = 0.001  # water


class Sway:
    """x_wall(t) = A (1 - cos(w t)) along ``axis`` until ``stop`` (a whole number of periods: at rest
    there, at its rest position), then still. The RigidMotion interface (pose, velocity, pivot)."""

    def __init__(self, amplitude, omega, stop, axis=(1.0, 0.0, 0.0), pivot=(0.0, 0.0, 0.0)):
        self.a, self.w, self.stop = amplitude, omega, stop
        self.axis = np.asarray(axis, float)
        self.pivot = np.asarray(pivot, float)

    def pose(self, t):
        t = min(t, self.stop)
        return np.eye(3), self.axis * self.a * (1.0 - math.cos(self.w * t))

    def velocity(self, t):
        s = self.a * self.w * math.sin(self.w * t) if t < self.stop else 0.0
        return self.axis * s, np.zeros(3)


class Held:
    """A wall held at the offset ``T`` from its rest pose (the RigidMotion interface)."""

    def __init__(self, T, pivot=(0.0, 0.0, 0.0)):
        self.T = np.asarray(T, float)
        self.pivot = np.asarray(pivot, float)

    def pose(self, t):
        return np.eye(3), self.T.copy()

    def velocity(self, t):
        return np.zeros(3), np.zeros(3)


class Glide:
    """Constant velocity ``u`` from t = 0 (the RigidMotion interface)."""

    def __init__(self, u, pivot=(0.0, 0.0, 0.0)):
        self.u = np.asarray(u, float)
        self.pivot = np.asarray(pivot, float)

    def pose(self, t):
        return np.eye(3), self.u * t

    def velocity(self, t):
        return self.u.copy(), np.zeros(3)


def open_space(lo, hi, spacing) -> SDFGrid:
    """No static wall: the SDF is +1 m over the box (the domain the moving walls sweep)."""
    return grid_from_function(lambda p: np.ones(len(p)), lo, hi, spacing, band=1.0)


def slab_sdf(lo, hi, spacing) -> SDFGrid:
    """A solid box [lo, hi] (fluid outside): positive outside it."""
    inside = box_interior_sdf(lo, hi)
    return grid_from_function(lambda p: -inside(p), np.subtract(lo, 0.05), np.add(hi, 0.05), spacing)


def test_a_body_at_rest_is_the_static_wall_and_moves_with_its_pose():
    """Density and acceleration of a splashing block in a tank: with the tank as the static wall, as a
    body at its rest pose over an empty static field, and with the body and the particles translated by
    the same offset (and the velocities unchanged): the same numbers, to rounding."""
    l0 = 0.01
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.12, 0.08, 0.1])
    tank = grid_from_function(box_interior_sdf(lo, hi), lo, hi, 0.5 * l0)
    x = lattice([0.0, 0.0, 0.0], [0.06, 0.08, 0.06], l0)
    rng = np.random.default_rng(3)
    x = x + rng.uniform(-0.15, 0.15, x.shape) * l0
    v = rng.normal(0.0, 0.2, x.shape)
    kw = dict(spacing=l0, rho0=1000.0, params=SPHParams(), gravity=(0, 0, -G), mu=MU, v_ref=1.0)

    def one(sdf, x, bodies=()):
        s = SPHSolver(x, v, np.arange(len(x)), sdf, bodies=bodies, **kw)
        s.sort_and_density(rebuild=True)
        s.forces()
        order = np.argsort(s.id)
        return s.rho[order], s.acc[order], s.d[order]

    rho0, acc0, d0 = one(tank, x)
    shift = np.array([0.031, -0.017, 0.023])
    for off in (np.zeros(3), shift):
        space = open_space(lo - 0.05 + np.minimum(off, 0), hi + 0.05 + np.maximum(off, 0), 0.5 * l0)
        rho, acc, d = one(space, x + off, [(tank, Held(off, pivot=0.5 * (lo + hi)))])
        assert (d0 < 2 * l0).sum() > 100  # many particles feel the walls
        assert np.allclose(d, d0, rtol=0, atol=1e-9)
        assert np.allclose(rho, rho0, rtol=1e-12, atol=1e-9)
        assert np.abs(acc - acc0).max() < 1e-6 * np.abs(acc0).max()


def sloshing_frequency(L=0.2, depth=0.1, width=0.2, l0=0.0125, amplitude=0.002, cycles=2, free=3.5, solver=SPHSolver,
                       params=None, jitter_seed=None):
    """Sway a tank at the linear f1 for ``cycles`` periods, stop it, and measure the free oscillation of
    the first sloshing mode over ``free`` periods by a damped sinusoid fitted to (a) its modal velocity: the
    particles' velocities projected on the mode's, u ~ (sin kx cosh kz, -cos kx sinh kz) from the floor
    and the left wall (orthogonal to the other modes; the tank is at rest then), and (b) the free surface
    at the left wall: the water's depth there (its volume per unit area near the wall).
    Returns (measured by the velocity, measured at the wall, theory) in Hz. ``solver``: the solver class
    (SPHSolver's keywords), with ``params`` (its defaults without).
    (At l0 = 1 cm a tank 6 l0 wide rang 4-6 % fast by zero crossings, with free-slip walls too; 12 l0 wide,
    3 %; 20 l0, 1-2 %. Here, 16 l0 wide, the fit gives +1.2 to +2.3 % by the velocity and +1.3 to +2.3 % at the
    wall over starts 1e-4 l0 off the lattice (``jitter_seed``; +0.3 % from the exact lattice) (MPS, 8 l0 wide:
    -1.8 % and -1.8 % on the mean of three such starts), and a decay delta ~ 2.2 / s: damping ratio 0.19, far
    above water's; the solver's artificial viscosity.)"""
    k = math.pi / L
    f1 = sloshing_f1(L, depth, G)
    w = 2.0 * math.pi * f1
    stop = cycles / f1
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([L, width, 2.0 * depth])
    tank = grid_from_function(box_interior_sdf(lo, hi), lo, hi, 0.5 * l0)
    space = open_space(lo - 0.02, hi + [0.02 + 2 * amplitude, 0.02, 0.02], 0.5 * l0)
    x = lattice(lo, [L, width, depth], l0)
    if jitter_seed is not None:  # a start 1e-4 l0 off the lattice: one member of an ensemble (the fit's spread)
        x += np.random.default_rng(jitter_seed).uniform(-1e-4, 1e-4, x.shape) * l0
    s = solver(x, np.zeros_like(x), np.arange(len(x)), space, spacing=l0, rho0=1000.0,
               params=params if params is not None else SPHParams(), gravity=(0, 0, -G), mu=MU,
               v_ref=math.sqrt(2 * G * depth), bodies=[(tank, Sway(amplitude, w, stop, pivot=0.5 * (lo + hi)))])
    hydrostatic_start(s)
    fps = 120.0
    t, q, eta = [], [], []
    for f in range(1, int((stop + free / f1) * fps) + 1):
        s.advance_to(f / fps)
        if s.t > stop:
            t.append(s.t)  # the tank is back at its rest position after the stop
            xx, zz = s.x[:, 0], s.x[:, 2]
            q.append(float((s.v[:, 0] * np.sin(k * xx) * np.cosh(k * zz) - s.v[:, 2] * np.cos(k * xx) * np.sinh(k * zz)).mean()))
            # the free surface at the wall, of the first mode: eta(x) = eta1 cos(kx) + other modes, and
            # (2 / L) int eta cos(kx) dx = eta1 = its height at the wall, where the integral is the particles'
            # volume weighted by cos(kx) per unit width (the still water below contributes nothing). Smooth
            # in the positions and blind to the other modes, unlike the top particle near the wall (it moves
            # in steps of a spacing) or the volume in a window by the wall (its fit swung by +-2 % between
            # runs that differ by rounding)
            eta.append(float(2.0 / L * l0 ** 3 * np.cos(k * xx).sum() / width))
    t = np.array(t)
    assert np.ptp(q) > 0.02 and np.ptp(eta) > 0.002  # it sloshes (m/s; m at the wall)
    return damped_frequency(t, np.array(q))[0], damped_frequency(t, np.array(eta))[0], f1


def test_sloshing_rings_at_the_first_natural_frequency():
    """The mode's velocity and the free surface at the wall both ring at f1 within 3 %, on the mean of three starts
    1e-4 l0 off the lattice. One run's fit moves by 1-2 % with a perturbation that small: the exact lattice gave
    +0.3 %, the same with 200 / 300 wall-table samples +2.8 / +2.4 %, these members +1.6 / +1.8 / +2.3 % by the
    velocity; so a single run passed by a margin the method does not have (session 27)."""
    runs = np.array([sloshing_frequency(jitter_seed=seed) for seed in range(3)])
    by_velocity, at_wall, f1 = runs.mean(axis=0)
    assert abs(by_velocity / f1 - 1.0) < 0.03, runs
    assert abs(at_wall / f1 - 1.0) < 0.03, runs


def test_a_paddle_pushes_water_without_entering_it_and_within_its_work():
    """Weightless water (a 6 x 8 x 8 l0 block) and a plate moving into it at U = 0.5 m/s: the plate's
    impulse on the fluid is the fluid's momentum (nothing else acts), so its work is U J_x; the fluid's
    kinetic energy gain never exceeds it (the wall is passive: no energy from the method) and is a fair part
    of it (an inelastic push gives half); the fluid ahead moves with the plate; no particle is ever found
    inside the plate. The front layer's speed is averaged over the last third of the push: at one instant it
    rides the block's acoustic ringing (0.84-0.91 U over frames 21-30 with either kernel)."""
    l0 = 0.01
    U = 0.5
    plate_lo, plate_hi = np.array([-0.03, -0.01, -0.01]), np.array([-0.01, 0.09, 0.09])
    plate = slab_sdf(plate_lo, plate_hi, 0.5 * l0)
    x = lattice([0.0, 0.0, 0.0], [0.06, 0.08, 0.08], l0)
    space = open_space([-0.05, -0.03, -0.03], [0.3, 0.11, 0.11], 0.5 * l0)
    motion = Glide([U, 0.0, 0.0], pivot=0.5 * (plate_lo + plate_hi))
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), space, spacing=l0, rho0=1000.0, params=SPHParams(),
                  mu=MU, v_ref=U, bodies=[(plate, motion)])
    worst = np.inf
    front_speed = []
    for f in range(1, 31):
        while s.t < f / 300.0:
            s.step(f / 300.0)
            _, T = motion.pose(s.t)
            d, _ = plate.sample(s.x - T)
            worst = min(worst, float(d.min()))
        if f > 20:
            face = motion.pose(s.t)[1][0] + plate_hi[0]
            inner = np.all((s.x[:, 1:] > plate_lo[1:] + 2 * l0) & (s.x[:, 1:] < plate_hi[1:] - 2 * l0), axis=1)
            front = inner & (s.x[:, 0] > face) & (s.x[:, 0] < face + 1.5 * l0)  # the layer on the plate's face
            assert front.sum() > 20
            front_speed.append(s.v[front, 0].mean())
    m = s.mass
    jx = m * s.v[:, 0].sum()  # the fluid started at rest
    work = U * jx
    ke = 0.5 * m * (s.v ** 2).sum()
    assert worst > 0.0, worst  # never inside the plate (eq. 16 keeps them r_rep = l0 / 2 out)
    assert jx > 0.0
    assert 0.3 * work < ke <= work, (ke, work)
    assert abs(np.mean(front_speed) / U - 1.0) < 0.15, np.array(front_speed) / U


def _simulate(tmp_path, walls, tag, count=10, settle=0.0):
    """mesh_import -> sdf_bake -> simulate.sph of a tank 0.52 m deep with ``walls`` added (Z up, metres,
    25 fps): the particle frames (x by particle id) and the bodies."""
    from pipeline.testing import run_stage
    from stages.common.formats import load_particle_frame
    from stages.common.sdf import load_bodies
    from stages.mesh_import.trimesh_import import TrimeshImport
    from stages.sdf_bake.open3d_bake import Open3dBake
    from stages.simulate.sph import SPHSimulate

    tank = {"builtin": "box_tank", "size": [0.8, 1.2, 0.9], "center": [1.0, 0.5, 0.0]}
    scene = {"scene": {"name": "t", "frames": {"fps": 25, "count": count}}, "walls": [tank, *walls],
             "fluid": {"spacing": 0.05, "emitters": [{"box": {"min": [0.6, -0.1, 0.0], "max": [1.4, 1.1, 0.52]}}],
                       "settle": settle},
             "effects": {"gravity": {}, "viscosity": {"mu": MU}}}
    w = run_stage(TrimeshImport, tmp_path / f"walls_{tag}", scene=scene, config_dir=tmp_path)
    s = run_stage(Open3dBake, tmp_path / f"sdf_{tag}", scene=scene, inputs={"walls": w})
    p = run_stage(SPHSimulate, tmp_path / f"sim_{tag}", scene=scene, params={"threads": 1}, inputs={"sdf": s})
    frames = []
    for f in range(count):
        fr = load_particle_frame(p, f)
        x = np.full((fr.id.max() + 1, 3), np.nan)
        x[fr.id] = fr.x
        frames.append(x)
    return frames, load_bodies(s)


def test_settling_among_walls_animated_in_usd_is_refused(tmp_path):
    """The config refuses fluid.settle with walls[].motion; walls animated in their USD file are known only once
    imported: the solver refuses them in one line (settling zeroes velocities the moving wall gives)."""
    from pipeline.stage import StageError
    from test_motion import _animated_usd

    with pytest.raises(StageError, match="fluid.settle is for a fluid among walls at rest, but the scene has walls "
                                         "animated in their USD file"):
        _simulate(tmp_path, [{"usd": _animated_usd(tmp_path), "fluid": "outside"}], "usd", count=2, settle=0.5)


def test_an_animated_usd_prop_moves_the_fluid_as_its_keyframes_do(tmp_path):
    """A 20 cm cube animated in a USD file (translate and rotate time samples at different codes, under a
    translated, turned and scaled parent, Y up, centimetres) pushed through the water of a tank, and the
    same motion given as config keyframes on a solid box: the same fluid, frame by frame; and no particle
    is ever inside the cube where it stands at the frame's time."""
    from test_motion import _animated_usd, _keyframes_by_hand

    name = _animated_usd(tmp_path)
    usd, bodies = _simulate(tmp_path, [{"usd": name, "fluid": "outside"}], "usd")
    keyed, _ = _simulate(tmp_path, [{"builtin": "box_tank", "size": [0.2, 0.2, 0.2], "center": [1.0, 0.2, 0.4],
                                     "fluid": "outside", "motion": {"keyframes": _keyframes_by_hand(),
                                                                    "pivot": [1.0, 0.2, 0.5]}}], "keyed")
    (cube, motion), = bodies
    moved = 0.0
    for f, (a, b) in enumerate(zip(usd, keyed)):
        both = ~np.isnan(a[:, 0]) & ~np.isnan(b[:, 0])
        assert both.mean() > 0.99
        assert np.abs(a[both] - b[both]).max() < 0.05 * 0.05, f  # 5 % of a spacing
        d, _ = cube.sample(motion.to_rest(a[both], f / 25.0))
        assert d.min() > 0.0, (f, d.min())
        moved = max(moved, float(np.linalg.norm(a[both] - usd[0][both], axis=1).max()))
    assert moved > 0.05  # the cube stirred the water


def test_resume_with_a_moving_wall_is_bitwise_identical(tmp_path, caplog):
    """A run interrupted after frame 3's checkpoint and resumed gives the same frames, bit for bit, as one
    run straight through: the walls' poses are functions of the resumed time, not state carried over."""
    import shutil

    from pipeline.stage import Artifact
    from pipeline.testing import run_stage, stage_context
    from stages.common.formats import load_particle_frame
    from stages.mesh_import.trimesh_import import TrimeshImport
    from stages.sdf_bake.open3d_bake import Open3dBake
    from stages.simulate.sph import SPHSimulate

    paddle = {"builtin": "box_tank", "size": [0.04, 0.3, 0.3], "center": [0.1, 0.15, 0.15], "fluid": "outside",
              "motion": {"keyframes": [{"time": 0.0}, {"time": 0.3, "translate": [0.15, 0.0, 0.05],
                                                         "rotate": [0.0, 0.0, 30.0]}]}}
    scene = {"scene": {"name": "r", "frames": {"fps": 20, "count": 6}},
             "walls": [{"builtin": "box_tank", "size": [0.5, 0.3, 0.4], "center": [0.25, 0.15, 0.0]}, paddle],
             "fluid": {"spacing": 0.025, "emitters": [{"box": {"min": [0.0, 0.0, 0.0], "max": [0.5, 0.3, 0.15]}}]},
             "effects": {"gravity": {}, "viscosity": {"mu": MU}}}
    w = run_stage(TrimeshImport, tmp_path / "walls", scene=scene, config_dir=tmp_path)
    s = run_stage(Open3dBake, tmp_path / "sdf", scene=scene, inputs={"walls": w})
    arts = {"sdf": Artifact(name="sdf", key="t", path=s)}
    params = SPHSimulate.Params(threads=1, checkpoint_every=1)

    def run(out, ck):
        out.mkdir()
        SPHSimulate().run(stage_context(SPHSimulate, out, scene=scene, checkpoint_dir=ck), arts, params)

    run(tmp_path / "straight", tmp_path / "ck_straight")
    shutil.copytree(tmp_path / "ck_straight", tmp_path / "ck")
    for p in (tmp_path / "ck").glob("state_*.npz"):
        if p.name != "state_00003.npz":
            p.unlink()
    for f in (4, 5):
        (tmp_path / "ck" / "frames" / f"{f:05d}.npz").unlink(missing_ok=True)
    caplog.set_level("INFO")
    run(tmp_path / "resumed", tmp_path / "ck")
    assert "resumed from the checkpoint at frame 3" in caplog.text
    moved = 0.0
    for f in range(6):
        a, b = load_particle_frame(tmp_path / "straight", f), load_particle_frame(tmp_path / "resumed", f)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and np.array_equal(a.id, b.id), f
        moved = max(moved, float(np.abs(a.v).max()))
    assert moved > 0.1  # the paddle stirred the water (m/s)


def test_a_fast_thin_plate_sweeps_water_without_any_particle_tunnelling():
    """A plate a quarter spacing thick driven at 10 m/s right through a block of weightless water: no
    particle ever gets to the plate's other side or inside it. (The sound speed is set from the wall's
    speed, half what the driver's ballistic bound gives; at that speed the acoustic step alone keeps the
    plate's travel per step far below r_rep, the wall-speed limit on dt is the solver's second guard.)"""
    l0, U = 0.01, 10.0
    lo, hi = np.array([-0.0225, -0.01, -0.01]), np.array([-0.02, 0.09, 0.09])
    plate = slab_sdf(lo, hi, 0.125 * l0)
    x = lattice([0.0, 0.0, 0.0], [0.06, 0.08, 0.08], l0)
    space = open_space([-0.05, -0.03, -0.03], [0.4, 0.11, 0.11], 0.5 * l0)
    motion = Glide([U, 0.0, 0.0], pivot=0.5 * (lo + hi))
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), space, spacing=l0, rho0=1000.0, params=SPHParams(),
                  mu=MU, v_ref=U, bodies=[(plate, motion)])
    mid0 = 0.5 * (lo[0] + hi[0])
    worst = np.inf
    while s.t < 0.02:  # the plate travels 20 cm: through the 6 cm block and on
        s.step(0.02)
        behind = np.all((s.x[:, 1:] > lo[1:]) & (s.x[:, 1:] < hi[1:]), axis=1) & (s.x[:, 0] < mid0 + U * s.t)
        assert not behind.any(), (s.t, np.flatnonzero(behind))
        d, _ = plate.sample(s.x - motion.pose(s.t)[1])
        worst = min(worst, float(d.min()))
    assert worst > 0.4 * l0, worst / l0  # kept r_rep = l0 / 2 off the plate
    assert (s.v[:, 0] > 0.5 * U).sum() > 0.2 * len(x)  # it swept the water along


def test_friction_damps_the_velocity_relative_to_the_wall_it_touches():
    """One water layer in zero gravity on a plate (no pressure: a single layer's density is below rho0;
    no viscosity: friction alone acts), wall friction rate 20 / s for 0.05 s. The contact velocity relative
    to the plate decays as exp(-rate t): a layer carried at the plate's speed U is not braked (it keeps U
    within 1 %); a layer at rest on the moving plate is dragged to U (1 - e^-1); a layer sliding at U on
    the plate held still keeps U e^-1 (as on a static floor, test_effects)."""
    from pipeline.scene import Effects
    from stages.simulate.effects import compile_effects

    l0, U, rate, t = 0.008, 0.5, 20.0, 0.05
    lo, hi = np.array([-0.06, -0.04, -0.03]), np.array([0.26, 0.08, 0.0])
    plate = slab_sdf(lo, hi, 0.5 * l0)
    layer = lattice([0.0, 0.0, 0.0], [0.12, 0.04, l0], l0)  # 15 x 5 particles, l0 / 2 above the plate
    space = open_space([-0.12, -0.1, -0.1], [0.4, 0.14, 0.1], 0.5 * l0)
    p = SPHParams()
    effects = compile_effects(Effects(wall_friction={"rate": rate}), meters_per_unit=1.0, rho0=1000.0, l0=l0,
                              h=p.support * l0)
    decay = math.exp(-rate * t)
    for motion, v0, expected in ((Glide([U, 0.0, 0.0], pivot=0.5 * (lo + hi)), U, U),
                                 (Glide([U, 0.0, 0.0], pivot=0.5 * (lo + hi)), 0.0, U * (1.0 - decay)),
                                 (Held([0.0, 0.0, 0.0], pivot=0.5 * (lo + hi)), U, U * decay)):
        v = np.zeros_like(layer)
        v[:, 0] = v0
        s = SPHSolver(layer, v, np.arange(len(layer)), space, spacing=l0, rho0=1000.0, params=p, v_ref=1.0,
                      effects=effects, bodies=[(plate, motion)])
        s.advance_to(t)
        assert len(s.x) == len(layer) and np.abs(s.x[:, 2] - 0.5 * l0).max() < 0.01 * l0
        assert np.allclose(s.v[:, 0], expected, rtol=0.01, atol=1e-3 * U), (v0, expected, s.v[:, 0].min(),
                                                                            s.v[:, 0].max())
