"""The stability suite at CI size (stability_cases.py; `make stability` runs the long version and
prints the table). Every case runs through each solver as a pipeline run would start it (hydrostatic
start, the blow-up guard) and must end without a blow-up, a particle inside a wall or through the
thin plate, an escape, a particle faster than twice the ballistic bound sqrt(2 g H) + emitter speed
(Ritter's dam-break front runs at 2 sqrt(g H), 1.41 x sqrt(2 g H)) at a sample or 3 x within any step
(not in the cone, where no speed bound holds: FOCUSING), or energy created (kinetic + potential at the end at most
5 % above the start; in the cone below it). The case asking for a
time step far above the stable one must end in the guard's error for WCSPH (explicit); the implicit
solvers may survive it but then obey the same checks."""
from __future__ import annotations

import numba as nb
import pytest

from stability_cases import CASES, RESTING, SOLVERS, rest_summary, run_case


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # hundreds of particles: one thread is faster than two that synchronise every pass
    before = nb.get_num_threads()
    nb.set_num_threads(1)
    yield
    nb.set_num_threads(before)


# Open defects the suite found (issue 17), kept visible: strict, so a fix turns them into errors to remove.
KNOWN = {
    ("rest", "sph_poly6"): "decaying but above the floor: 0.0087 m/s over 2.5-3 s against 0.0071 (0.017 m/s at 1.5 s "
                           "in bench_rest's tank; the spline default is at the goal)",
    ("rest", "dfsph"): "not at rest with water's viscosity: 0.20 m/s over 2.5-3 s, the surface churning a spacing "
                       "up and down (dfsph.py: the constant-density solve keeps the work of removing each step's "
                       "compression as kinetic energy)",
    ("rest", "mps"): "decaying but above the floor: 0.024 m/s over 2.5-3 s (particle-scale motion that grows from "
                     "0.004 m/s after 0.2 s: mps.py)",
    # the same in the curved tanks (session 40, their wall band re-packed; WCSPH's default is at rest there: 0.0017 and
    # 0.0020 m/s in session 41; Poly6/Spiky near the floor: NEAR_THE_FLOOR)
    ("rest_cylinder", "dfsph"): "not at rest with water's viscosity: 0.18 m/s over 2.5-3 s (as in the box tank)",
    ("rest_cylinder", "mps"): "decaying but above the floor: 0.017 m/s over 2.5-3 s (as in the box tank)",
    ("rest_bowl", "dfsph"): "not at rest with water's viscosity: 0.18 m/s over 2.5-3 s (as in the box tank)",
    ("rest_bowl", "mps"): "decaying but above the floor: 0.019 m/s over 2.5-3 s (as in the box tank)",
}


# Cases where pressure focuses the fluid's energy without bound in the continuum: the void closing over a cone's
# apex throws particles into it at 2-3.2 x the ballistic bound at 2 cm (WCSPH, DFSPH), 6-14 x at 0.7-1 cm
# (test_blowup.py). No speed bound holds there; what must hold is that the fluid makes no energy.
FOCUSING = {"cone_40deg"}


# Issue 17's goal not met reliably: Poly6/Spiky in the curved tanks ends on either side of the floor as round-off in
# the start changes (over 2.5-3 s, m/s, against 0.0071: cylinder 0.0079 / 0.0103 / 0.0067, bowl 0.0070 / 0.0094 /
# 0.0061 with three starts that differ by at most 1e-4 m, sessions 40-41). Judged at rest against this multiple of
# the floor instead: an assertion that holds on either side (a non-strict xfail asserted nothing)
NEAR_THE_FLOOR = {("rest_cylinder", "sph_poly6"): 2.0, ("rest_bowl", "sph_poly6"): 2.0}


def _cases():
    for case in CASES:
        for solver in SOLVERS:
            why = KNOWN.get((case, solver))
            yield pytest.param(case, solver, id=f"{case}-{solver}",
                               marks=[pytest.mark.xfail(strict=True, reason=f"issue 17: {why}")] if why else [])


@pytest.mark.parametrize("case, solver", list(_cases()))
def test_case_stays_stable(case, solver):
    r = run_case(case, solver)
    print(r.row())
    if case == "huge_time_step" and solver in ("sph", "sph_poly6"):
        assert r.blowup is not None and "likely cause: the time step" in r.blowup, r.blowup
        return
    if case == "huge_time_step" and r.blowup is not None:
        assert "likely cause" in r.blowup
        return
    assert r.blowup is None, r.blowup
    assert r.inside_walls == 0
    assert r.escaped == 0
    assert r.through_plate == 0
    if case in FOCUSING:
        assert r.energy_ratio < 1.0, r.energy_ratio
        return
    assert r.speed_ratio < 2.0, r.speed_ratio
    # between the samples too: a single step's spike (the MPS wedge's reached 9.5 x before session 37); WCSPH's wedge
    # reaches 2.1 x within a step here (2.4 x in the long suite), its particles on the V's apex line
    assert r.peak_ratio < 3.0, r.peak_ratio
    assert r.energy_ratio < 1.05, r.energy_ratio
    if case in RESTING:
        assert_at_rest(r, NEAR_THE_FLOOR.get((case, solver), 1.0))


def assert_at_rest(r, slack: float = 1.0) -> None:
    """Issue 17's resting tank, from the pipeline's start (hydrostatic, water's viscosity, no settling): the mean
    speed averaged over the run's last sixth (2.5-3 s) below the goal's floor, Froude-scaled to the spacing
    (stability_cases.rest_floor: 0.0071 m/s at 2.5 cm), and below its average over 1-1.5 s (decaying); the
    free surface still over the run's second half (no creep or leak: within 0.1 l0) and within half a spacing
    of where it started (the top layer settles by about a third of a spacing into its resting packing in the
    first second: 0.31 l0 for WCSPH at 1 s, 0.345 at 3 s). The curved tanks too since session 40: the emitted
    lattice left up to half a spacing of water out along their walls, and their surface settled 0.7-1.7 spacings
    at 2.5 cm, until emitters._fill_wall_band put it back. ``slack``: the floor's multiple allowed (NEAR_THE_FLOOR)."""
    f = rest_summary(r)
    assert f["late"] < slack * f["floor"] and f["late"] < f["early"], (f, r.speeds)
    assert f["drift_second_half"] < 0.1, (f, r.surfaces)
    assert abs(f["drift"]) < 0.5, (f, r.surfaces)


@pytest.mark.parametrize("angle", [10.0, 20.0, 30.0])
@pytest.mark.parametrize("apex_x", [0.15, 0.1525, 0.155])  # on an SDF node plane, between, a quarter cell off
@pytest.mark.parametrize("solver", ["sph", "dfsph"])
def test_no_particle_ends_inside_an_acute_v(solver, apex_x, angle, monkeypatch):
    """Water poured into V troughs of 10-30 degrees, the apex on and off the SDF's nodes: in the apex
    both sides are within r_rep and the push-out must satisfy both (walls.maps.push_move); before it,
    DFSPH (r_rep 0.2 l0) left particles inside the 20 degree V."""
    import stability_cases as S
    monkeypatch.setitem(S.CASES, "wedge_20deg", lambda: S.wedge(angle_deg=angle, apex_x=apex_x))
    r = run_case("wedge_20deg", solver)
    assert r.blowup is None, r.blowup
    assert r.inside_walls == 0
    assert r.speed_ratio < 2.0 and r.energy_ratio < 1.05, (r.speed_ratio, r.energy_ratio)


@pytest.mark.parametrize("angle", [10.0, 20.0, 30.0])
def test_mps_in_a_v_stays_below_twice_the_bound_at_every_step(angle, monkeypatch):
    """MPS in V troughs with the apex on an SDF node plane (the scene mirror-symmetric to rounding), at three
    frame samplings (each frame's end shortens a step, so each is another run): the fastest particle over every
    step below 2 x the ballistic bound. The projection put mirror-image particles of the apex on one point, and
    before mps_kernels.part_stacked parted them such runs reached 2.7-9.5 x within a step (3.5 x in this set)."""
    import stability_cases as S
    monkeypatch.setitem(S.CASES, "wedge_20deg", lambda: S.wedge(angle_deg=angle, apex_x=0.15))
    peaks = []
    for samples in (7, 10, 13):
        monkeypatch.setattr(S, "SAMPLES", samples)
        r = run_case("wedge_20deg", "mps")
        assert r.blowup is None and r.inside_walls == 0, r.blowup
        peaks.append(r.peak_ratio)
    assert max(peaks) < 2.0, peaks


@pytest.mark.parametrize("solver", ["sph", "dfsph", "mps"])  # mps: its compressibility term Froude-scaled (mps.py)
def test_kilometre_dam_break_is_the_metre_one_scaled(solver):
    """The dam break 10,000 x larger at the same Froude time (lengths x 1e4, times x 100): the surge
    front, as a fraction of the tank, and the energy left within a few percent of the metre-sized run
    (water's viscosity is negligible at both sizes; the millimetre case is not compared because at
    2 mm it is not: Reynolds number about 300)."""
    m = run_case("dam_break", solver)
    km = run_case("kilometres", solver)
    print(m.row(), m.front, km.row(), km.front)
    assert m.blowup is None and km.blowup is None
    assert abs(km.front - m.front) < 0.05, (m.front, km.front)  # one spacing is 0.05 of the tank
    assert abs(km.energy_ratio - m.energy_ratio) < 0.05, (m.energy_ratio, km.energy_ratio)


def test_dfsph_survives_a_step_far_below_the_stable_one(monkeypatch):
    """The metre dam break with dt_max 0.05 ms (the kilometre scene's former 5 ms cap, Froude-scaled)
    against the same with 0.5 ms: the same flow after 0.04 s. Before the constant-density solve removed
    the density error over the natural step (DFSPHSolver.step's beta), the short step turned the start
    lattice's 0.7 % error at the walls into 9 m/s in its first step."""
    import stability_cases as S
    runs = {}
    for dt_max in (5e-5, 5e-4):
        def short_steps(dt_max=dt_max):
            scene = S.dam_break()
            scene.params = {"dfsph": {"dt_max": dt_max}}
            return scene

        monkeypatch.setitem(S.CASES, "dam_break", short_steps)
        monkeypatch.setitem(S.SHORT, "dam_break", 0.04)
        runs[dt_max] = r = S.run_case("dam_break", "dfsph")
        assert r.blowup is None, r.blowup
    fine, coarse = runs[5e-5], runs[5e-4]
    assert fine.steps >= 800 and coarse.steps <= 100
    assert abs(fine.energy_ratio - coarse.energy_ratio) < 0.01, (fine.energy_ratio, coarse.energy_ratio)
    assert abs(fine.mean_speed_end / coarse.mean_speed_end - 1.0) < 0.05, (fine.speeds, coarse.speeds)
    assert abs(fine.speed_ratio / coarse.speed_ratio - 1.0) < 0.1, (fine.speed_ratio, coarse.speed_ratio)


@pytest.mark.parametrize("case, setting", [("jet_10ms", {"cfl": 0.2}), ("jet_10ms", {"dt_max": 2e-4}),
                                           ("dam_break", {"cfl": 0.1})])
def test_dfsph_at_steps_shorter_than_its_own_makes_no_energy(case, setting, monkeypatch):
    """The solves' tolerances bound dt x the error's rate, so at steps much shorter than the defaults' a warm-started
    pressure passed as converged and was applied whole every step: the 10 m/s jet blew up at cfl 0.2 (114 m/s) and
    its energy rose to 2.94 x the start's at dt_max 0.2 ms; the dam break blew up at cfl 0.1. The warm start is now
    scaled by cfl / 0.8 and dt_max / its default: the flow ends as at the default step (energy within 0.1 of it)."""
    import stability_cases as S
    default = S.run_case(case, "dfsph")
    base = S.CASES[case]

    def shorter():
        scene = base()
        scene.params = {**scene.params, "dfsph": {**scene.params.get("dfsph", {}), **setting}}
        return scene

    monkeypatch.setitem(S.CASES, case, shorter)
    short = S.run_case(case, "dfsph")
    assert default.blowup is None and short.blowup is None, short.blowup
    assert short.steps > 2 * default.steps
    assert short.energy_ratio < default.energy_ratio + 0.1, (short.energy_ratio, default.energy_ratio)
    assert short.peak_ratio < 2.0, short.peak_ratio
