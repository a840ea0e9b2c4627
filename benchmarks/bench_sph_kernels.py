"""WCSPH step cost of the two pressure kernels (issue 17), side by side in one process: bench_rest.py's
tank at 8 mm spacing (28.7k particles, hydrostatic start, water's viscosity, 2 threads), 20 warm-up steps,
then 4 alternating rounds of 50 steps each; median ms per step and each variant's ratio to the first.
A variant is a kernel, or kernel@support (support in l0; else the kernel's default).

    .venv/bin/python benchmarks/bench_sph_kernels.py [poly6_spiky spline spline@2.2 ...]
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

KERNELS = ("poly6_spiky", "spline")


def make(variant: str, l0: float):
    import bench_rest as B
    from stages.simulate.driver import hydrostatic_start
    from stages.simulate.sph import SPHParams, SPHSolver
    B.L0 = l0
    x, sdf = B.tank()
    kernel, _, support = variant.partition("@")
    params = SPHParams(kernel=kernel, support=float(support) if support else None)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=params,
                  gravity=(0, 0, -9.81), mu=0.001, v_ref=math.sqrt(2 * 9.81 * B.DEPTH))
    hydrostatic_start(s)
    return s


def main() -> None:
    import numba as nb
    nb.set_num_threads(min(2, nb.config.NUMBA_NUM_THREADS))
    variants = sys.argv[1:] or KERNELS
    solvers = {k: make(k, 0.008) for k in variants}
    for s in solvers.values():
        for _ in range(20):
            s.step(10.0)
    ms = {k: [] for k in variants}
    for _ in range(4):  # alternating rounds: machine load hits both alike
        for k, s in solvers.items():
            t0 = time.perf_counter()
            for _ in range(50):
                s.step(10.0)
            ms[k].append((time.perf_counter() - t0) / 50 * 1e3)
    med = {k: float(np.median(v)) for k, v in ms.items()}
    first = variants[0]
    print(f"{len(solvers[first].x)} particles: " + ", ".join(f"{k} {v:.2f} ms/step" for k, v in med.items())
          + "; " + ", ".join(f"{k} / {first} {med[k] / med[first]:.2f}" for k in variants[1:]))


if __name__ == "__main__":
    main()
