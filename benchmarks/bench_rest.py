"""Water at rest (issue 17): a 0.3 x 0.2 m tank filled 0.25 m deep at 1.25 cm spacing, gravity and
water's viscosity (mu = 0.001 Pa s) only; mean and 99th percentile speed at 0.5, 1, 1.5 and 3 s (and the mean
averaged over the half second before each: one sample swings with the tank's first mode) for WCSPH (sph), DFSPH
and MPS, each from the scene's start as the pipeline makes it, and SPlisHSPlasH's DFSPH on the same tank (its own
lattice start, volume maps, CFL steps) when pysplishsplash imports:

    .venv/bin/python benchmarks/bench_rest.py [--solvers sph,dfsph,mps,splishsplash] [--until 3] [--settle 1.5]
                                              [--set sph.wall_gradient=false ...] [--wall-offset 0.25[,0.25,0]]
                                              [--spacing 0.013] [--sdf-cell 0.25]

Also the centre of mass's drop since t = 0 (the potential energy the start releases: g times it), overall, in the
band within 3 l0 of the side walls and in the interior. Also the hydrostatic pressure error over the last 0.3 s (mean of 11 samples, and their range; pressure of the particles 2-8 layers deep, at least
2 l0 from the side walls, against rho g h of their depth below the mean free surface). Each solver runs in
its own subprocess (2 threads). Writes benchmarks/results/rest.json."""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

G, RHO0, MU = 9.81, 1000.0, 0.001
SIZE = (0.3, 0.2)
DEPTH = 0.25
L0 = float(os.environ.get("REST_SPACING", "0.0125"))  # --spacing (the solvers' subprocesses read it)
TANK_H = 0.35
TIMES = (0.5, 1.0, 1.5, 3.0)
AVERAGE_EVERY = 0.05  # s: the mean speed sampled this often and averaged over the half second before each of TIMES
                      # (one run's samples at 0.5 / 1 / 1.5 s read 0.038 / 0.018 / 0.041 m/s: the tank rings)
GL_PRELOAD = "/lib/x86_64-linux-gnu/libGLdispatch.so.0"


def tank():
    """The tank's SDF (its nodes on the walls, or REST_WALL_OFFSET l0 off them: --wall-offset; REST_SDF_CELL l0 apart:
    --sdf-cell) and its lattice."""
    from stages.common.sdf import box_interior_sdf, grid_from_function
    from stages.simulate.emitters import lattice
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([SIZE[0], SIZE[1], TANK_H])
    shift = np.array([float(v) for v in os.environ.get("REST_WALL_OFFSET", "0").split(",")]) * np.ones(3)
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo - shift * L0, hi, float(os.environ.get("REST_SDF_CELL", "0.5")) * L0)
    x = lattice([0, 0, 0], [SIZE[0], SIZE[1], DEPTH], L0)
    return x, sdf


def make(solver: str, sets: dict, hydrostatic: bool = True):
    """The solver on the tank, started as the pipeline starts it (driver.initial_state)."""
    from stages.simulate.driver import hydrostatic_start
    x, sdf = tank()
    v = np.zeros_like(x)
    g = np.array([0.0, 0.0, -G])
    vref = math.sqrt(2 * G * DEPTH)
    ids = np.arange(len(x))
    if solver == "sph":
        from stages.simulate.sph import SPHParams, SPHSolver
        s = SPHSolver(x, v, ids, sdf, spacing=L0, rho0=RHO0, params=SPHParams(**sets), gravity=g, mu=MU, v_ref=vref)
    elif solver == "dfsph":
        from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
        from stages.simulate.effects import EffectConstants
        s = DFSPHSolver(x, v, ids, sdf, spacing=L0, rho0=RHO0, params=DFSPHParams(**sets), gravity=g,
                        effects=EffectConstants(mu=MU, wall_viscosity=True))
    else:
        from stages.simulate.mps import MPSParams, MPSSolver
        s = MPSSolver(x, v, ids, sdf, spacing=L0, rho0=RHO0, params=MPSParams(**sets), gravity=g, mu=MU, v_ref=vref)
    if hydrostatic:
        hydrostatic_start(s)
    return s


def run_one(solver: str, until: float, sets: dict, settle: float = 0.0) -> dict:
    import numba as nb
    nb.set_num_threads(min(2, nb.config.NUMBA_NUM_THREADS))
    s = make(solver, sets, hydrostatic=os.environ.get("REST_LATTICE_START") != "1")
    rows = []
    t0 = time.perf_counter()  # the settling counts: it is part of what the run costs
    if settle > 0:
        from stages.simulate.driver import settle as settle_start
        settle_start(s, settle)
    errors, speeds = [], []
    f0 = s.frame()
    z0 = heights(f0)
    x0 = f0.x[np.argsort(f0.id)]  # the band within 3 l0 of a side wall, by id, as it starts
    band = side_distance(x0) < 3 * L0
    times = [t for t in TIMES if t <= until + 1e-9]
    pressure_at = {round(until - 0.3 + 0.03 * k, 9) for k in range(10)}  # the pressure swings with the surface's
    speed_at = {round(AVERAGE_EVERY * k, 9) for k in range(1, int(until / AVERAGE_EVERY + 1e-9) + 1)}  # slow modes
    for t in sorted(pressure_at | speed_at | {round(t, 9) for t in times}):
        s.advance_to(t)
        f = s.frame()
        sp = np.linalg.norm(f.v, axis=1)
        if t in pressure_at:
            errors.append(hydrostatic_error(f))
        if t in speed_at:
            speeds.append((t, float(sp.mean())))
        if any(abs(t - tt) < 1e-9 for tt in times):
            window = [m for ts, m in speeds if t - 0.5 < ts <= t + 1e-9]
            dz = 1e3 * (heights(f) - z0)  # mm, per particle
            rows.append({"t": t, "mean": float(sp.mean()), "p99": float(np.percentile(sp, 99)), "max": float(sp.max()),
                         "mean_last_half_second": float(np.mean(window)), "steps": s.steps,
                         "drop_mm": -float(dz.mean()), "drop_side_mm": -float(dz[band].mean()),
                         "drop_inner_mm": -float(dz[~band].mean())})
    f = s.frame()
    errors.append(hydrostatic_error(f))
    return {"solver": solver, "particles": len(f.x), "rows": rows, "hydrostatic_error": float(np.mean(errors)),
            "hydrostatic_error_range": [float(min(errors)), float(max(errors))],
            "surface_drop_mm": 1e3 * (DEPTH - surface(f.x)), "wall_seconds": time.perf_counter() - t0, "set": sets, "settle": settle}


def heights(f) -> np.ndarray:
    """Each particle's height, ordered by id: the centre of mass's drop since t = 0 is the potential energy the
    fluid released (g times it, J/kg)."""
    return f.x[np.argsort(f.id), 2]


def side_distance(x) -> np.ndarray:
    """Each particle's distance from the nearest side wall (the tank's walls at x = 0, SIZE[0], y = 0, SIZE[1])."""
    return np.minimum(np.minimum(x[:, 0], SIZE[0] - x[:, 0]), np.minimum(x[:, 1], SIZE[1] - x[:, 1]))


def surface(x) -> float:
    """The free surface: the mean height of the top layer (particles within l0 of the highest) + l0 / 2."""
    z = x[:, 2]
    return float(z[z > z.max() - 0.5 * L0].mean() + 0.5 * L0)


def hydrostatic_error(f) -> float:
    z = f.x[:, 2]
    top = surface(f.x)
    depth = top - z
    sel = (depth > 2 * L0) & (depth < 8 * L0)
    sel &= side_distance(f.x) > 2 * L0
    return float(f.p[sel].mean() / (RHO0 * G * depth[sel]).mean() - 1.0)


def run_splishsplash(until: float) -> dict:
    """SPlisHSPlasH DFSPH on the same tank, headless (PEERS.md), in its own process."""
    try:
        import importlib.util
        if importlib.util.find_spec("pysplishsplash") is None:
            return {"skipped": "pysplishsplash is not installed (pip install pysplishsplash)"}
    except ImportError:
        return {"skipped": "pysplishsplash is not installed"}
    script = ROOT / "benchmarks" / "splishsplash_rest.py"
    env = dict(os.environ, LD_PRELOAD=GL_PRELOAD, STOP_AT=str(until), OMP_NUM_THREADS="2")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=3600)
    if r.returncode != 0:
        return {"skipped": f"pysplishsplash failed: {r.stderr.strip().splitlines()[-1:]}"}
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solvers", default="sph,dfsph,mps,splishsplash")
    ap.add_argument("--until", type=float, default=3.0)
    ap.add_argument("--set", action="append", default=[], help="SOLVER.PARAM=VALUE")
    ap.add_argument("--settle", type=float, default=0.0, help="seconds of fluid.settle before t = 0 (driver.settle)")
    ap.add_argument("--wall-offset", default="0", help="the SDF's nodes this many l0 off the walls, one number or "
                    "x,y,z (0.25: the wall maps' nodes a quarter of their spacing off, as for a mesh sdf_bake cannot align; "
                    "0.25,0.25,0: the floor on them, the sides off)")
    ap.add_argument("--spacing", type=float, default=0.0125, help="particle spacing l0, m (0.013: the tank is no "
                    "whole number of spacings wide, as a user's rarely is: a gap at the far walls)")
    ap.add_argument("--sdf-cell", type=float, default=0.5, help="the SDF's node spacing in l0 (sdf_bake's cell; "
                    "0.25: the wall maps' quadrature points on its nodes)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "rest.json"))
    a = ap.parse_args()
    if not a.one:
        os.environ["REST_WALL_OFFSET"] = str(a.wall_offset)  # the solvers' subprocesses read it
        os.environ["REST_SPACING"] = str(a.spacing)
        os.environ["REST_SDF_CELL"] = str(a.sdf_cell)
    sets: dict = {}
    for kv in a.set:
        k, v = kv.split("=", 1)
        solver, param = k.split(".", 1)
        sets.setdefault(solver, {})[param] = json.loads(v)
    if a.one:
        print(json.dumps(run_one(a.one, a.until, sets.get(a.one, {}), a.settle)))
        return
    results = []
    for solver in a.solvers.split(","):
        if solver == "splishsplash":
            res = {"solver": "SPlisHSPlasH DFSPH", **run_splishsplash(a.until)}
        else:
            cmd = [sys.executable, __file__, "--one", solver, "--until", str(a.until), "--settle", str(a.settle)] + sum((["--set", s] for s in a.set), [])
            r = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)))
            if r.returncode != 0:
                res = {"solver": solver, "failed": (r.stderr.strip().splitlines() or ["?"])[-1]}
            else:
                res = json.loads(r.stdout.strip().splitlines()[-1])
        results.append(res)
        print(table_row(res), flush=True)
    Path(a.out).write_text(json.dumps(results, indent=1) + "\n")


def table_row(res: dict) -> str:
    if "rows" not in res:
        return f"{res['solver']:<20} {res.get('skipped') or res.get('failed')}"
    cells = "  ".join(f"{r['t']:.1f}s {r['mean']:.4f}/{r['p99']:.4f}" + (f" (avg {r['mean_last_half_second']:.4f})"
                      if "mean_last_half_second" in r else "") for r in res["rows"])
    last = res["rows"][-1] if res["rows"] else {}
    if "drop_mm" in last:
        cells += (f"  centre of mass {last['drop_mm']:+.2f} mm down (side band {last['drop_side_mm']:+.2f}, "
                  f"interior {last['drop_inner_mm']:+.2f})")
    extra = ""
    if "hydrostatic_error" in res:
        extra = f"  p err {100 * res['hydrostatic_error']:+.1f}%  surface drop {res['surface_drop_mm']:.2f} mm"
    return f"{res['solver']:<20} mean/p99 m/s: {cells}{extra}"


if __name__ == "__main__":
    main()
