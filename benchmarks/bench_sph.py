"""WCSPH step benchmark (issue 4), walls + viscosity on, 2 threads:

    .venv/bin/python benchmarks/bench_sph.py [--quick] [--sizes 20000,100000,1000000] [--scenes dam_break,dragon]
                                             [--steps 20] [--no-reference] [--no-peers]

Scenes: (a) the PEERS.md dam break, a 1 m cube of water in a 3 x 2 x 1.2 m tank; (b) the dragon tank of
configs/dragon.yaml (1.4 x 0.8 x 0.9 m, the dragon standing in it) filled with water to 0.5 m, the
dragon submerged. The particle spacing is set from the target count.

The walls' SDF has the node spacing the sdf_bake stage uses (0.5 l0), as in a pipeline run.

Each (scene, size) runs in a fresh subprocess so that its memory figures are its own: peak traced
(numpy) memory from the solver's construction through the timed steps, and the peak RSS growth over
the process after imports and kernel compilation, both per particle. Timed, as SPlisHSPlasH is timed
(PEERS.md: the median step of its first 60 after 10): the median ms per step over steps 10-70 from
rest, particle-steps/s, the stable dt and wall seconds per simulated second at that dt; and, up to
100k, the same over 60 steps from t = 0.3 s, when the surge runs along the floor (disordered
particles, more of them at walls, the neighbour list rebuilt every few steps: the dear part of a run).

Side by side in the same process (20k and 100k unless --no-reference): the step as it was before the
speed work (benchmarks/sph_reference.py, the frozen kernels: 27 cells of size h scanned in the density
and in the force pass) against the current one, timed in alternating rounds so machine load hits both
alike; ``speedup`` is their ratio. When pysplishsplash imports (optional extra "peers"), its WCSPH
(volume maps) runs the same dam break in a subprocess of the same run and the ratios are printed;
otherwise that is reported as skipped. Writes benchmarks/results/sph.json.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from stages.common.sdf import SDFGrid, box_interior_sdf, grid_from_function  # noqa: E402
from stages.simulate.emitters import drop_inside_walls, lattice  # noqa: E402
from stages.simulate.kernels import poly6_coef, spiky_grad_coef  # noqa: E402
from stages.simulate.neighbours import CellGrid, reorder  # noqa: E402
from stages.simulate.sph import SPHParams, SPHSolver  # noqa: E402

G = 9.81
RHO0 = 1000.0
MU = 0.01
REF_SIZES = (20000, 100000)
SDF_CELL = 0.5  # SDF node spacing in l0, the sdf_bake stage's default
SURGE_T = 0.3  # s: the second timed window starts here (dam break only, up to SURGE_MAX particles)
SURGE_MAX = 200000
PEERS = Path(__file__).resolve().parents[2] / "shared" / "peers"  # ../shared beside the clone, as CI has it
GL_PRELOAD = "/lib/x86_64-linux-gnu/libGLdispatch.so.0"


# -- scenes ---------------------------------------------------------------------------------------
def dam_break(n_target: int):
    """PEERS.md: 1 m cube in a 3 x 2 x 1.2 m tank (z up). Returns x, sdf, l0, fluid height."""
    l0 = 1.0 / round(n_target ** (1 / 3))
    lo, hi = np.array([-1.5, -1.0, 0.0]), np.array([1.5, 1.0, 1.2])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, SDF_CELL * l0)
    x = lattice([-1.5, -1.0, 0.0], [-0.5, 0.0, 1.0], l0)
    return x, sdf, l0, 1.0


DRAGON_WATER = 0.5  # m of water in the dragon tank (the dragon is 0.45 m tall)


def dragon_sdf() -> SDFGrid:
    """The baked SDF of configs/dragon.yaml's walls (tank + dragon), through the pipeline (cached in
    benchmarks/.cache, so only the first run bakes)."""
    import pipeline
    report = pipeline.run(ROOT / "configs" / "dragon.yaml", overrides=("outputs=[sdf]",),
                          cache_dir=ROOT / "benchmarks" / ".cache", out_dir=ROOT / "out" / "bench_sph_dragon",
                          progress=False)
    return SDFGrid.load(Path(report.outputs["sdf"]))


def dragon_tank(n_target: int):
    """The dragon tank filled to DRAGON_WATER; spacing from the target count of fluid particles."""
    sdf = dragon_sdf()
    lo = np.array([-0.7, -0.4, 0.0])
    hi = np.array([0.7, 0.4, DRAGON_WATER])
    l0 = (np.prod(hi - lo) / n_target) ** (1 / 3)
    x = lattice(lo, hi, l0)
    x, _, _ = drop_inside_walls(x, np.zeros_like(x), sdf, l0, _QuietLog())
    l0 *= (len(x) / n_target) ** (1 / 3)  # the dragon displaces some water
    x = lattice(lo, hi, l0)
    x, _, _ = drop_inside_walls(x, np.zeros_like(x), sdf, l0, _QuietLog())
    return x, sdf, l0, DRAGON_WATER


class _QuietLog:
    def warning(self, *a, **k):
        pass

    info = warning


SCENES = {"dam_break": dam_break, "dragon": dragon_tank}


# -- the step before the speed work, for the side-by-side timing ---------------------------------
class ReferenceSolver(SPHSolver):
    """SPHSolver stepping with the frozen pre-speed-work kernels (sph_reference.py): cells of size h,
    27 cells scanned in the density pass and again in the force pass."""

    def __init__(self, *a, **k):
        import stages.simulate.sph as S
        from stages.simulate.walls.maps import WallMaps
        bricks, S.BrickWallMaps = S.BrickWallMaps, WallMaps  # the dense map, as before
        try:
            super().__init__(*a, **k)
        finally:
            S.BrickWallMaps = bricks
        self.grid = CellGrid(self.sdf.origin, self.sdf.upper, self.h)
        self.nbr = np.zeros((0, 0), np.int32)  # the reference keeps no neighbour list
        self.cnt = np.zeros(0, np.int32)

    def _alloc(self) -> None:
        super()._alloc()
        self.nbr = np.zeros((0, 0), np.int32)

    def sort_and_density(self, rebuild: bool = False) -> None:
        import sph_reference as R
        order = self.grid.sort(self.x)
        self.x, self.v, self.id = reorder([self.x, self.v, self.id], order, self._scratch)
        g = self.grid
        R.density_pressure(self.x, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, poly6_coef(self.h), self.mass,
                           self.rho0, self.walls.maps, self.walls.origin, 1.0 / self.walls.spacing,
                           self.walls.fix_rho, self.inv_dr, self.sdf.dist, self.sdf.origin, self.sdf_inv,
                           self.eos, self.stiffness, self.p.clamp_pressure, self.rho, self.pr, self.d, self.nrm)

    def forces(self) -> None:
        import sph_reference as R
        g = self.grid
        grad_coef = spiky_grad_coef(self.h) / self.grad_norm
        pressure = (self.pr, grad_coef, self.fix_press, self.p.artificial_viscosity * self.c * self.h)
        R.forces(self.x, self.v, self.rho, self.d, self.nrm, g.starts, g.lo, 1.0 / g.cell, g.dims, self.h, self.mass,
                 self.rho0, self.walls.maps, self.walls.origin, 1.0 / self.walls.spacing, self.inv_dr, self.gravity,
                 self.acc, pressure, *self.effect_args())


def make_solver(cls, x, sdf, l0, height):
    return cls(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=RHO0, params=SPHParams(),
               gravity=(0, 0, -G), mu=MU, v_ref=math.sqrt(2 * G * height))


def _status_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def rss_now() -> int:
    """Current RSS, bytes; and resets the peak (VmHWM) so that ``rss_peak`` is measured from here."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    return _status_kb("VmRSS") * 1024


def rss_peak() -> int:
    kb = _status_kb("VmHWM")
    return kb * 1024 if kb else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


# -- one (scene, size), run in its own process ----------------------------------------------------
def measure_one(scene: str, n_target: int, steps: int, warmup: int, reference: bool) -> dict:
    # compile every kernel on a tiny case first, so the RSS growth below is the case's own
    x, sdf, l0, height = dam_break(2000)
    make_solver(SPHSolver, x, sdf, l0, height).step(10.0)
    if reference:
        make_solver(ReferenceSolver, x, sdf, l0, height).step(10.0)
    x, sdf, l0, height = SCENES[scene](n_target)
    rss0 = rss_now()
    tracemalloc.start()
    t0 = time.perf_counter()
    s = make_solver(SPHSolver, x, sdf, l0, height)
    setup_s = time.perf_counter() - t0
    for _ in range(warmup):
        s.step(10.0)
    wall, dt, builds = timed_steps(s, steps)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss_top = rss_peak()
    n = len(s.x)
    out = {"scene": scene, "particles": n, "spacing": l0, "threads": _threads(), "steps": steps,
           "ms_per_step": wall * 1e3, "particle_steps_per_s": n / wall, "dt": dt, "wall_s_per_sim_s": wall / dt,
           "neighbour_builds_per_step": builds,
           "traced_bytes_per_particle": peak / n, "rss_growth_bytes_per_particle": (rss_top - rss0) / n,
           "wall_map_bytes_per_particle": s.walls.nbytes / n, "sdf_bytes_per_particle": sdf.dist.nbytes / n,
           "neighbour_slots": int(s.nbr.shape[1]),
           "density_error_mean": float(np.maximum(s.rho / RHO0 - 1, 0).mean()), "sound_speed": s.c,
           "solver_setup_s": setup_s}
    out["cpu_ms_per_step_1thread"] = one_thread_cpu_ms(s, max(2, min(steps, 8)))
    if reference:
        out.update(side_by_side(s, x, sdf, l0, height, min(steps, 20)))
    if scene == "dam_break" and n <= SURGE_MAX:
        s.advance_to(SURGE_T)
        wall, dt, builds = timed_steps(s, steps)
        out.update({"surge_t": SURGE_T, "surge_ms_per_step": wall * 1e3, "surge_particle_steps_per_s": n / wall,
                    "surge_dt": dt, "surge_wall_s_per_sim_s": wall / dt, "surge_neighbour_builds_per_step": builds,
                    "surge_cpu_ms_per_step_1thread": one_thread_cpu_ms(s, max(2, min(steps, 8)))})
    return out


def timed_steps(s: SPHSolver, steps: int) -> tuple[float, float, float]:
    """(median wall seconds per step, median dt, neighbour-list builds per step) over ``steps`` steps."""
    times, dts = [], []
    built = [0]
    build = s.build_neighbours

    def counted():
        built[0] += 1
        build()
    s.build_neighbours = counted
    try:
        for _ in range(steps):
            t0 = time.perf_counter()
            dts.append(s.step(10.0))
            times.append(time.perf_counter() - t0)
    finally:
        del s.build_neighbours
    return float(np.median(times)), float(np.median(dts)), built[0] / steps


def one_thread_cpu_ms(solver, steps: int) -> float:
    """CPU milliseconds per step on one thread (process time): unlike wall time on 2 threads, this
    barely moves when other jobs share the machine (a descheduled thread stalls every parallel loop)."""
    import numba
    nt = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        solver.step(10.0)
        t0 = time.process_time()
        for _ in range(steps):
            solver.step(10.0)
        return 1e3 * (time.process_time() - t0) / steps
    finally:
        numba.set_num_threads(nt)


def side_by_side(new: SPHSolver, x, sdf, l0, height, steps: int) -> dict:
    """The old and the new step from the same state, in alternating rounds (noisy machine)."""
    tracemalloc.start()
    ref = make_solver(ReferenceSolver, x, sdf, l0, height)  # with the dense wall map of walls/maps.py
    ref.load_state({k: np.copy(v) for k, v in new.state().items()})  # own arrays: the sort reuses buffers
    ref.step(10.0)
    _, ref_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    new.step(10.0)
    t_new, t_ref = [], []
    rounds = 4
    per = max(steps // rounds, 2)
    for _ in range(rounds):
        for solver, times in ((ref, t_ref), (new, t_new)):
            t0 = time.perf_counter()
            for _ in range(per):
                solver.step(10.0)
            times.append((time.perf_counter() - t0) / per)
    ms_new, ms_ref = 1e3 * min(t_new), 1e3 * min(t_ref)
    cpu_new, cpu_ref = [], []
    for _ in range(3):  # and on one thread, in CPU time (robust to machine load)
        cpu_ref.append(one_thread_cpu_ms(ref, per))
        cpu_new.append(one_thread_cpu_ms(new, per))
    return {"side_by_side_ms_per_step_reference": ms_ref, "side_by_side_ms_per_step_new": ms_new,
            "speedup": ms_ref / ms_new, "side_by_side_cpu_ms_per_step_1thread_reference": min(cpu_ref),
            "side_by_side_cpu_ms_per_step_1thread_new": min(cpu_new), "cpu_speedup_1thread": min(cpu_ref) / min(cpu_new),
            "reference_traced_bytes_per_particle": ref_peak / len(x),
            # same physics, other arithmetic and pair order: how far apart the two runs drifted
            "max_position_difference_l0_after_rounds": _drift(ref, new) / l0}


def _drift(a: SPHSolver, b: SPHSolver) -> float:
    """Largest distance between the same particle (by id) in two solvers."""
    xa = np.empty_like(a.x)
    xb = np.empty_like(b.x)
    xa[a.id] = a.x
    xb[b.id] = b.x
    return float(np.linalg.norm(xa - xb, axis=1).max())


def _threads() -> int:
    import numba
    return numba.get_num_threads()


# -- SPlisHSPlasH (optional) ----------------------------------------------------------------------
def peers_available() -> bool:
    env = {**os.environ, "LD_PRELOAD": GL_PRELOAD}
    r = subprocess.run([sys.executable, "-c", "import pysplishsplash"], env=env, capture_output=True)
    return r.returncode == 0 and (PEERS / "bench_sph.py").exists()


def run_peers(n_target: int, steps: int) -> dict:
    """SPlisHSPlasH WCSPH with volume maps on the same dam break (PEERS.md settings: particle radius
    l0 / 2, fixed dt from PEERS.md's table, 2 OpenMP threads); its per-step median."""
    import tempfile
    radius = {20000: 0.0178, 100000: 0.0106}.get(n_target, 0.5 / round(n_target ** (1 / 3)))
    dt = {20000: 0.0005, 100000: 0.00025}.get(n_target, 0.00025)
    sys.path.insert(0, str(PEERS))
    from make_scene import scene  # noqa: E402  (../shared/peers)
    with tempfile.TemporaryDirectory() as tmp:
        # the scene references ../box.obj relative to itself
        scenes = Path(tmp) / "scenes"
        scenes.mkdir()
        (Path(tmp) / "box.obj").write_bytes((PEERS / "box.obj").read_bytes())
        f = scenes / f"dam_{n_target}.json"
        f.write_text(json.dumps(scene(radius, 0, 2, dt=dt)))
        env = {**os.environ, "LD_PRELOAD": GL_PRELOAD, "OMP_NUM_THREADS": "2"}
        r = subprocess.run([sys.executable, str(PEERS / "bench_sph.py"), str(f), str(steps)], env=env,
                           capture_output=True, text=True, timeout=1200)
    for line in r.stdout.splitlines():
        if line.startswith("RESULT "):
            res = json.loads(line[7:])
            return {"particles": res["n_fluid"], "dt": res["dt"], "ms_per_step": res["step_median_ms"],
                    "wall_s_per_sim_s": res["step_median_ms"] / 1e3 / res["dt"], "setup_s": res["setup_s"]}
    return {"failed": (r.stderr or r.stdout)[-400:]}


# -- driver ---------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="20000,100000,1000000")
    ap.add_argument("--scenes", default="dam_break,dragon")
    ap.add_argument("--steps", type=int, default=60, help="timed steps per window (1M: at most 4)")
    ap.add_argument("--quick", action="store_true", help="20k only, no SPlisHSPlasH")
    ap.add_argument("--no-reference", dest="reference", action="store_false")
    ap.add_argument("--no-peers", dest="peers", action="store_false")
    ap.add_argument("--one", nargs=2, metavar=("SCENE", "N"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        scene, n = a.one[0], int(a.one[1])
        steps = a.steps if n < 500000 else min(a.steps, 4)
        print("RESULT " + json.dumps(measure_one(scene, n, steps, warmup=10 if n < 500000 else 1,
                                                 reference=a.reference)), flush=True)
        return
    sizes = [20000] if a.quick else [int(s) for s in a.sizes.split(",")]
    steps = a.steps
    rows = []
    for scene in a.scenes.split(","):
        for n in sizes:
            cmd = [sys.executable, __file__, "--one", scene, str(n), "--steps", str(steps)]
            if not (a.reference and n in REF_SIZES):
                cmd.append("--no-reference")
            r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            res = next((json.loads(ln[7:]) for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
            if res is None:
                print(f"{scene} {n}: failed\n{r.stderr[-2000:]}", file=sys.stderr)
                continue
            rows.append(res)
            print(json.dumps(res), flush=True)
    peers: dict = {"skipped": "pysplishsplash does not import (optional extra 'peers')"}
    if a.quick or not a.peers:
        peers = {"skipped": "--quick / --no-peers"}
    elif peers_available():
        peers = {}
        for n in (n for n in sizes if n in REF_SIZES):
            p = run_peers(n, 60)
            ours = next((r for r in rows if r["scene"] == "dam_break" and r["particles"] and
                         abs(r["particles"] - p.get("particles", -1)) < 0.05 * r["particles"]), None)
            if ours and "ms_per_step" in p:
                p["ratio_ms_per_step_theirs_over_ours"] = p["ms_per_step"] / ours["ms_per_step"]
                p["ratio_wall_s_per_sim_s_theirs_over_ours"] = p["wall_s_per_sim_s"] / ours["wall_s_per_sim_s"]
            peers[str(n)] = p
    print("SPlisHSPlasH WCSPH:", json.dumps(peers))
    nan = float("nan")
    print(f"\n{'scene':10} {'particles':>9} {'ms/step':>8} {'Mpart-steps/s':>13} {'surge ms':>8} {'B/particle':>10} "
          f"{'wall s/sim s':>12} {'ref ms':>7} {'speedup':>7} {'1-thread CPU ms: ref':>20} {'new':>7} {'speedup':>7}")
    for r in rows:
        print(f"{r['scene']:10} {r['particles']:9d} {r['ms_per_step']:8.1f} {r['particle_steps_per_s'] / 1e6:13.2f} "
              f"{r.get('surge_ms_per_step', nan):8.1f} {r['traced_bytes_per_particle']:10.0f} {r['wall_s_per_sim_s']:12.1f} "
              f"{r.get('side_by_side_ms_per_step_reference', nan):7.1f} {r.get('speedup', nan):7.2f} "
              f"{r.get('side_by_side_cpu_ms_per_step_1thread_reference', nan):20.1f} "
              f"{r['cpu_ms_per_step_1thread']:7.1f} {r.get('cpu_speedup_1thread', nan):7.2f}")
    if not a.quick:
        out = ROOT / "benchmarks" / "results" / "sph.json"
        out.write_text(json.dumps({"command": " ".join(["benchmarks/bench_sph.py"] + sys.argv[1:]),
                                   "cpus": os.cpu_count(), "runs": rows, "splishsplash_wcsph": peers}, indent=2))


if __name__ == "__main__":
    main()
