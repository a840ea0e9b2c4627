"""Blow-up detection through the CLI: a time step far above the stable one ends in one line naming the
frame, the time, the count and the likely cause, exit 1, with the state saved for inspection."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import main
from stability_cases import run_case

TANK = """\
config_version: 1
scene:
  name: tank
  units: {meters_per_unit: 1.0, up_axis: Z}
  frames: {fps: 20, count: 4}
walls:
  - builtin: box_tank
    size: [0.3, 0.2, 0.4]
    center: [0.0, 0.0, 0.0]
fluid:
  spacing: 0.025
  emitters:
    - box: {min: [-0.15, -0.1, 0.0], max: [0.15, 0.1, 0.25]}
effects:
  gravity: {}
  viscosity: {mu: 0.001}
stages:
  simulate: {use: SOLVER}
outputs: [frames]
"""


def _run(tmp_path: Path, solver: str, *sets: str):
    cfg = tmp_path / "tank.yaml"
    cfg.write_text(TANK.replace("SOLVER", solver))
    args = ["run", str(cfg), "--until", "simulate", "--cache", str(tmp_path / "cache")]
    for s in sets:
        args += ["--set", s]
    return CliRunner().invoke(main, args)


def test_time_step_far_above_stable_exits_1_with_one_line(tmp_path):
    r = _run(tmp_path, "sph", "simulate.time_step=0.01")  # 20 x the acoustic limit
    assert r.exit_code == 1, r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.output
    line = err[0]
    assert re.search(r"blew up during frame \d+", line)
    assert re.search(r"at t = [0-9.e-]+ s \(\d+ particles\)", line)
    assert "likely cause: the time step" in line
    saved = Path(re.search(r"state saved in (\S+\.npz)", line).group(1))
    with np.load(saved) as z:  # the state at the blow-up, to inspect
        v = z["v"]
    assert len(v) > 0 and not np.all(np.isfinite(v).all(axis=1) & (np.linalg.norm(v, axis=1) < 13.8))
    # the resume never picks the blown-up state up: a sane run of the same scene starts afresh and succeeds
    assert _run(tmp_path, "sph").exit_code == 0


@pytest.mark.parametrize("solver, field", [("sph", "time_step"), ("mps", "time_step"), ("dfsph", "dt_max")])
def test_a_fixed_step_below_the_floor_is_named_before_the_run(tmp_path, solver, field):
    """The tank's floor is 1e-3 l0 / its ballistic bound (about 9e-6 s): a fixed step below it stopped the run at its
    first step as a blow-up, advising a smaller cfl."""
    r = _run(tmp_path, solver, f"stages.simulate.{field}=1e-6")
    assert r.exit_code == 2, r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.output and "blew up" not in err[0], r.output
    assert f"{field} 1e-06 s is below this scene's time-step floor" in err[0]
    assert not list(tmp_path.glob("cache/simulate/**/*.npz"))  # the stages before it ran and are kept


def test_a_sound_speed_near_the_flow_speed_is_warned_of(tmp_path, caplog):
    """WCSPH compresses by about (v / c)^2: sound_speed 1 m/s flattened a dam break's column to a quarter of its height
    with densities of 6 rho0 and nothing said."""
    r = _run(tmp_path, "sph", "stages.simulate.sound_speed=1")
    said = " ".join((r.output + caplog.text).split())  # the console wraps its lines
    assert "sound_speed 1 m/s is 0.36 x the scene's ballistic speed bound 2.76 m/s" in said, said
    (tmp_path / "default").mkdir()
    r = _run(tmp_path / "default", "sph")
    assert r.exit_code == 0 and "ballistic speed bound" not in r.output, r.output


@pytest.mark.parametrize("solver, setting, advice", [
    ("mps", "stages.simulate.compressibility=1e-6", "lower compressibility"),
    ("sph", "stages.simulate.sound_speed=1", "raise sound_speed"),
    ("dfsph", "stages.simulate={use: dfsph, max_iterations: 1, min_iterations: 1}", "raise max_iterations")])
def test_water_compressed_beyond_a_liquid_is_warned_of_where_the_run_ends(tmp_path, caplog, solver, setting, advice):
    """MPS's compressibility 1e-6 (allowed: any alpha >= 0) compressed the tank's water by 4.7 % on average, 12 % at
    most, and a dam break's by 2 % with peaks of 16 %, and nothing was said; the defaults keep under 0.4 %."""
    r = _run(tmp_path, solver, setting)
    said = " ".join((r.output + caplog.text).split())
    assert r.exit_code == 0, r.output
    m = re.search(rf"simulate.{solver}: the water is compressed by ([0-9.]+) % on average at frame (\d+)", said)
    assert m and float(m.group(1)) > 1.0 and advice in said, said
    (tmp_path / "default").mkdir()
    caplog.clear()
    r = _run(tmp_path / "default", solver)
    assert r.exit_code == 0 and "compressed by" not in r.output + caplog.text, r.output


def test_wcsphs_default_sound_speed_counts_the_wind(tmp_path):
    """The default sound speed (10 x the expected speed) counted falling and the emitters only: a 30 m/s wind
    (drag 5 1/s) left it at 22 m/s and the tank's water compressed by up to 12.7 % (an attractor in a 1 m tank,
    28,000 %). It now counts the wind's speed: 322 m/s, at most 2.3 %."""
    from stages.common.formats import ParticleMeta

    r = _run(tmp_path, "sph", "effects.wind={velocity: [30, 0, 0], drag: 5}", "scene.frames.count=7")
    assert r.exit_code == 0, r.output
    stats = ParticleMeta.load(next((tmp_path / "cache").glob("simulate/*/*/meta.json")).parent).stats
    assert stats["sound_speed"] > 10 * 30.0, stats["sound_speed"]
    assert max(stats["density_error_max"]) < 0.05, max(stats["density_error_max"])


def _drop(tmp_path: Path, mpu: float, up: str) -> dict:
    """A 0.2 x 0.2 x 0.1 m slab released 0.5 m over the floor of a 0.7 m tank, in scene units of ``mpu`` m, ``up`` up."""
    import yaml

    from stages.common.formats import ParticleMeta

    k = 1.0 / mpu
    lo, hi, size = np.array([-0.1, -0.1, 0.5]) * k, np.array([0.1, 0.1, 0.6]) * k, np.array([0.2, 0.2, 0.7]) * k
    if up == "Y":  # the same scene, Y up: (x, y, z) -> (x, z, -y)
        lo, hi = np.array([lo[0], lo[2], -hi[1]]), np.array([hi[0], hi[2], -lo[1]])
        size = size[[0, 2, 1]]
    config = {"config_version": 1,
              "scene": {"name": "drop", "units": {"meters_per_unit": mpu, "up_axis": up}, "frames": {"fps": 30, "count": 13}},
              "walls": [{"builtin": "box_tank", "size": size.tolist()}],
              "fluid": {"spacing": 0.02 * k, "emitters": [{"box": {"min": lo.tolist(), "max": hi.tolist()}}]},
              "effects": {"gravity": {}, "viscosity": {"mu": 0.001}},
              "stages": {"simulate": {"use": "sph"}}, "outputs": ["particles"]}
    cfg = tmp_path / f"drop_{up}.yaml"
    cfg.write_text(yaml.safe_dump(config))
    cache = tmp_path / f"cache_{up}"
    r = CliRunner().invoke(main, ["run", str(cfg), "--cache", str(cache)])
    assert r.exit_code == 0 and "compressed by" not in r.output, r.output
    return ParticleMeta.load(next(cache.glob("simulate/*/*/meta.json")).parent).stats


def test_wcsphs_default_sound_speed_counts_the_fall_to_the_floor(tmp_path):
    """The default sound speed (10 x the expected speed) counted the fluid's own thickness and the emitters' speed,
    not the fall under it: a 0.1 m slab released 0.5 m over the floor got 14 m/s for a 3.4 m/s landing, compressed
    by up to 23 % where it landed and was told to "raise sound_speed, or leave it out", which it had (the shipped
    open bowl's slab: 9.7 m/s, 63 %). The fall to the wall under the fluid now counts: 10 sqrt(2 g 0.62 m) = 35 m/s,
    4.9 %, nothing said; the same in centimetres with Y up."""
    m = _drop(tmp_path, 1.0, "Z")
    assert m["sound_speed"] >= 10 * np.sqrt(2 * 9.81 * 0.6), m["sound_speed"]
    assert max(m["density_error_max"]) < 0.08, max(m["density_error_max"])
    cm = _drop(tmp_path, 0.01, "Y")
    assert cm["sound_speed"] == pytest.approx(m["sound_speed"], rel=1e-6)
    assert max(cm["density_error_max"]) == pytest.approx(max(m["density_error_max"]), rel=0.05)


def test_an_effect_counts_in_the_speed_bound_only_by_what_it_can_give():
    """Wind with drag 0 moves nothing and an attractor of 1e12 1,000 km away pulls at 1 m/s^2 (2.4 m/s across a 3 m
    tank), but the bound counted the wind's 1,000 m/s and the attractor's escape speed sqrt(2 k / s), 3.5e6 m/s: a false warning
    of shrinking steps, and a guard so loose that a viscous blow-up (41 m/s in a 3 m tank) ended in exit 0."""
    from stages.simulate.driver import effects_speed
    from stages.simulate.effects import EffectConstants

    corners = np.array([[a, b, c] for a in (-1.5, 1.5) for b in (-1.0, 1.0) for c in (-0.6, 0.6)])
    still = EffectConstants(wind_velocity=np.array([1000.0, 0, 0]), wind_drag=0.0)
    assert effects_speed(still, corners) == 0.0
    assert effects_speed(EffectConstants(wind_velocity=np.array([30.0, 40.0, 0]), wind_drag=1.0), corners) == 50.0
    far = EffectConstants(attractor_point=np.array([1e6, 0, 0]), attractor_k=1e12, attractor_soft=0.17)
    assert 2.4 < effects_speed(far, corners) < 2.5  # sqrt(2 k (1/r_near - 1/r_far)), as 1 m/s^2 over 3 m
    inside = EffectConstants(attractor_point=np.zeros(3), attractor_k=1e5, attractor_soft=0.17)
    escape = np.sqrt(2 * 1e5 / 0.17)
    assert 0.9 * escape < effects_speed(inside, corners) < escape  # all but the far corners' potential
    repel = EffectConstants(attractor_point=np.zeros(3), attractor_k=-1e5, attractor_soft=0.17)
    assert effects_speed(repel, corners) == effects_speed(inside, corners)


@pytest.mark.parametrize("solver, mu", [("sph", 1e4), ("dfsph", 3e4)])
def test_a_very_viscous_block_flows_without_particles_thrown_out(tmp_path, solver, mu):
    """The viscous step limit, 0.125 h^2 / nu, was 0.94-0.98 of the viscosity sum's own stability limit on the rest
    lattice (timestep.viscous_coefficient), and walls and the free surface tipped it over: the dam break's block
    at 1e4 Pa s (a 1 m block, 1/12 m spacing) threw WCSPH particles out at 4-16 m/s, 3 x the ballistic bound, while
    the flow moved at 0.05-0.15 m/s, and DFSPH at 3e4 blew up in its first frame. Now at 0.8 of the limit: no
    particle far above the flow (the Stokes scale rho g H^2 / mu is 1 m/s at 1e4, 0.3 at 3e4)."""
    root = Path(__file__).resolve().parents[2]
    args = ["run", str(root / "configs/dam_break.yaml"), "--until", "simulate", "--cache", str(tmp_path / "cache"),
            "--out", str(tmp_path / "out"), "--set", "fluid.spacing=0.0833333", "--set", "scene.frames.count=10",
            "--set", f"stages.simulate={{use: {solver}}}", "--set", f"effects.viscosity.mu={mu:g}"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    frames = sorted((tmp_path / "cache").glob("simulate/*/*/frames/*.npz"))
    speeds = [np.linalg.norm(np.load(f)["v"], axis=1) for f in frames]
    fastest = max(float(v.max()) for v in speeds)
    assert fastest < 0.5 and fastest < 2.0 * max(float(np.percentile(v, 99)) for v in speeds), fastest


def test_a_viscosity_whose_steps_a_frame_end_would_halve_below_the_floor_is_refused_before_the_run(tmp_path):
    """MPS at 3e4 Pa s in the dam break needs steps of 2.9e-5 s against a floor of 1.6e-5 s: a frame's last step,
    split in halves, fell below it and the run stopped as a blow-up after its first frame."""
    root = Path(__file__).resolve().parents[2]
    args = ["run", str(root / "configs/dam_break.yaml"), "--until", "simulate", "--cache", str(tmp_path / "cache"),
            "--out", str(tmp_path / "out"), "--set", "fluid.spacing=0.0833333", "--set", "scene.frames.count=10",
            "--set", "stages.simulate={use: mps}", "--set", "effects.viscosity.mu=3e4"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2, r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "effects.viscosity.mu (30000 Pa s) needs time steps of 2.89e-05 s" in err[0], r.output
    assert not list((tmp_path / "cache").glob("simulate/**/*.npz"))


def test_a_rate_that_shortens_every_step_far_below_the_flows_is_warned_of(tmp_path, caplog):
    """A wall friction of 2e4 1/s (allowed up to where its step meets the floor) needs steps of 2.5e-5 s: a dam break
    ran 28 x its steps with the fluid all but frozen, and nothing was said."""
    r = _run(tmp_path, "sph", "effects.wall_friction={rate: 20000}")
    said = " ".join((r.output + caplog.text).split())
    assert r.exit_code == 0, r.output
    assert "effects.wall_friction.rate (20000 1/s) needs time steps of 2.5e-05 s, 145 x shorter than the flow's" in said
    (tmp_path / "default").mkdir()
    caplog.clear()
    r = _run(tmp_path / "default", "sph", "effects.wall_friction={rate: 5}", "effects.viscosity={mu: 10}")
    assert r.exit_code == 0 and "shorter than the flow's" not in r.output + caplog.text, r.output


def test_dfsph_at_a_large_support_runs_and_a_relaxation_beyond_its_limit_is_refused_in_one_line(tmp_path):
    """DFSPH allows a support up to 4 l0; from 2.5 l0 its Jacobi solves diverged at the fixed relaxation 0.5 and the
    run hung in its first step. The relaxation now defaults below the solves' limit for the kernel and support
    (dfsph.jacobi_limit), and a value beyond 0.8 of it is a config error naming it."""
    assert _run(tmp_path, "dfsph", "stages.simulate.support=3").exit_code == 0
    (tmp_path / "refused").mkdir()
    r = _run(tmp_path / "refused", "dfsph", "stages.simulate.relaxation=0.9")
    assert r.exit_code != 0
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.output, r.output
    assert "tank.yaml" in err[0] and "stages.simulate" in err[0] and "relaxation 0.9 is above 0.568" in err[0]
    assert not list((tmp_path / "refused").glob("cache/**/*.npz"))


@pytest.mark.parametrize("solver", ["sph", "dfsph"])
@pytest.mark.parametrize("effect, name", [("effects.wall_friction={rate: 1e9}", "effects.wall_friction.rate"),
                                          ("effects.wind={velocity: [1, 0, 0], drag: 1e9}", "effects.wind.drag")])
def test_an_effect_whose_rate_needs_a_step_below_the_floor_is_named_before_the_run(tmp_path, solver, effect, name):
    """It ran into the time-step floor at the first step and blamed 'the stiffness or the spacing'."""
    r = _run(tmp_path, solver, effect)
    assert r.exit_code == 2, r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and name in err[0] and "lower it" in err[0] and "Traceback" not in r.output


def test_a_surface_tension_no_liquid_has_is_refused_in_one_line(tmp_path):
    """1e6 N/m used to blow the run up (the sound speed ignored the capillary speed); with the capillary speed
    in the sound speed it would crawl on at steps of 2e-6 s: refused before anything runs instead."""
    r = _run(tmp_path, "sph", "effects.surface_tension={gamma: 1e6}")
    assert r.exit_code == 2, r.output
    line = r.output.strip().splitlines()[-1]
    assert "effects.surface_tension.gamma" in line and "10" in line, r.output
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").glob("simulate/*/*"))


def test_particles_through_a_wall_stop_the_run():
    """No speed or step limit notices particles carried through a wall by a step far above the stable one (MPS
    survives such steps): at a frame's end the guard counts particles deeper than INSIDE_DEPTH spacings inside a
    static wall (or gone through it and out of the grid) and stops the run naming the time step."""
    import stages.simulate.driver as D
    from stages.common.sdf import box_interior_sdf, grid_from_function
    from stages.simulate.sph import SPHParams, SPHSolver

    l0 = 0.02
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [0.2, 0.2, 0.2]), [0, 0, 0], [0.2, 0.2, 0.2], l0 / 2)
    for depth, caught in ((0.0, False), (0.2, False), (0.3, True)):
        x = np.array([[0.1, 0.1, 0.1], [0.1, 0.1, -depth * l0 + 1e-9]])
        s = SPHSolver(x, np.zeros_like(x), np.arange(2), sdf, spacing=l0, rho0=1000.0, params=SPHParams())
        s.guard = D.Guard(v_bound=1.0, l0=l0)
        s.x = x.copy()  # where a bad step left them (the next step's projection may not undo it)
        try:
            s.guard.check(s, 1e-3, last_of_frame=True)
            got = None
        except D.BlowUp as e:
            got = str(e)
        assert (got is not None) == caught, (depth, got)
        if caught:
            assert "inside a wall or through it" in got and "(1 particles)" in got and "likely cause" in got
    outside = np.array([[0.1, 0.1, 0.1], [0.1, 0.1, -0.5]])  # through the floor and out of the grid
    s.x = outside
    try:
        s.guard.check(s, 1e-3, last_of_frame=True)
        raise AssertionError("a particle below the tank's grid was not caught")
    except D.BlowUp as e:
        assert "(1 particles)" in str(e)
    s.guard.check(s, 1e-3, last_of_frame=False)  # the check is at frames' ends only


class _Fluid:
    """What Guard.check reads of a solver: positions, velocities, the clock, what flowed in and out."""
    flowed = (0.0, 0)
    gravity = np.array([0.0, 0.0, -9.81])
    inflows = ()

    def __init__(self, x, v):
        self.x, self.v, self.t = x, v, 0.1

    def take(self, k: int) -> "_Fluid":
        """The fluid after a sink took particle ``k`` (booked as SolverBase.drain_sinks books it)."""
        import stages.simulate.driver as D
        keep = np.arange(len(self.x)) != k
        D.SolverBase._book(self, self.x[k:k + 1], self.v[k:k + 1], -1)
        out = _Fluid(self.x[keep], self.v[keep])
        out.flowed = self.flowed
        return out


@pytest.mark.parametrize("others_pay", [True, False])
def test_a_fast_particle_is_a_blow_up_only_if_the_fluid_energy_rose(others_pay):
    """One particle at 20 x the ballistic bound. If the rest of the fluid lost the energy it carries (pressure
    focusing it: a void closing in a cone's apex), the run goes on and the event is counted; if the fluid's
    energy rose by it (a solver making energy), the run stops. What a sink took is booked, not a change of the
    fluid's energy (the guard fell back to the strict limit after any sink's removal, so a tank with a drain
    had no energy test). Without gravity given, the guard is the strict speed limit."""
    import stages.simulate.driver as D

    rng = np.random.default_rng(1)
    n, g = 400, np.array([0.0, 0.0, -9.81])
    x = rng.uniform(0.0, 0.1, (n, 3))
    v = np.zeros((n, 3))
    v[:, 2] = -2.0
    guard = D.Guard(v_bound=1.0, l0=0.01, gravity=g, base=0.0)
    fluid = _Fluid(x, v.copy())
    with pytest.raises(D.BlowUp):  # no reference yet (a check outside an advance): the strict limit
        guard.check(_Fluid(x, np.full((n, 3), 20.0)), 1e-4, last_of_frame=False)
    guard.start_frame(fluid)  # where the advance to the frame's time begins: the reference energy
    e0 = D.mechanical_energy(fluid, g, 0.0)
    fluid.v[0] = [0.0, 0.0, -20.0]
    if others_pay:  # the others slowed so that the total is what it was
        potential = float(np.sum(-(x @ g)))
        fluid.v[1:, 2] = -np.sqrt((2.0 * (e0 - potential) - 400.0) / (n - 1))
        assert abs(D.mechanical_energy(fluid, g, 0.0) - e0) < 1e-6 * e0
        guard.check(fluid, 1e-4, last_of_frame=True)
        assert guard.focus_steps == 1 and guard.focus_peak[0] == pytest.approx(20.0) and guard.focus_peak[2] == 1
        top = int(np.argmax(-(x @ g)))  # a sink took the highest particle: its energy left the sum, booked
        guard.check(fluid.take(top), 1e-4, last_of_frame=True)
        assert guard.focus_steps == 2
        unbooked = _Fluid(np.delete(fluid.x, top, axis=0), np.delete(fluid.v, top, axis=0))
        unbooked.v[1:, 2] *= 1.1  # gone unbooked, and the others faster: the fluid made energy, strict
        with pytest.raises(D.BlowUp):
            guard.check(unbooked, 1e-4, last_of_frame=True)
    else:
        with pytest.raises(D.BlowUp, match=r"speed 20 m/s above 10 x .* \(1 particles\)"):
            guard.check(fluid, 1e-4, last_of_frame=True)
    strict = D.Guard(v_bound=1.0, l0=0.01)
    strict.start_frame(fluid)
    with pytest.raises(D.BlowUp):
        strict.check(fluid, 1e-4, last_of_frame=True)


def test_the_energy_budget_says_a_rise_once_books_flows_and_resumes_from_the_shots_start(caplog):
    """EnergyBudget (driver.py) on a fluid whose energy is set by hand: a rise of more than 10 % above the start's
    is said once, with its frame, and kept (``said``); what an inflow brings (booked in ``flowed``) is no rise,
    the same energy unbooked is; a budget built where a run resumes, given the checkpoint's entries, judges
    against the shot's start (built alone, it took the resumed frame's energy as its start and said a rise that
    was none)."""
    import logging
    from types import SimpleNamespace

    import stages.simulate.driver as D

    log = logging.getLogger("t")
    g = np.array([0.0, 0.0, -9.81])
    effects = SimpleNamespace(wind=None, attractor=None, surface_tension=None, wall_adhesion=None)
    sdf = SimpleNamespace(origin=np.zeros(3), upper=np.ones(3))
    setup = SimpleNamespace(effects=effects, bodies=(), inflows=(), gravity=g, domain=None, sdf=sdf)
    x = np.column_stack([np.zeros(10), np.zeros(10), np.linspace(0.0, 0.09, 10)])
    fluid = _Fluid(x, np.zeros((10, 3)))
    budget = D.EnergyBudget(setup, fluid)
    e0 = budget.energy(fluid)  # 9.81 x (0 + 0.01 + ... + 0.09) J/kg
    fluid.v[:, 2] = np.sqrt(2 * 0.05 * e0 / 10)  # +5 %: not said
    with caplog.at_level(logging.WARNING):
        budget.check(fluid, 1, log)
        assert budget.said is None and not caplog.text
        fluid.v[:, 2] = np.sqrt(2 * 0.2 * e0 / 10)  # +20 %
        budget.check(fluid, 2, log)
        budget.check(fluid, 3, log)
    assert budget.said[0] == 2 and budget.said[1] == pytest.approx(0.2) and caplog.text.count("above the start") == 1
    # a run resumed at a frame where the fluid had lost energy: built alone, its start is that frame's
    slow = _Fluid(x * 0.5, np.zeros((10, 3)))
    alone, carried = D.EnergyBudget(setup, slow), D.EnergyBudget(setup, slow)
    carried.load_state(D.EnergyBudget(setup, fluid).state())  # the checkpoint of a run that said nothing yet
    back = _Fluid(x * 0.8, np.zeros((10, 3)))  # below the shot's start, 60 % above the resumed frame's
    alone.check(back, 5, log)
    carried.check(back, 5, log)
    assert alone.said is not None and carried.said is None
    carried.load_state(budget.state())  # said before the checkpoint: kept, not said again
    assert carried.said == budget.said
    # an inflow: a particle brought at 2 m/s, 1 m up, is no rise when booked, and one when not
    jet = SimpleNamespace(swept_points=lambda: np.array([[0.0, 0.0, 1.0]]))
    fed = SimpleNamespace(**{**vars(setup), "inflows": (jet,)})
    for booked in (True, False):
        pool = _Fluid(x.copy(), np.zeros((10, 3)))
        b = D.EnergyBudget(fed, pool)
        new_x, new_v = np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -2.0]])
        if booked:
            D.SolverBase._book(pool, new_x, new_v, 1)
        pool.x, pool.v = np.vstack([pool.x, new_x]), np.vstack([pool.v, new_v])
        b.check(pool, 1, log)
        assert (b.said is None) == booked, (booked, b.said)


@pytest.mark.parametrize("solver", ["dfsph", "mps"])
def test_water_poured_into_a_cone_at_a_fine_spacing_is_no_blow_up(solver, monkeypatch):
    """The stability suite's closed cone at 0.7 cm: where the converging water closes over the apex, the void
    below it collapses and throws one or two particles into the apex at 12-14 x the ballistic bound (Rayleigh's
    collapse is singular: the peak grows as the spacing shrinks; 1.4-2.1 x at 2 cm). The guard stopped both
    incompressible solvers here as a blow-up, advising a finer spacing. (DFSPH's peak here is 13.0 x since session
    39's change of its solves' error, which stopped the energy it made in the apex: the end's energy 0.75 of the
    start's.) The fluid's energy did not rise (it fell),
    so the guard lets it through: the run ends with nothing inside a wall, none escaped, no energy made."""
    import stability_cases as S
    monkeypatch.setitem(S.CASES, "cone_40deg", lambda: S.cone(l0=0.007))
    monkeypatch.setitem(S.SHORT, "cone_40deg", 0.16)  # past the collapse (0.146 s)
    r = run_case("cone_40deg", solver)
    print(r.row())
    assert r.blowup is None, r.blowup
    assert r.inside_walls == 0 and r.escaped == 0
    assert r.energy_ratio < 1.0, r.energy_ratio


CONE = """\
config_version: 1
scene:
  name: cone
  units: {meters_per_unit: MPU, up_axis: UP}
  frames: {fps: 50, count: 9}
walls:
  - file: cone.ply
    fluid: inside
fluid:
  spacing: SPACING
  emitters:
    - box: {min: BOX_MIN, max: BOX_MAX}
effects:
  gravity: {}
  viscosity: {mu: 0.001}
stages:
  simulate: {use: mps}
outputs: [frames]
"""


def _cone_run(folder: Path, scale: float, up: str, *extra: str) -> tuple:
    """The cone model (0.45 m tall, 40 degrees, apex down) and a block over it, in units of 1 / scale m with the
    given up axis, through a pipeline run (``extra``: more CLI options; the folder is reused if it exists): (the
    CLI's result, the newest meta.json's stats)."""
    import math

    import trimesh

    from stages.common.formats import ParticleMeta

    folder.mkdir(exist_ok=True)
    cone = trimesh.creation.cone(radius=0.45 * math.tan(math.radians(20.0)), height=0.45, sections=96)
    cone.apply_transform(trimesh.transformations.rotation_matrix(math.pi, [1, 0, 0]))  # the apex down, at z = 0
    cone.apply_translation([0.0, 0.0, -cone.bounds[0][2]])
    cone.apply_scale(scale)
    lo, hi = [-0.091, -0.091, 0.25], [0.091, 0.091, 0.37]
    if up == "Y":  # z up -> y up
        cone.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, [1, 0, 0]))
        lo, hi = [lo[0], lo[2], -hi[1]], [hi[0], hi[2], -lo[1]]
    cone.export(folder / "cone.ply")
    cfg = folder / "cone.yaml"
    cfg.write_text(CONE.replace("MPU", str(1.0 / scale)).replace("UP", up).replace("SPACING", str(0.007 * scale))
                   .replace("BOX_MIN", str([scale * v for v in lo])).replace("BOX_MAX", str([scale * v for v in hi])))
    r = CliRunner().invoke(main, ["run", str(cfg), "--until", "simulate", "--cache", str(folder / "cache"), *extra])
    meta = max((folder / "cache" / "simulate").rglob("meta.json"), key=lambda p: p.stat().st_mtime, default=None)
    return r, (ParticleMeta.load(meta.parent).stats if meta is not None else None)


def test_a_cone_run_through_the_cli_reports_the_focusing_and_ends_well(tmp_path, monkeypatch):
    """The same collapse through a pipeline run (a cone model, MPS at 0.7 cm, 0.16 s), in metres with Z up and in
    centimetres with Y up: exit 0, the log says once how many steps had particles above the limit and the fastest,
    meta.json's stats keep it, and both units give the same flow: the same density errors (mean and largest) in
    every frame before the collapse within 2 % (1e-4 measured), and the collapse at the same time within 1 ms
    (0.14377 and 0.14387 s measured), above the limit in both. The test holds the guard's limit at 5 x. The peak itself
    is not compared: the collapse is singular, and how far above 10 x it goes is set by the last few particles in
    the apex, which the start's round-off decides (pairs of peaks measured with three versions of the start's
    packing in session 40: 13.95 / 11.12, 9.63 / 10.96, 11.2 / 15.1 x; one of them fell below the default 10 x).
    Before the energy test this run ended in exit 1, "blew up during frame 8: speed ... above 10 x the scene's
    ballistic bound". (Until session 39 the run was DFSPH's, 13.05 and 13.04 x; the solves' new error, which stops
    DFSPH making energy in the apex, moves its peak: 8.8 x with the full complementarity residual, 13.0 x with the
    kept weight, so it is no longer a fixed target.)"""
    from stages.simulate import driver

    # the guard's limit at 5 x, not 10 x: how far above 10 x the singular collapse goes depends on the start's
    # packing along the cone's wall (a few particles in the apex), and either run crossed it or not
    monkeypatch.setattr(driver, "SPEED_LIMIT", 5.0)
    got, errors = [], []
    for scale, up in ((1.0, "Z"), (100.0, "Y")):
        r, stats = _cone_run(tmp_path / f"{scale:g}{up}", scale, up)
        assert r.exit_code == 0, r.output
        said = " ".join(r.output.split())
        assert "while the fluid's energy did not rise: pressure focusing it, not a blow-up" in said, r.output
        focused = stats["focused"]
        assert focused["peak_over_bound"] > 5.0 and focused["steps"] >= 1 and 0.1 < focused["t"] < 0.16, focused
        got.append(focused)
        errors.append(np.array([stats["density_error_mean"], stats["density_error_max"]])[:, :7])  # frames to 0.14 s
    m, cm = got
    assert np.allclose(errors[0], errors[1], rtol=0.02, atol=0.0), errors
    assert abs(m["t"] - cm["t"]) < 1e-3, got
    # a longer shot continues from the cached run (Stage.extends) and reports the whole shot's focusing: the
    # guard's count was the continuation's own, so the two frames after the collapse reported none
    r, stats = _cone_run(tmp_path / "1Z", 1.0, "Z", "--set", "scene.frames.count=11")
    assert r.exit_code == 0 and "resumed from the checkpoint at frame 8" in " ".join(r.output.split()), r.output
    assert len(stats["density_error_mean"]) == 11 and stats["focused"]["steps"] >= m["steps"], stats.get("focused")
    assert stats["focused"]["peak_over_bound"] >= m["peak_over_bound"] and stats["focused"]["t"] >= m["t"], stats
