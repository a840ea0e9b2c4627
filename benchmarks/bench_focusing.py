"""How fast the fastest particle gets where pressure focuses the fluid's energy, against the spacing (issue 17,
session 38): the stability suite's closed cone (a void closes over its apex), its knife-edge ridge (the split
halves' fronts) and its dam break (the surge's run-up), each solver from the suite's start with its blow-up guard,
to 0.3 s; the fastest particle over every step and at 0.01 s samples, over the scene's ballistic bound, the
particles above 1.5 x it, the steps the guard let through as focusing (Guard.focused), the energy at the end over
the start:

    .venv/bin/python benchmarks/bench_focusing.py [--cases cone_40deg,ridge_20deg,dam_break]
                                                  [--solvers sph,dfsph,mps] [--spacings 0.02,0.014,0.01,0.007]

A peak that grows as the spacing shrinks has no bound to converge to: the cone's is Rayleigh's collapse of an empty
pocket, singular in a single-phase model. Writes benchmarks/results/focusing.json and
benchmarks/results/images/focusing.png (about 6 minutes on 2 cores)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "stability"))

import stability_cases as S  # noqa: E402
from stages.simulate.driver import mechanical_energy  # noqa: E402

T_END, SAMPLE = 0.3, 0.01


def run(case: str, solver: str, l0: float) -> dict:
    scene = {"cone_40deg": S.cone, "ridge_20deg": S.ridge, "dam_break": S.dam_break}[case](l0=l0)
    sol = S.make_solver(solver, scene)
    vb = scene.v_bound
    e0 = mechanical_energy(sol, scene.gravity, 0.0)  # per kg, the potential from z = 0 (each scene's floor)
    sampled, above, t0, blowup = 0.0, 0, time.perf_counter(), None
    try:
        while sol.t < T_END - 1e-12:
            sol.advance_to(min(T_END, sol.t + SAMPLE))
            speed = np.linalg.norm(sol.v, axis=1)
            sampled = max(sampled, float(speed.max()) / vb)
            above = max(above, int((speed > 1.5 * vb).sum()))
    except S.BlowUp as e:
        blowup = str(e)
    return {"case": case, "solver": solver, "spacing": l0, "particles": len(scene.x), "peak": sol.guard.peak / vb,
            "sampled": sampled, "above_1.5": above, "focused_steps": sol.guard.focus_steps,
            "energy_end_over_start": mechanical_energy(sol, scene.gravity, 0.0) / e0, "blowup": blowup, "steps": sol.steps,
            "wall_seconds": time.perf_counter() - t0}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cases = sorted({r["case"] for r in rows}, key=[r["case"] for r in rows].index)
    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 3.6), sharey=True)
    for ax, case in zip(np.atleast_1d(axes), cases):
        for solver in sorted({r["solver"] for r in rows if r["case"] == case}):
            pts = sorted((r["spacing"] * 100, r["peak"]) for r in rows if r["case"] == case and r["solver"] == solver)
            ax.plot(*zip(*pts), "o-", label=solver)
        ax.axhline(S.SPEED_LIMIT, color="k", lw=0.8, ls="--", label="the guard's speed limit")
        ax.set_xscale("log")
        ticks = sorted({r["spacing"] * 100 for r in rows})
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.minorticks_off()
        ax.invert_xaxis()
        ax.set_title(case)
        ax.set_xlabel("spacing, cm")
    np.atleast_1d(axes)[0].set_ylabel("fastest particle / ballistic bound")
    np.atleast_1d(axes)[0].legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="cone_40deg,ridge_20deg,dam_break")
    ap.add_argument("--solvers", default="sph,dfsph,mps")
    ap.add_argument("--spacings", default="0.02,0.014,0.01,0.007")
    a = ap.parse_args()
    rows = []
    for case in a.cases.split(","):
        for solver in a.solvers.split(","):
            for l0 in (float(s) for s in a.spacings.split(",")):
                r = run(case, solver, l0)
                rows.append(r)
                print(f"{case:12s} {solver:6s} l0 {l0:.3f} n {r['particles']:6d}  peak {r['peak']:6.2f}  sampled "
                      f"{r['sampled']:5.2f}  >1.5x {r['above_1.5']:4d}  let through {r['focused_steps']:2d}  E end/0 "
                      f"{r['energy_end_over_start']:.3f}  {r['wall_seconds']:.0f} s" + (f"  {r['blowup']}" if r["blowup"] else ""),
                      flush=True)
    out = ROOT / "benchmarks" / "results" / "focusing.json"
    out.write_text(json.dumps(rows, indent=1))
    plot(rows, ROOT / "benchmarks" / "results" / "images" / "focusing.png")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
