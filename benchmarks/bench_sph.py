"""SPH step benchmark: the PEERS.md dam break (1 m cube in a 3 x 2 x 1.2 m tank), walls + viscosity on.

    python benchmarks/bench_sph.py [--sizes 20000,100000] [--steps 30]

Reports ms/step, particle-steps/s, peak traced memory per particle, the stable dt and wall seconds per
simulated second (at that dt); writes benchmarks/results/sph.json."""
from __future__ import annotations

import argparse
import json
import time
import tracemalloc
from pathlib import Path

import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.simulate.sph import SPHParams, SPHSolver


def run(n_target: int, steps: int) -> dict:
    l0 = 1.0 / round(n_target ** (1 / 3))
    lo, hi = np.array([-1.5, -1.0, 0.0]), np.array([1.5, 1.0, 1.2])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0)
    x = lattice([-1.5, -1.0, 0.0], [-0.5, 0.0, 1.0], l0)
    tracemalloc.start()
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=SPHParams(),
                  gravity=(0, 0, -9.81), mu=0.01, v_ref=float(np.sqrt(2 * 9.81 * 1.0)))
    s.step(1.0)  # compile / warm up
    t0 = time.perf_counter()
    dts = [s.step(1.0) for _ in range(steps)]
    wall = (time.perf_counter() - t0) / steps
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    dt = float(np.mean(dts))
    err = float(np.maximum(s.rho / 1000.0 - 1, 0).mean())
    return {"particles": len(x), "ms_per_step": wall * 1e3, "particle_steps_per_s": len(x) / wall,
            "bytes_per_particle": peak / len(x), "dt": dt, "wall_s_per_sim_s": wall / dt,
            "density_error_mean": err, "sound_speed": s.c}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="20000,100000")
    ap.add_argument("--steps", type=int, default=30)
    a = ap.parse_args()
    results = [run(int(n), a.steps) for n in a.sizes.split(",")]
    for r in results:
        print(json.dumps(r))
    out = Path(__file__).parent / "results" / "sph.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
