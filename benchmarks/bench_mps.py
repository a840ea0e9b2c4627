"""MPS step benchmark beside SPH in the same run: the PEERS.md dam break (1 m cube of water in a
3 x 2 x 1.2 m tank), gravity + viscosity (mu 0.01) + walls, as benchmarks/bench_sph.py.

    .venv/bin/python benchmarks/bench_mps.py [--sizes 20000] [--steps 20] [--threads 2]

Per solver: set-up seconds (MPS: its wall maps), ms/step, particle-steps/s, the step dt, wall seconds per
simulated second, and for MPS the CG iterations per step. Both start from the same lattice and take the
same warm-up; the machine is shared, so the SPH / MPS ratio from one run is the figure to quote.
Writes benchmarks/results/mps.json."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numba as nb
import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.simulate.mps import MPSParams, MPSSolver
from stages.simulate.sph import SPHParams, SPHSolver


def scene(n_target: int):
    l0 = 1.0 / round(n_target ** (1 / 3))
    lo, hi = np.array([-1.5, -1.0, 0.0]), np.array([1.5, 1.0, 1.2])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0)
    x = lattice([-1.5, -1.0, 0.0], [-0.5, 0.0, 1.0], l0)
    return l0, sdf, x


def run(solver: str, n_target: int, steps: int, warmup: int, mps_params: dict | None = None) -> dict:
    l0, sdf, x = scene(n_target)
    kw = dict(spacing=l0, rho0=1000.0, gravity=(0, 0, -9.81), mu=0.01, v_ref=float(np.sqrt(2 * 9.81 * 1.0)))
    t0 = time.perf_counter()
    if solver == "mps":
        s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, params=MPSParams(**(mps_params or {})), **kw)
    else:
        s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, params=SPHParams(), **kw)
    setup = time.perf_counter() - t0
    for _ in range(warmup):  # compile, and let the column start to fall (the CG needs more iterations then)
        s.step(1.0)
    cg0 = getattr(s, "cg_iterations", 0)
    t0 = time.perf_counter()
    dts = [s.step(1.0) for _ in range(steps)]
    wall = (time.perf_counter() - t0) / steps
    dt = float(np.mean(dts))
    out = {"solver": solver, "particles": len(x), "setup_s": setup, "ms_per_step": wall * 1e3,
           "particle_steps_per_s": len(x) / wall, "dt": dt, "wall_s_per_sim_s": wall / dt, "threads": nb.get_num_threads()}
    if solver == "mps":
        out["cg_iterations_per_step"] = (s.cg_iterations - cg0) / steps
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="20000")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--re-laplacian", type=float, default=None, help="MPS Laplacian radius in l0 (default 3.1)")
    a = ap.parse_args()
    if a.threads:
        nb.set_num_threads(a.threads)
    results = []
    for n in a.sizes.split(","):
        for solver in ("sph", "mps"):
            mps = {"re_laplacian": a.re_laplacian} if a.re_laplacian else {}
            r = run(solver, int(n), a.steps, a.warmup, mps)
            if solver == "mps":
                r["re_laplacian"] = a.re_laplacian or MPSParams().re_laplacian
            print(json.dumps(r))
            results.append(r)
    out = Path(__file__).parent / "results" / "mps.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"command": "benchmarks/bench_mps.py " + " ".join(
        f"--{k.replace('_', '-')}={v}" for k, v in vars(a).items() if v is not None), "results": results}, indent=2))


if __name__ == "__main__":
    main()
