"""simulate.dfsph: the pieces of the solver against brute force and finite differences, the dam break
against Martin & Moyce, resume-from-checkpoint equality through the stage; the hydrostatic tank is a
strict xfail until a resting tank stays at rest (see dfsph.py)."""
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.stage import Artifact, Context
from pipeline.testing import run_stage, scene_sections, stage_context
from stages.common.formats import ParticleMeta, load_particle_frame

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHParams, DFSPHSimulate, DFSPHSolver
from stages.simulate.emitters import lattice
from stages.simulate.walls.spline import spline_np
from stages.simulate.kernels import poly6_np

L0, W, H, G = 0.01, 0.1, 0.2, 9.81


def _tank(jitter=0.0, mu=0.01, params: DFSPHParams | None = None, **fields):
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, 0.3]), [0, 0, 0], [W, W, 0.3], L0 / 2)
    x = lattice([0, 0, 0], [W, W, H], L0)
    if jitter:
        x = x + np.random.default_rng(0).normal(0, jitter * L0, x.shape)
    return DFSPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0,
                       params=params or DFSPHParams(threads=None, **fields), gravity=(0, 0, -G), mu=mu)


@pytest.mark.parametrize("gradient", ["spiky", "spline"])
def test_neighbour_lists_and_density_match_brute_force(gradient):
    s = _tank(jitter=0.05, gradient=gradient)
    s.cap = 4  # far too small: the pass must grow it, never drop a neighbour
    s._alloc()
    s.refresh()
    assert s.cap >= s.count.max()
    kernel = spline_np if gradient == "spline" else poly6_np
    for i in (0, 137, 801, 1999):
        r = np.linalg.norm(s.x - s.x[i], axis=1)
        expect = set(np.flatnonzero(r < s.h)) - {i}
        assert set(s.nbr[i * s.cap:i * s.cap + s.count[i]].tolist()) == expect
        fluid = s.mass * kernel(r, s.h).sum()
        assert s.rho[i] >= fluid - 1e-9  # plus the wall's share (eq. 11)
        if s.d[i] >= s.h:
            assert s.rho[i] == pytest.approx(fluid, rel=1e-12)


def test_wall_gradient_balances_the_fluid_gradient_on_a_flat_floor():
    """A particle l0/2 above the floor in the rest lattice: sum_fluid m grad W + Psi = 0 (the wall stands
    in for the missing half of the neighbourhood), with the exact Poly6 derivative of the density."""
    s = _tank(gradient="poly6")
    s.refresh()
    i = np.argmin(np.linalg.norm(s.x - [0.045, 0.045, 0.005], axis=1))
    n = s.count[i]
    j = s.nbr[i * s.cap:i * s.cap + n]
    S = -s.mass * (s.fac[i * s.cap:i * s.cap + n, None] * (s.x[i] - s.x[j])).sum(axis=0)
    assert S[2] > 0 and s.psi[i, 2] < 0
    assert abs(S[2] + s.psi[i, 2]) < 0.05 * S[2]
    assert np.allclose(s.psi[i, :2], 0.0, atol=1e-6 * S[2])


@pytest.mark.parametrize("gradient", ["spiky", "spline"])
def test_wall_gradient_balances_the_fluid_gradient_in_edges_and_corners(gradient):
    """The Spiky (default) or spline gradient on the rest lattice: a particle l0/2 from one, two or three
    walls has S_i + Psi_i = 0 (S_i = sum_fluid m grad_i W_ij): the wall supplies exactly the missing
    neighbours' gradient in a floor, an edge and a corner (the gradient of Z_rho was 11-13 % short in the
    last two; the spline's quadrature measured 0.1, 0.8 and 4 %)."""
    s = _tank(gradient=gradient)
    s.refresh()
    for p in ([0.045, 0.045, 0.005], [0.045, 0.005, 0.005], [0.005, 0.005, 0.005], [0.095, 0.095, 0.005]):
        i = np.argmin(np.linalg.norm(s.x - p, axis=1))
        n = s.count[i]
        j = s.nbr[i * s.cap:i * s.cap + n]
        S = -s.mass * (s.fac[i * s.cap:i * s.cap + n, None] * (s.x[i] - s.x[j])).sum(axis=0)
        assert np.linalg.norm(S + s.psi[i]) < 0.05 * np.linalg.norm(S), (p, S, s.psi[i])


@pytest.mark.parametrize("gradient", ["poly6", "spline"])
def test_predicted_density_rate_matches_the_real_change(gradient):
    """D rho / Dt of the solver (fluid pairs + wall term) against the density recomputed after a tiny move
    (Poly6 density with its exact derivative, or the spline for both)."""
    from stages.simulate import dfsph_kernels as D
    s = _tank(jitter=0.05, gradient=gradient)
    s.refresh()
    vel = np.random.default_rng(1).normal(0, 1, s.x.shape)
    rate = np.zeros(len(s.x))
    for sign in (1, -1):  # the kernel clamps at 0: the signed rate from +v and -v
        s.v[:] = sign * vel
        kappa, err = np.zeros(len(s.x)), np.zeros(len(s.x))
        D.jacobi_density(s.x, s.v, s.nbr, s.fac, s.count, s.cap, s.mass, s.psi, s.rho * 0 + 1.0, s.alpha, 1.0,
                         1.0, 1.0, 0.5, kappa, np.zeros(len(s.x)), np.zeros(len(s.x)), err)
        rate += sign * err
    dt = 1e-6
    moved = DFSPHSolver(s.x + dt * vel, np.zeros_like(s.x), s.id, s.sdf, spacing=L0, rho0=1000.0, params=s.p,
                        gravity=(0, 0, -G), mu=0.01)
    moved.refresh()
    after = np.empty(len(s.x))
    after[moved.id] = moved.rho
    before = np.empty(len(s.x))
    before[s.id] = s.rho
    real = np.empty(len(s.x))
    real[s.id] = rate
    actual = (after - before) / dt
    d = np.empty(len(s.x))
    d[s.id] = s.d
    far = d >= s.h
    # away from walls the rate is the exact derivative of the density (one kernel for both)
    assert np.abs(actual - real)[far].max() < 1e-3 * np.abs(actual).max()
    # near walls Psi is a central difference (step l0/4) of the trilinear wall map (poly6) or the spline
    # gradient's quadrature (spline), the map's slope jumping at its cell faces (l0/2): they agree in the
    # mean, not per particle
    assert np.corrcoef(actual[~far], real[~far])[0, 1] > 0.95


def _jacobi_run(gradient: str, support: float, omega: float | None, steps: int = 6) -> tuple[float, int]:
    """The test tank at water's viscosity from rest, ``steps`` steps with the solves relaxed by ``omega`` (None: the
    default; a value above the limit set past the validator, as a solver's own code could): the fastest particle
    and the iterations of the last density solve."""
    params = DFSPHParams(gradient=gradient, support=support)
    if omega is not None:
        object.__setattr__(params, "relaxation", omega)
    s = _tank(mu=0.001, params=params)
    it = 0
    for _ in range(steps):
        before = s.iterations[0]
        s.step(1.0)
        it = s.iterations[0] - before
    return float(np.linalg.norm(s.v, axis=1).max()), it


@pytest.mark.parametrize("gradient, support", [("spiky", 2.0), ("spiky", 3.0), ("poly6", 2.25)])
def test_the_solves_diverge_above_the_jacobi_limit_and_the_default_stays_below_it(gradient, support):
    """dfsph.jacobi_limit: 2 / the largest eigenvalue of the Jacobi-scaled system on the rest lattice. Relaxed 1.5 x
    that, the solves diverge on a resting tank (measured here: 1e3-1e21 m/s in 6 steps; from 0.95 x for Spiky at
    2 l0, 1.3 x at 3 l0, 1.15 x for Poly6 at 2.25 l0: walls and the free surface move the threshold). Spiky at 3 l0
    and Poly6 at 2.25 l0 diverged with the old fixed omega 0.5, and a step then never ended (sub-steps of a 1e30 m/s
    move). At the default (0.5, or 0.8 x the limit where that is less) the tank is DFSPH's resting tank (below 1
    m/s, the solves within their cap)."""
    from stages.simulate.dfsph import jacobi_limit
    limit = jacobi_limit(gradient, support)
    fast, _ = _jacobi_run(gradient, support, 1.5 * limit)
    assert fast > 20.0, fast
    fast, it = _jacobi_run(gradient, support, None)
    assert fast < 1.0 and it < DFSPHParams().max_iterations, (fast, it)


def test_a_relaxation_above_the_limit_is_refused_and_the_default_resolves_below_it():
    from pydantic import ValidationError
    from stages.simulate.dfsph import jacobi_limit
    assert jacobi_limit("spiky", 2.0) == pytest.approx(0.710, abs=1e-3)  # the lattice's modes (Fourier), as measured
    assert DFSPHParams().relaxation == 0.5  # the defaults as before: 0.5 is 0.7 of the limit
    assert DFSPHParams(gradient="spline").relaxation == 0.5
    assert DFSPHParams(gradient="poly6").relaxation == pytest.approx(0.8 * jacobi_limit("poly6", 2.0), abs=1e-3)
    assert DFSPHParams(support=3.0).relaxation == pytest.approx(0.8 * jacobi_limit("spiky", 3.0), abs=1e-3)
    assert DFSPHParams(relaxation=0.55).relaxation == 0.55
    with pytest.raises(ValidationError, match=r"relaxation 0\.6 is above 0\.568"):
        DFSPHParams(relaxation=0.6)


def test_dam_break_surge_front_and_density_error():
    """The column of tests/test_sph_dam_break.py (a = 0.1 m, H = 2a, 800 particles): surge front against
    Martin & Moyce up to T = 3, and the density error against the solver's bound."""
    from test_sph_dam_break import _reference
    a, l0, width, g = 0.1, 0.01, 0.04, 9.81
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([5 * a, width, 3 * a])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    x = lattice([0, 0, 0], [a, width, 2 * a], l0)
    params = DFSPHParams()
    s = DFSPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=params,
                    gravity=(0, 0, -g), mu=0.01)
    scale = np.sqrt(2 * g / a)
    front, err = [], []
    for T in np.arange(0.25, 3.0 + 1e-9, 0.25):
        s.advance_to(T / scale)
        xs = np.sort(s.x[:, 0])
        front.append((T, (xs[-3] + 0.5 * l0) / a))  # ignore lone droplets, as for sph
        err.append(np.maximum(s.rho / 1000.0 - 1, 0).mean())
    ref = _reference()
    ref = ref[ref[:, 0] <= 3.0]
    sim = np.array(front)
    z = np.interp(ref[:, 0], sim[:, 0], sim[:, 1])
    rel = (z - ref[:, 1]) / ref[:, 1]
    print("dfsph dam break rel. front error", rel.round(3).tolist(), "density error", np.mean(err), s.solver_stats())
    assert s.left_domain == 0 and s.x[:, 2].min() > 0
    # like sph, ahead of the experiment (its gate is not modelled): measured 6-10 % ahead
    assert np.all(rel > -0.05) and np.all(rel < 0.15), rel
    # every solve ended under its bound; the real density error (after the move) stays under 1 %
    assert s.solver_stats()["mean_density_solve_error"] <= params.max_density_error
    assert np.mean(err) < 0.01 and max(err) < 0.02
    assert s.solver_stats()["mean_density_iterations"] < 10


def test_bulk_particles_skipping_the_sdf_changes_nothing(monkeypatch):
    """DFSPH's integrate passes the density pass's wall distances, so particles far from the walls skip
    the SDF: the run is bitwise the run that tests every particle, here a breaking dam whose fast
    particles move farther in a step than DFSPH's sub-step limit near walls (r_rep 0.2 l0)."""
    from stages.common.sdf import wall_move_limit
    from stages.simulate import sph_kernels as K

    a, l0, width = 0.1, 0.01, 0.04
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([5 * a, width, 3 * a])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    x = lattice([0, 0, 0], [a, width, 2 * a], l0)
    integrate = K.integrate
    longest = []  # the longest move of a step, in units of the sub-step limit

    def run(bound: bool) -> DFSPHSolver:
        def traced(x, v, acc, dt, walls, r_rep, max_corr, max_move, travel=None, d=None):
            longest.append(dt * np.linalg.norm(v + dt * acc, axis=1).max() / max_move)
            integrate(x, v, acc, dt, walls, r_rep, max_corr, max_move, travel, d if bound else None)

        monkeypatch.setattr(K, "integrate", traced)
        s = DFSPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=DFSPHParams(),
                        gravity=(0, 0, -9.81), mu=0.001)
        s.advance_to(0.2)
        return s

    fast, slow = run(True), run(False)
    assert wall_move_limit(DFSPHParams().r_rep) < 0.5 and max(longest) > 1.0  # some moves were sub-stepped
    assert np.abs(fast.v).max() > 0.5 and fast.x[:, 0].max() > 0.2  # the surge ran along the floor
    assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.v, slow.v) and fast.steps == slow.steps


L0_STAGE = 0.02
SCENE = {
    "scene": {"name": "t", "frames": {"fps": 50, "count": 7}, "units": {"up_axis": "Z"}},
    "fluid": {"spacing": L0_STAGE, "emitters": [{"box": {"min": [0, 0, 0], "max": [0.12, 0.2, 0.2]}}]},
    "effects": {"gravity": {}, "viscosity": {"mu": 0.01}},
}


def _ctx(out: Path, ckpt: Path | None) -> Context:
    sections = scene_sections(SCENE)
    return stage_context(DFSPHSimulate, out, scene=sections, frames=tuple(range(7)), log=logging.getLogger("t"),
                         checkpoint_dir=ckpt)


def test_stage_resume_from_checkpoint_is_bitwise_identical(tmp_path):
    folder = tmp_path / "sdf"
    folder.mkdir()
    grid_from_function(box_interior_sdf([0, 0, 0], [0.3, 0.2, 0.4]), [0, 0, 0], [0.3, 0.2, 0.4],
                       L0_STAGE / 2).save(folder)
    arts = {"sdf": Artifact(name="sdf", key="t", path=folder)}
    params = DFSPHSimulate.Params(threads=1, checkpoint_every=2)
    straight = tmp_path / "straight"
    straight.mkdir()
    DFSPHSimulate().run(_ctx(straight, tmp_path / "ck_straight"), arts, params)
    ck = tmp_path / "ck"
    shutil.copytree(tmp_path / "ck_straight", ck)
    for p in ck.glob("state_*.npz"):
        if p.name != "state_00004.npz":
            p.unlink()
    for f in (5, 6):
        (ck / "frames" / f"{f:05d}.npz").unlink(missing_ok=True)
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    DFSPHSimulate().run(_ctx(resumed, ck), arts, params)
    for f in range(7):
        a, b = load_particle_frame(straight, f), load_particle_frame(resumed, f)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and np.array_equal(a.p, b.p)
    meta = ParticleMeta.load(straight)
    assert meta.solver == "dfsph" and meta.stats["summary"]["inside_wall_max"] == 0
    assert load_particle_frame(straight, 6).x[:, 2].min() > 0.0


@pytest.mark.xfail(strict=True, reason="a resting tank under gravity does not stay at rest: the column bounces "
                   "and boils (mean speed 0.1-0.3 m/s), see the dfsph.py docstring")
def test_hydrostatic_tank_stays_at_rest():
    """10 x 10 x 20 particles at rest in a box: after 0.1 s still at rest, density error under 1 %, the
    pressure 10 and 20 particles below the surface within 5 % of rho g h (h from the surface, l0/2 above
    the top layer; the mean over the layer away from the side walls), no particle below the floor."""
    s = _tank()
    s.advance_to(0.1)
    assert np.linalg.norm(s.v, axis=1).max() < 0.05
    assert np.maximum(s.rho / 1000.0 - 1, 0).mean() < 0.01
    assert s.x[:, 2].min() > 0.0
    f = s.frame()
    top = f.x[:, 2].max() + 0.5 * L0
    inner = np.all(np.abs(f.x[:, :2] - W / 2) < W / 2 - 2.5 * L0, axis=1)
    for depth in (10, 20):
        z = H - (depth - 0.5) * L0
        layer = inner & (np.abs(f.x[:, 2] - z) < 0.5 * L0)
        assert layer.sum() >= 16
        assert f.p[layer].mean() == pytest.approx(1000.0 * G * (top - z), rel=0.05)


@pytest.mark.parametrize("source", ["block", "jet"])
def test_dfsph_makes_no_energy_in_a_narrow_pipe(source, tmp_path, caplog):
    """One column of particles in a pipe 2.5 spacings wide (a block released in it), or a pipe 3.5 spacings wide
    fed by a jet 2 spacings across from 15 cm up (what the inflow brings booked: SolverBase.flowed). DFSPH's
    energy (kinetic + gravitational) rose 90-200 % above the start's with the block and 17-23 % above the start's
    and the jet's, its top particle above its release height: the solves' error counted compression only, so a
    warm-started pressure that pushed the column apart passed as converged. With the complementarity residual
    (session 39, dfsph_kernels) it falls as WCSPH's does: the energy budget says nothing, and with the block the
    energy of every frame is below the start's (at most 0.973 of it, measured, water's viscosity). Before
    session 39 the budget's warning (a rise above 10 %) was tested on this DFSPH run; EnergyBudget's own test is in
    tests/stability/test_blowup.py."""
    from stages.mesh_import.trimesh_import import TrimeshImport
    from stages.sdf_bake.open3d_bake import Open3dBake
    from stages.simulate.sph import SPHSimulate

    scene = {"scene": {"name": "pipe", "frames": {"fps": 10, "count": 9}},
             "walls": [{"builtin": "cylinder", "size": [0.05, 0.05, 0.4]}],
             "fluid": {"spacing": 0.02, "emitters": [{"box": {"min": [-0.01, -0.01, 0.1], "max": [0.01, 0.01, 0.3]}}]},
             "effects": {"gravity": {}, "viscosity": {"mu": 0.001}}}
    if source == "jet":
        scene["walls"][0]["size"] = [0.07, 0.07, 0.4]
        scene["fluid"] = {"spacing": 0.02, "inflow": [{"center": [0, 0, 0.15], "direction": [0, 0, -1],
                                                       "radius": 0.02, "speed": 0.5, "end": 0.3}]}
    run_stage(TrimeshImport, tmp_path / "walls", scene=scene)
    run_stage(Open3dBake, tmp_path / "sdf", scene=scene, inputs={"walls": tmp_path / "walls"})
    for name, stage in (("dfsph", DFSPHSimulate), ("sph", SPHSimulate)):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            out = run_stage(stage, tmp_path / name, scene=scene, params={"threads": 1}, inputs={"sdf": tmp_path / "sdf"})
        stats = ParticleMeta.load(out).stats
        assert "energy the method made" not in caplog.text and "energy_rise" not in stats, (name, caplog.text)
        if source == "jet":
            assert stats["inflow_particles"] >= 20
            continue
        frames = [load_particle_frame(out, f) for f in range(9)]
        assert len(frames[0]) == 10
        base = frames[0].x[:, 2].min()
        energy = [float(0.5 * np.sum(f.v ** 2) + G * np.sum(f.x[:, 2] - base)) for f in frames]
        assert max(energy[1:]) < energy[0], (name, [e / energy[0] for e in energy])
        top = max(float(f.x[:, 2].max()) for f in frames[1:])
        assert top < frames[0].x[:, 2].max(), (name, top)  # no particle above where the column's top was released


def test_a_solve_stopped_at_its_cap_is_named_as_a_blow_ups_likely_cause():
    """A blow-up whose step was within the time-step limits blamed 'the pressure solve or the spacing' and advised
    a smaller cfl, whatever the solve had done; a solve that stopped at max_iterations short of its tolerance is
    now named with its error and the setting to change."""
    from stages.simulate.driver import Guard
    capped = _tank(jitter=0.05, max_iterations=1, min_iterations=1, max_divergence_error=1e-9)
    capped.advance_to(0.002)
    cause = Guard(v_bound=2.0, l0=L0)._cause(capped, 0.002)
    assert cause.startswith("the density solve stopped at max_iterations (1) with an average error of "), cause
    assert "raise max_iterations" in cause
    solved = _tank(jitter=0.05)
    solved.advance_to(0.002)
    assert solved.unconverged() is None
    assert "the pressure solve" in Guard(v_bound=2.0, l0=L0)._cause(solved, 0.002)


def test_the_energy_warning_names_dfsphs_churn_for_dfsph_only():
    """A DFSPH U-tube 6 spacings wide made 48 % more energy and was told to look for a passage narrower than 3
    spacings: the warning now names DFSPH's churn in slow water, and sph for such scenes, where DFSPH runs."""
    from types import SimpleNamespace

    from stages.simulate.driver import EnergyBudget

    dfsph = EnergyBudget.causes(SimpleNamespace(kappa_v=np.zeros(3)))
    assert "DFSPH's churn in slow or still water" in dfsph and "simulate: {use: sph}" in dfsph
    assert "DFSPH" not in EnergyBudget.causes(SimpleNamespace()) and "narrower than about 3" in EnergyBudget.causes(SimpleNamespace())
