"""simulate.mps: lattice constants, wall maps, hydrostatic pressure, dam break against Martin & Moyce,
zero wall penetration on the dragon, resume-from-checkpoint equality, frames readable by surface_extract."""
import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import pipeline
from pipeline import Registry
from pipeline.stage import Artifact, Context, StageError
from pipeline.testing import run_stage, scene_sections, stage_context
from stages.common.formats import ParticleMeta, load_particle_frame
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.simulate import mps_kernels as K
from stages.simulate.mps import MPSParams, MPSSimulate, MPSSolver
from stages.simulate.walls.mps import MPSWallMaps, build_tables, lattice_constants

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_sph_dam_break import _reference  # noqa: E402  (the Martin & Moyce series)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
G = 9.81


pytestmark = pytest.mark.usefixtures("one_numba_thread")  # (conftest.py)


def test_lattice_constants_match_physics_md():
    for re, n0, lam in ((2.1, 14.42, 1.702), (3.1, 54.32, 3.243), (4.0, 123.99, 5.212)):
        n, l = lattice_constants(1.0, re)
        assert abs(n - n0) < 0.01 and abs(l - lam) < 0.001


def test_wall_maps_count_every_wall_in_edges_and_corners():
    """A particle of the cubic lattice next to a flat wall, in an edge and in a corner of a box: fluid
    neighbours plus the wall maps give n0 (a wall-particle lattice would give exactly n0)."""
    l0 = 0.01
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.1, 0.1, 0.1]), [0, 0, 0], [0.1, 0.1, 0.1], l0 / 2)
    tables = build_tables(l0, 2.1 * l0, 3.1 * l0, 256)
    maps = MPSWallMaps(sdf, l0, 2.1 * l0, 3.1 * l0, tables)
    x = lattice([0, 0, 0], [0.1, 0.1, 0.1], l0)
    s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=MPSParams())
    s.walls = maps
    s.sort_and_neighbours()
    s.number_density(s.x)
    ratio = s.n / s.n0
    dist = np.sort(np.minimum(s.x, 0.1 - s.x), axis=1)  # per particle: nearest, second, third wall
    flat = (dist[:, 0] < l0) & (dist[:, 1] > 4 * l0)
    edge = (dist[:, 1] < l0) & (dist[:, 2] > 4 * l0)
    corner = dist[:, 2] < l0
    print("n/n0 flat, edge, corner:", ratio[flat].mean(), ratio[edge].mean(), ratio[corner].mean())
    assert np.allclose(ratio[flat], 1.0, atol=1e-3)  # calibrated to the lattice table
    # the quadrature's error adds up over two or three walls; measured +2.3 % / +4.6 %
    assert np.all(np.abs(ratio[edge] - 1) < 0.04) and np.all(np.abs(ratio[corner] - 1) < 0.07)
    # the planar table of the nearest wall alone would put these far below beta = 0.97 (free surface)
    assert np.all(ratio[edge | corner] > 0.97)


def test_corrected_gradient_is_exact_for_a_linear_pressure_on_a_squeezed_lattice():
    """The corrective matrix (mps_kernels.correct): on a lattice squeezed 5 % vertically (n0 kept by
    stretching x and y) a hydrostatic pressure gives exactly rho g; the plain 1996 gradient is off by the
    zz part of (d / n0) sum r r^T / r^2 w, the error that left the tank at rest 6 % below rho g h."""
    l0, W = 0.01, 0.12
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, W]), [0, 0, 0], [W, W, W], l0 / 2)
    x = lattice([0, 0, 0], [W, W, W], l0)
    c = W / 2
    x = c + (x - c) * np.array([1.025, 1.025, 0.95])
    s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=MPSParams(),
                  gravity=(0, 0, -G))
    s.sort_and_neighbours()
    s._walls(s.x)
    p = 1000.0 * G * (W - s.x[:, 2])
    inner = s.d > s.re_n + 0.1 * l0
    grads = {}
    for det_min in (0.0, 0.5):
        xo, vo = np.zeros_like(s.x), np.zeros_like(s.x)
        K.correct(s.x, np.zeros_like(s.x), p, s.offsets, s.nbr, s.re_n, s.grad_coef, s.d, s.wall_terms, s.gravity,
                  1000.0, np.zeros(len(p), np.bool_), det_min, 1.0, xo, vo)
        grads[det_min] = -1000.0 * vo[inner] / (1000.0 * G)  # <grad p> in units of rho g
    plain, corrected = grads[0.0], grads[0.5]
    print("grad p_z / rho g: plain %.4f, corrected %.6f" % (plain[:, 2].mean(), corrected[:, 2].mean()))
    assert inner.sum() > 100
    assert np.allclose(corrected, [0.0, 0.0, -1.0], atol=1e-9)
    assert np.all(plain[:, 2] < -1.03)  # the plain gradient over-estimates, so p settles too low


def test_a_pair_on_top_of_each_other_stays_finite():
    """Two particles 1e-7 m apart (the eq. 16 projection put particles of a 20 degree V's apex onto one line;
    the unbounded w = re / r - 1 then gave n/n0 = 31,000 and the run blew up): each pair counts as R_MIN re
    apart, so n, the divergence and the pressure gradient stay finite and bounded, and pairs beyond that
    distance keep the plain 1996 weight."""
    l0, re = 0.02, 2.1 * 0.02
    for r in (1e-7 * l0, 0.5 * l0, l0):
        assert K.weight(r, re) <= re / (K.R_MIN * re) - 1.0
        assert abs(K.weight_over_r2(r * r, re) - K.weight(r, re) / max(r, K.R_MIN * re) ** 2) < 1e-9 / l0 ** 2
    assert K.weight(0.5 * l0, re) == re / (0.5 * l0) - 1.0  # the collision distance: untouched
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.2, 0.2, 0.2]), [0, 0, 0], [0.2, 0.2, 0.2], l0 / 2)
    x = np.array([[0.1, 0.1, 0.1], [0.1, 0.1, 0.1 + 2e-9]])
    s = MPSSolver(x, np.array([[0.0, 0, -1], [0, 0, 1]]), np.arange(2), sdf, spacing=l0, rho0=1000.0,
                  params=MPSParams(), gravity=(0, 0, -G))
    s.sort_and_neighbours()
    s.number_density(s.x)
    assert np.all(s.n <= re / (K.R_MIN * re) - 1.0 + 1e-9)
    for _ in range(20):
        s.step(1.0)
    assert np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.v)) and np.linalg.norm(s.v, axis=1).max() < 5.0


def test_pairs_the_projection_stacks_are_parted():
    """part_stacked: a pair closer than r_sep moves apart to r_sep along its line, half each; an exactly coincident
    pair (the projection put mirror-image particles of a V's apex on one point) along STACK_AXIS, the lower id to
    the minus side; each pair's centre stays where it was (no momentum made) and particles with no neighbour that
    close stay put."""
    l0 = 0.02
    r_sep = K.R_MIN * 2.1 * l0
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.2, 0.2, 0.2]), [0, 0, 0], [0.2, 0.2, 0.2], l0 / 2)
    walls = MPSSolver(np.array([[0.05, 0.05, 0.05]]), np.zeros((1, 3)), np.arange(1), sdf, spacing=l0, rho0=1000.0,
                      params=MPSParams(), gravity=(0, 0, -G)).wall_terms
    c = np.array([0.1, 0.1, 0.1])
    x = np.array([c, c, c + [0, 0, 2 * l0], c + [0.1 * l0, 0, 2 * l0], c + [0, 0, 4 * l0], c + [0.09, 0.0, 0.0]])
    ids = np.array([7, 3, 0, 1, 2, 5], np.int32)
    v = np.zeros_like(x)
    offsets = np.arange(0, 31, 5)  # every other particle is a neighbour
    nbr = np.array([j for i in range(6) for j in range(6) if j != i], np.int32)
    out = np.zeros_like(x)
    K.part_stacked(x, v, ids, offsets, nbr, r_sep, walls, 0.5 * l0, 0.5 * l0, out)
    axis = np.array(K.STACK_AXIS)
    assert np.allclose(out[0], c + 0.5 * r_sep * axis) and np.allclose(out[1], c - 0.5 * r_sep * axis)  # id 7 > 3
    assert np.isclose(np.linalg.norm(out[3] - out[2]), r_sep) and np.allclose(out[2] + out[3], x[2] + x[3])
    assert np.allclose(out[2, 1:], x[2, 1:])  # along the pair's own line
    assert np.array_equal(out[4], x[4]) and np.array_equal(out[5], x[5])
    assert not v.any()


def test_mirror_particles_in_a_v_apex_are_parted():
    """Two particles at mirror positions in a 20 degree V's apex, falling: the projection puts both on the line
    r_rep from both walls, at one point. Parted along their own line, into the walls, the projection puts them
    back together; the next step parts them along the V, and they stay apart (before: 0-0.005 l0 for the rest of
    the run), outside every wall's r_rep band."""
    import math
    l0, half = 0.02, math.radians(10.0)
    n1, n2 = np.array([math.cos(half), 0, math.sin(half)]), np.array([-math.cos(half), 0, math.sin(half)])
    apex = np.array([0.15, 0.05, 0.0])
    box = box_interior_sdf([0, 0, 0], [0.3, 0.1, 0.3])

    def fn(p):
        q = p - apex
        return np.minimum(box(p), np.minimum(q @ n1, q @ n2))

    sdf = grid_from_function(fn, [0, 0, 0], [0.3, 0.1, 0.3], l0 / 2)
    x = apex + np.array([[-0.2 * l0, 0, 2.0 * l0], [0.2 * l0, 0, 2.0 * l0]])
    s = MPSSolver(x, np.array([[0.3, 0, -1.0], [-0.3, 0, -1.0]]), np.arange(2), sdf, spacing=l0, rho0=1000.0,
                  params=MPSParams(), gravity=(0, 0, -G))
    r_sep = K.R_MIN * s.re_n
    apart = []
    for _ in range(6):
        s.step(1.0)
        apart.append(np.linalg.norm(s.x[0] - s.x[1]) / r_sep)
        d = sdf.sample(s.x)[0]
        assert np.all(d >= 0.99 * s.p.r_rep * l0), d / l0
    assert min(apart[1:]) > 0.5 and min(apart[3:]) > 0.9, apart


def test_frames_on_multiples_of_a_fixed_step_take_that_step():
    """A block compressed 3 % over n0, floating without gravity, at a fixed 2 ms step, framed every step and every
    other step: both take the same 20 steps and leave the same density error. Frame times a few ulps above a
    multiple of the step had each second frame's last step split in two (timestep.step_to), and MPS's density source
    removes its share of the error per step: 23 steps, 0.0225 error left against 0.0247."""
    l0 = 0.01
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.3, 0.3, 0.3]), [0, 0, 0], [0.3, 0.3, 0.3], l0 / 2)

    def run(frame):
        x = lattice([0.1, 0.1, 0.1], [0.2, 0.2, 0.2], l0)
        c = x.mean(axis=0)
        x = c + 0.99 * (x - c)
        s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                      params=MPSParams(time_step=0.002), gravity=(0, 0, 0), mu=0.001)
        for t in np.arange(frame, 0.04 + 1e-9, frame):
            s.advance_to(round(t, 6))
        f = s.frame()
        r = np.linalg.norm(f.x - c, axis=1)
        return s.steps, f.rho[r < np.percentile(r, 30)].mean() / 1000.0 - 1.0

    (n2, e2), (n4, e4) = run(0.002), run(0.004)
    assert n2 == n4 == 20
    assert abs(e4 - e2) < 1e-4 and 0.02 < e2 < 0.03, (e2, e4)


@pytest.mark.parametrize("frame", [None, 0.001])
@pytest.mark.parametrize("into", ["floor", "edge", "corner"])
def test_a_small_block_fired_into_a_wall_is_not_thrown_back(into, frame):
    """A 3 x 3 x 3 block of water (l0 = 1 cm, water's viscosity, no gravity) fired at 2 m/s into a floor,
    an edge and a corner of a box, stepped freely and to 1 ms frames: the water spreads along the walls,
    and no particle may come off them much faster than the block came in. Before the PPE counted the
    p_min gradient's repulsion in lopsided neighbourhoods (mps_kernels.build_poisson), the Laplacian
    alone solved for several times the pressure that stops such a block, and the repulsion threw single
    particles out: 2.64 x the impact speed out of the edge (free steps), 1.28 x out of the corner (1 ms
    frames). Now at most 1.11 x."""
    l0, W, speed = 0.01, 0.2, 2.0
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, W]), [0, 0, 0], [W, W, W], l0 / 2)
    x = lattice([2 * l0] * 3, [5 * l0] * 3, l0)
    direction = {"floor": np.array([0.0, 0.0, -1.0]), "edge": np.array([-1.0, 0.0, -1.0]) / np.sqrt(2),
                 "corner": -np.ones(3) / np.sqrt(3)}[into]
    x += {"floor": [0.08, 0.08, 0.0], "edge": [0.0, 0.08, 0.0], "corner": [0.0, 0.0, 0.0]}[into]
    s = MPSSolver(x, np.tile(speed * direction, (len(x), 1)), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                  params=MPSParams(), gravity=(0, 0, 0), mu=0.001, v_ref=speed)
    fastest = 0.0
    while s.t < 0.04 - 1e-12:  # the block hits at about 0.01 s (the corner's at 0.015 s)
        if frame is None:
            s.step(0.04)
        else:
            s.advance_to(min(s.t + frame, 0.04))
        fastest = max(fastest, float(np.linalg.norm(s.v, axis=1).max()))
    print(into, frame, "fastest / impact speed", fastest / speed)
    assert fastest < 1.2 * speed
    assert s.d.min() > 0.0


def test_hydrostatic_pressure_against_rho_g_h():
    """8 x 8 x 16 particles at rest; each layer's mean pressure averaged over every step from 0.3 to 0.5 s
    (the MPS pressure oscillates from step to step: a few frames are not a mean)."""
    l0, W, H = 0.01, 0.08, 0.16
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, 0.22]), [0, 0, 0], [W, W, 0.22], l0 / 2)
    x = lattice([0, 0, 0], [W, W, H], l0)
    s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=MPSParams(),
                  gravity=(0, 0, -G), mu=0.001, v_ref=float(np.sqrt(2 * G * H)))  # water (issue 17: was 1 Pa s)
    s.advance_to(0.3)
    depths = (4, 8, 12, 15)  # particle layers below the surface, the whole layer (walls included)
    samples = {d: [] for d in depths}
    while s.t < 0.5:
        s.step(0.5)
        z = s.xs[:, 2]  # the pressure was solved at the predicted positions
        for d in depths:
            layer = np.abs(z - (H - (d - 0.5) * l0)) < 0.5 * l0
            samples[d].append((s.pr[layer].mean(), 1000.0 * G * (H - z[layer]).mean(), s.pr[layer].std()))
    f = s.frame()
    assert f.x[:, 2].min() > 0.0 and s.d.min() > 0.0
    # settled? with water's viscosity not yet (issue 17): 0.118 m/s max at 0.5 s, decaying (0.021 m/s mean
    # at 1.5 s in bench_rest); the resting-tank goal is tracked in tests/stability
    assert np.linalg.norm(f.v, axis=1).max() < 0.2
    rows = []
    for d in depths:
        mean, expected, std = np.array(samples[d]).T
        rows.append((d, mean.mean() / expected.mean(), (std / expected).mean(), (mean / expected).std()))
    print("hydrostatic (depth in layers, mean p / rho g h, spread in the layer, step-to-step std):",
          np.round(rows, 3).tolist())
    # measured: 0.982, 0.992, 0.996, 0.998; spread in a layer 6.9, 3.1, 1.8, 1.3 %; step-to-step 11, 6, 4, 4 %
    # (0.985-0.995 at depths 8-15 over 1.3-1.5 s). Before the corrective matrix and gamma 0.01: 0.95, 0.94,
    # 0.94, 0.94 and step-to-step 22-13 %; with the matrix and gamma 0.03: 0.94, 0.97, 0.98, 0.99.
    for d, ratio, spread, wobble in rows:
        assert abs(ratio - 1.0) < (0.03 if d >= 8 else 0.06), (d, ratio)
        assert spread < (0.05 if d >= 8 else 0.1)
        # with water's viscosity (was 1 Pa s) the step-to-step wobble at depth 8 measured 9.5 % (6 % before):
        # the undamped churn of the open resting-tank defect (issue 17). The top layer's (depth 4) measured 0.146
        # with the wall maps summed in float32 and 0.156-0.161 summed in float64 (six runs 1e-12 l0 apart): a
        # change of the maps by 1e-7 flips which particles within 1e-5 of the free-surface threshold are free
        # surface, so its bound leaves room for that
        assert wobble < (0.12 if d >= 8 else 0.18)


def test_dam_break_surge_front_against_martin_moyce():
    a, l0, width = 0.1, 0.01, 0.04  # the SPH test's column (tests/test_sph_dam_break.py), 800 particles
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([5 * a, width, 3 * a])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    x = lattice([0, 0, 0], [a, width, 2 * a], l0)
    s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=MPSParams(),
                  gravity=(0, 0, -G), v_ref=float(np.sqrt(2 * G * 2 * a)))
    scale = np.sqrt(2 * G / a)
    sim = []
    for T in np.arange(0.25, 3.0 + 1e-9, 0.25):
        s.advance_to(T / scale)
        xs = np.sort(s.x[:, 0])
        sim.append((T, (xs[-3] + 0.5 * l0) / a))  # the front, ignoring two lone droplets
    sim = np.array(sim)
    ref = _reference()
    ref = ref[ref[:, 0] <= 3.0]
    z_sim = np.interp(ref[:, 0], sim[:, 0], sim[:, 1])
    rel = (z_sim - ref[:, 1]) / ref[:, 1]
    print("MPS dam break T, Z/a ref, Z/a sim, rel:", np.c_[ref, z_sim, rel].round(3).tolist())
    assert s.left_domain == 0 and s.x[:, 2].min() > 0
    # ahead of the experiment as expected (no gate modelled); measured 3-8 % ahead at 800 particles.
    # Looser than PHYSICS.md's 10 % because 4 particles across the width and 10 across the column
    # make the front position jump by one spacing (0.1 a) between samples.
    assert np.all(rel > -0.05) and np.all(rel < 0.15), rel


def test_unsupported_effects_are_a_stage_error(tmp_path):
    sdf = _sdf(tmp_path)
    scene = dict(SCENE, effects={"gravity": {}, "surface_tension": {"gamma": 0.07}, "wind": {"velocity": [1, 0, 0]}})
    with pytest.raises(StageError, match="effects surface_tension, wind are not supported by MPS"):
        run_stage(MPSSimulate, tmp_path / "out", scene=scene, inputs={"sdf": sdf})


# -- the stage -----------------------------------------------------------------------------------------
L0 = 0.02
SCENE = {
    "scene": {"name": "t", "frames": {"fps": 50, "count": 7}, "units": {"up_axis": "Z"}},
    "fluid": {"spacing": L0, "emitters": [{"box": {"min": [0.0, 0, 0], "max": [0.12, 0.2, 0.2]}}]},
    "effects": {"gravity": {}, "viscosity": {"mu": 0.01}},
}


def _sdf(tmp: Path) -> Path:
    folder = tmp / "sdf"
    folder.mkdir(exist_ok=True)
    grid_from_function(box_interior_sdf([0, 0, 0], [0.3, 0.2, 0.4]), [0, 0, 0], [0.3, 0.2, 0.4], L0 / 2).save(folder)
    return folder


def _ctx(out: Path, ckpt: Path | None) -> Context:
    sections = scene_sections(SCENE)
    return stage_context(MPSSimulate, out, scene=sections, frames=tuple(range(7)), log=logging.getLogger("t"),
                         checkpoint_dir=ckpt)


def test_resume_from_checkpoint_is_identical_and_frames_feed_surface_extract(tmp_path):
    sdf = _sdf(tmp_path)
    arts = {"sdf": Artifact(name="sdf", key="t", path=sdf)}
    params = MPSSimulate.Params(threads=1, checkpoint_every=2)
    straight = tmp_path / "straight"
    straight.mkdir()
    MPSSimulate().run(_ctx(straight, tmp_path / "ck_straight"), arts, params)
    # an interrupted run: keep only what existed after frame 4's checkpoint, then run again
    ck = tmp_path / "ck"
    shutil.copytree(tmp_path / "ck_straight", ck)
    for p in ck.glob("state_*.npz"):
        if p.name != "state_00004.npz":
            p.unlink()
    for f in (5, 6):
        (ck / "frames" / f"{f:05d}.npz").unlink(missing_ok=True)
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    MPSSimulate().run(_ctx(resumed, ck), arts, params)
    for f in range(7):
        a, b = load_particle_frame(straight, f), load_particle_frame(resumed, f)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and np.array_equal(a.id, b.id)
        assert np.array_equal(a.p, b.p)
    meta = ParticleMeta.load(straight)
    assert meta.solver == "mps" and meta.stats["particles"] == 6 * 10 * 10 and max(meta.stats["inside_wall"]) == 0
    # the same ParticleFrame format: surface_extract reads it unchanged
    from stages.surface_extract.marching_cubes import MarchingCubes
    surf = run_stage(MarchingCubes, tmp_path / "surf", scene=SCENE, inputs={"particles": straight}, frames=(6,))
    from stages.common.formats import load_surface
    mesh = load_surface(surf, 6)
    assert len(mesh.faces) > 100
    f6 = load_particle_frame(straight, 6)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    assert np.all(lo > f6.x.min(axis=0) - 2 * L0) and np.all(hi < f6.x.max(axis=0) + 2 * L0)


def test_poured_fluid_stays_out_of_the_dragon(tmp_path):
    """tests/test_wall_integrity.py's dragon case with simulate: {use: mps}."""
    sets = ("scene.frames.count=13", "fluid.spacing=0.025", "simulate.use=mps")
    report = pipeline.run(CONFIGS / "seed_dragon.yaml", registry=Registry.from_entry_points(), overrides=sets,
                          cache_dir=tmp_path / "cache", out_dir=tmp_path / "out")
    stats = json.loads((Path(report.outputs["particles"]) / "meta.json").read_text())["stats"]
    print("dragon mps: particles", stats["particles"], "ms/step", stats["summary"]["ms_per_step"])
    assert stats["particles"] > 2000
    assert min(e[2] for e in stats["extent_min"]) < 0.45  # the fluid fell onto the model
    assert max(stats["inside_wall"]) == 0
    assert stats["left_domain"] == 0


def test_a_pressure_solve_stopped_at_its_cap_is_named_as_a_blow_ups_likely_cause():
    """A blow-up within the time-step limits blamed 'the pressure solve or the spacing' whatever the CG had done;
    a solve stopped at cg_max_iterations is now named with the setting to change."""
    from stages.simulate.driver import Guard
    l0 = 0.01
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.1, 0.1, 0.2]), [0, 0, 0], [0.1, 0.1, 0.2], l0 / 2)
    x = lattice([0, 0, 0], [0.1, 0.1, 0.1], l0)
    causes = []
    for cap in (1, 2000):
        s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0,
                      params=MPSParams(cg_max_iterations=cap), gravity=(0, 0, -G))
        s.advance_to(0.002)
        causes.append(Guard(v_bound=2.0, l0=l0)._cause(s, 0.002))
    assert causes[0].startswith("the pressure solve stopped at cg_max_iterations (1)"), causes[0]
    assert "raise cg_max_iterations" in causes[0] and "cg_max_iterations" not in causes[1], causes
