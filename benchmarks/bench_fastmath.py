"""What keeping NaN/Inf semantics costs (issue 17): the WCSPH force kernel built with
kernels.FASTMATH (no 'nnan'/'ninf', so a blow-up stays visible) against the same kernel with full
fastmath, and the per-step blow-up check (kernels.count_blown), on the PEERS dam break at 20k:

    .venv/bin/python benchmarks/bench_fastmath.py [--n 20000] [--rounds 7] [--steps 20]

Both builds of the force kernel are compiled from the same Python function in this process and timed
in alternating rounds as CPU time of one thread (a shared machine's load hits both alike); the
accelerations of the two builds are compared too. Writes benchmarks/results/fastmath.json."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numba as nb
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_sph import dam_break, make_solver  # noqa: E402
from stages.simulate.sph import SPHSolver  # noqa: E402
from stages.simulate import sph_kernels as K  # noqa: E402
from stages.simulate.kernels import count_blown  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--steps", type=int, default=20)
    a = ap.parse_args()
    nb.set_num_threads(1)
    x, sdf, l0, height = dam_break(a.n)
    s = make_solver(SPHSolver, x, sdf, l0, height)
    s.advance_to(0.15)  # the collapse under way: particles disordered, many at walls
    builds = {"FASTMATH (keeps NaN/Inf)": K.forces,
              "fastmath=True (full)": nb.njit(parallel=True, fastmath=True)(K.forces.py_func)}
    acc = {}
    times = {k: [] for k in builds}
    for name, fn in builds.items():  # compile, and the accelerations of each build
        K.forces, saved = fn, K.forces
        s.forces()
        acc[name] = s.acc.copy()
        K.forces = saved
    for _ in range(a.rounds):
        for name, fn in builds.items():
            K.forces, saved = fn, K.forces
            t0 = time.process_time()
            for _ in range(a.steps):
                s.forces()
            times[name].append(1e3 * (time.process_time() - t0) / a.steps)
            K.forces = saved
    count_blown(s.x, s.v, 1.0)
    t0 = time.process_time()
    for _ in range(200):
        count_blown(s.x, s.v, 1.0)
    check_ms = 1e3 * (time.process_time() - t0) / 200
    t0 = time.process_time()
    for _ in range(a.steps):
        s.step(1.0)
    step_ms = 1e3 * (time.process_time() - t0) / a.steps
    a_strict, a_full = acc.values()
    res = {"particles": len(s.x), "threads": 1,
           "forces_ms_median": {k: float(np.median(v)) for k, v in times.items()},
           "acc_max_relative_difference": float(np.abs(a_strict - a_full).max() / np.abs(a_full).max()),
           "blowup_check_ms": check_ms, "step_ms": step_ms}
    ms = list(res["forces_ms_median"].values())
    res["forces_cost"] = ms[0] / ms[1] - 1.0
    print(json.dumps(res, indent=1))
    out = ROOT / "benchmarks" / "results" / "fastmath.json"
    out.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
