"""DFSPH against our WCSPH and SPlisHSPlasH's DFSPH on the PEERS.md 20k dam break, in one run.

    python benchmarks/bench_dfsph.py [--sim-time 0.5] [--peer-steps 300] [--no-sph]

Scene: 1 m cube of water (19,683 particles, l0 = 1/27 m) in a 3 x 2 x 1.2 m tank, gravity, viscosity
mu = 0.01 Pa s, walls from the distance function only. For each of our solvers: wall seconds per
simulated second over ``--sim-time`` (the first step, which includes numba's cache load, excluded),
ms per step, steps, mean solver iterations (DFSPH), mean and max density error (mean over particles
of max(rho / rho0 - 1, 0), sampled every 1/30 s), peak traced memory per particle (solver set-up with
its wall maps and the run; the SDF grid, an input artifact, and numba's loading of the compiled
kernels, done by a tiny warm-up solver first, excluded). SPlisHSPlasH
(pip package pysplishsplash, the optional extra "peers") runs its DFSPH scene of ../shared/peers
(volume maps, fixed dt 0.001 s) in a subprocess with the settings of PEERS.md, when it is installed;
its wall seconds per simulated second are ms/step / dt over ``--peer-steps`` steps (set-up excluded).
Writes benchmarks/results/dfsph.json."""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
from stages.simulate.emitters import lattice
from stages.simulate.mps import MPSParams, MPSSolver
from stages.simulate.sph import SPHParams, SPHSolver

PEERS = Path(__file__).resolve().parents[2] / "shared" / "peers"
PEER_SCENE = PEERS / "scenes" / "dambreak_20k_dfsph_vm.json"
G, MU = 9.81, 0.01


L0 = 1.0 / 27


def make_sdf():
    lo, hi = np.array([-1.5, -1.0, 0.0]), np.array([1.5, 1.0, 1.2])
    return grid_from_function(box_interior_sdf(lo, hi), lo, hi, L0 / 2)


def solver(kind: str, x, sdf, v_ref: float):
    """Our solver ``kind`` (sph, dfsph, mps; default parameters) on particles x, at rest."""
    kw = dict(spacing=L0, rho0=1000.0, gravity=(0, 0, -G), mu=MU)
    ids = np.arange(len(x))
    if kind == "dfsph":
        return DFSPHSolver(x, np.zeros_like(x), ids, sdf, params=DFSPHParams(), **kw)
    if kind == "mps":
        return MPSSolver(x, np.zeros_like(x), ids, sdf, params=MPSParams(), v_ref=v_ref, **kw)
    return SPHSolver(x, np.zeros_like(x), ids, sdf, params=SPHParams(), v_ref=v_ref, **kw)


def make_solver(kind: str, sdf=None):
    sdf = make_sdf() if sdf is None else sdf
    return solver(kind, lattice([-1.5, -1.0, 0.0], [-0.5, 0.0, 1.0], L0), sdf, math.sqrt(2 * G * 1.0))


def warm_up(kind: str) -> None:
    """One step of a tiny solver of the same kind: numba loads its compiled kernels (tens of MB of
    Python objects) before the memory is traced, so the peak is the solver's own."""
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.3, 0.3])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, L0 / 2)
    s = solver(kind, lattice([0.0, 0.0, 0.0], [0.15, 0.15, 0.15], L0), sdf, 1.0)
    s.step(1.0 / 30)
    s.frame()


def run_ours(kind: str, sim_time: float, trace_memory: bool = True) -> dict:
    """``trace_memory`` False: no tracemalloc (it slows the Python side of a step), no bytes_per_particle."""
    sdf = make_sdf()  # the sdf_bake stage's artifact: not counted in the solver's memory
    warm_up(kind)
    if trace_memory:
        tracemalloc.start()
    s = make_solver(kind, sdf)
    s.step(1.0 / 30)  # first step: numba cache load / compile, excluded
    t_start, steps0 = s.t, s.steps
    if kind == "dfsph":
        it0 = list(s.iterations)
    err = []
    wall = cpu = 0.0  # cpu: the process's CPU seconds (all threads), steadier than wall time on a busy machine
    frames = max(1, round(sim_time * 30))
    for f in range(1, frames + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        s.advance_to(t_start + f / 30)
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        rho = s.rho if kind == "dfsph" else s.frame().rho  # dfsph's density is current after a step
        err.append(float(np.maximum(rho / 1000.0 - 1.0, 0.0).mean()))
    peak = 0.0
    if trace_memory:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    steps = s.steps - steps0
    simulated = s.t - t_start
    out = {"solver": kind, "particles": len(s.x), "simulated_s": simulated, "steps": steps,
           "wall_s": wall, "wall_s_per_simulated_s": wall / simulated, "ms_per_step": 1e3 * wall / steps,
           "cpu_s_per_simulated_s": cpu / simulated, "cpu_ms_per_step": 1e3 * cpu / steps,
           "mean_dt": simulated / steps, "density_error_mean": float(np.mean(err)),
           "density_error_max": float(np.max(err)), "bytes_per_particle": peak / len(s.x) if trace_memory else None,
           "left_domain": s.left_domain}
    if kind == "dfsph":
        out["mean_density_iterations"] = (s.iterations[0] - it0[0]) / steps
        out["mean_divergence_iterations"] = (s.iterations[1] - it0[1]) / steps
    return out


def run_peer(steps: int) -> dict:
    """SPlisHSPlasH's DFSPH via ../shared/peers/bench_sph.py in a subprocess (PEERS.md: LD_PRELOAD)."""
    env = dict(os.environ, OMP_NUM_THREADS="2", LD_PRELOAD="/lib/x86_64-linux-gnu/libGLdispatch.so.0")
    try:
        import importlib.util
        if importlib.util.find_spec("pysplishsplash") is None:
            return {"skipped": "pysplishsplash is not installed (optional extra 'peers')"}
        if not PEER_SCENE.is_file():
            return {"skipped": f"{PEER_SCENE} not found"}
        r = subprocess.run([sys.executable, str(PEERS / "bench_sph.py"), str(PEER_SCENE), str(steps)], env=env,
                           capture_output=True, text=True, timeout=1800)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {"skipped": f"SPlisHSPlasH did not run: {exc}"}
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if line is None:
        return {"skipped": f"SPlisHSPlasH failed (exit {r.returncode}): {r.stderr.strip()[-300:]}"}
    res = json.loads(line[len("RESULT "):])
    res["wall_s_per_simulated_s"] = res["step_mean_ms"] / 1e3 / res["dt"]
    res["solver"] = "SPlisHSPlasH DFSPH (volume maps)"
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sim-time", type=float, default=0.5, help="simulated seconds for our solvers")
    ap.add_argument("--peer-steps", type=int, default=300, help="SPlisHSPlasH steps (dt 0.001 s)")
    ap.add_argument("--no-sph", action="store_true", help="skip our WCSPH (slow: bound by the speed of sound)")
    a = ap.parse_args()
    results = {"scene": "PEERS.md 20k dam break", "command": " ".join(sys.argv),
               "note": "one run on a shared 2-core machine: compare the ratios, not the absolute times",
               "load_average_1min_start": os.getloadavg()[0]}
    results["dfsph"] = run_ours("dfsph", a.sim_time)
    print(json.dumps(results["dfsph"]), flush=True)
    if not a.no_sph:
        results["sph"] = run_ours("sph", a.sim_time)
        print(json.dumps(results["sph"]), flush=True)
    peer = run_peer(a.peer_steps)
    results["splishsplash_dfsph"] = peer
    if "skipped" in peer:
        print("SPlisHSPlasH: skipped:", peer["skipped"])
    else:
        print(json.dumps(peer))
        ratio = results["dfsph"]["wall_s_per_simulated_s"] / peer["wall_s_per_simulated_s"]
        results["dfsph_over_splishsplash"] = ratio
        print(f"wall s per simulated s: dfsph {results['dfsph']['wall_s_per_simulated_s']:.2f}, "
              f"SPlisHSPlasH DFSPH {peer['wall_s_per_simulated_s']:.2f}, ratio {ratio:.2f} (goal <= 0.5)")
    if "sph" in results:
        print(f"dfsph / our sph wall s per simulated s: "
              f"{results['dfsph']['wall_s_per_simulated_s'] / results['sph']['wall_s_per_simulated_s']:.3f}")
    results["load_average_1min_end"] = os.getloadavg()[0]
    out = Path(__file__).parent / "results" / "dfsph.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
