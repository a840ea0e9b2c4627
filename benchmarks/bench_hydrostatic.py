"""Hydrostatic column (issue 4/5): layer-mean pressure against rho g h at 10, 20 and 40 particles of depth.

    .venv/bin/python benchmarks/bench_hydrostatic.py [--solvers sph,sph_wall_gradient,sph_corrected,dfsph,mps]
                                                     [--layers 44] [--settle 0.8]

A 10 x 10 x ``layers`` column of water at rest in a box (l0 = 1 cm, viscosity 5 Pa s to damp the start
within a second), settled for ``settle`` s and then each particle's pressure averaged over 0.2 s (100
samples). Per depth: the mean pressure of the five layers around it (columns at least 2 l0 from the side
walls), its spread (standard deviation within the band) and the error against rho g (H - z), H the initial height. Also the
largest speed and whether any particle is below the floor. One thread: the column is small.
Writes benchmarks/results/hydrostatic.json.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numba as nb
import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
from stages.simulate.emitters import lattice
from stages.simulate.mps import MPSParams, MPSSolver
from stages.simulate.sph import SPHParams, SPHSolver

ROOT = Path(__file__).resolve().parents[1]
L0, W, G, RHO0, MU = 0.01, 0.1, 9.81, 1000.0, 5.0
AVERAGE, SAMPLES = 0.2, 100  # each particle's pressure averaged over 0.2 s, 100 samples


# WCSPH as configured by default (conservative wall pressure), with the former mirrored wall pressure, with the walls' share of the hydrostatic gradient only, and with the
# opt-in gradient correction too
SPH_VARIANTS = {"sph": {}, "sph_mirrored": {"wall_pressure": "mirrored"}, "sph_wall_gradient": {"wall_gradient": True},
                "sph_corrected": {"gradient_correction": True, "wall_gradient": True}}


def make(solver: str, x: np.ndarray, sdf, height: float):
    common = dict(spacing=L0, rho0=RHO0, gravity=(0, 0, -G), mu=MU)
    v_ref = float(np.sqrt(2 * G * height))
    ids = np.arange(len(x))
    if solver in SPH_VARIANTS:
        return SPHSolver(x, np.zeros_like(x), ids, sdf, params=SPHParams(**SPH_VARIANTS[solver]), v_ref=v_ref,
                         **common)
    if solver == "mps":
        return MPSSolver(x, np.zeros_like(x), ids, sdf, params=MPSParams(), v_ref=v_ref, **common)
    return DFSPHSolver(x, np.zeros_like(x), ids, sdf, params=DFSPHParams(), **common)


def measure(solver: str, layers: int, settle: float) -> dict:
    height = layers * L0
    top = height + 0.1
    sdf = grid_from_function(box_interior_sdf([0, 0, 0], [W, W, top]), [0, 0, 0], [W, W, top], L0 / 2)
    x = lattice([0, 0, 0], [W, W, height], L0)
    s = make(solver, x, sdf, height)
    t0 = time.perf_counter()
    s.advance_to(settle)
    p = np.zeros(len(x))
    for k in range(1, SAMPLES + 1):  # WCSPH pressure carries acoustic noise: sample it densely
        s.advance_to(settle + AVERAGE * k / SAMPLES)
        f = s.frame()
        p[f.id] += f.p / SAMPLES
    seconds = time.perf_counter() - t0
    p, z = p[f.id], f.x[:, 2]
    inner = np.minimum(f.x[:, :2], W - f.x[:, :2]).min(axis=1) > 2 * L0
    rows = []
    for depth in (10, 20, 40):
        if depth > layers:
            continue
        # a band of five layers around the depth: one layer holds ~36 inner particles whose pressures
        # spread 30-50 %, too few for a mean good to a few percent
        layer = inner & (np.abs(z - (height - (depth - 0.5) * L0)) < 2.5 * L0)
        rho_g_h = RHO0 * G * (height - z[layer]).mean()
        rows.append({"depth": depth, "p_mean": float(p[layer].mean()), "p_std": float(p[layer].std()),
                     "rho_g_h": float(rho_g_h), "error": float(p[layer].mean() / rho_g_h - 1),
                     "spread": float(p[layer].std() / rho_g_h)})
    return {"solver": solver, "particles": len(x), "layers": layers, "steps": s.steps, "seconds": seconds,
            "max_speed": float(np.linalg.norm(f.v, axis=1).max()), "below_floor": int((z < 0).sum()), "depths": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solvers", default="sph,sph_mirrored,sph_wall_gradient,sph_corrected,dfsph,mps")
    ap.add_argument("--layers", type=int, default=44)
    ap.add_argument("--settle", type=float, default=0.8)
    args = ap.parse_args()
    nb.set_num_threads(1)
    results = []
    for solver in args.solvers.split(","):
        r = measure(solver, args.layers, args.settle)
        results.append(r)
        cells = "  ".join(f"{d['depth']}: {100 * d['error']:+.1f} % (spread {100 * d['spread']:.1f} %)" for d in r["depths"])
        print(f"{solver:6s} {r['particles']} particles, {r['steps']} steps, {r['seconds']:.0f} s, max speed "
              f"{r['max_speed']:.3f} m/s, below floor {r['below_floor']} | p vs rho g h by depth  {cells}", flush=True)
    out = ROOT / "benchmarks" / "results" / "hydrostatic.json"
    out.write_text(json.dumps({"command": "benchmarks/bench_hydrostatic.py", "results": results}, indent=2))


if __name__ == "__main__":
    main()
