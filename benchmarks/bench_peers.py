"""Equal accuracy against SPlisHSPlasH (issue 20): the PEERS.md dam break, each side with its own adaptive
steps, in one run.

    python benchmarks/bench_peers.py [--sim-time 0.5] [--100k] [--solvers sph,dfsph,mps]
                                     [--peer-tolerances 0.1,0.05,0.02]

Scene: a 1 m cube of water (19,683 particles, l0 = 1/27 m; --100k: 97,336, l0 = 1/46 m) in a 3 x 2 x 1.2 m
tank, gravity, mu = 0.01 Pa s, as bench_dfsph.py (whose solver set-up and timing loop this reuses). Ours:
sph, dfsph, mps with their default parameters (CFL steps). SPlisHSPlasH 2.19 (volume maps, CFL steps,
splishsplash_run.py): DFSPH with the same CFL number and largest step as our DFSPH (cflFactor = 0.8 / 0.4, at
most 5 ms) and our density and divergence tolerances (0.1 %), then at tighter tolerances; WCSPH (stiffness
50,000, exponent 7) with the CFL number of our WCSPH and at most 0.5 ms (it blows up at 1 ms, PEERS.md).

Per solver: wall seconds per simulated second over ``--sim-time`` (set-up and the first step excluded), ms per
step, mean step, and the density error (mean over particles of max(rho / rho0 - 1, 0), sampled every 1/30 s:
its mean and max over the run). "Equal accuracy": SPlisHSPlasH DFSPH's wall time at our solver's mean density
error, interpolated (log-log) between its tolerances. Goal (issue 20): our best solver <= 0.5x that, and our
DFSPH's step no slower than SPlisHSPlasH DFSPH's at the same tolerance. Writes benchmarks/results/peers.json."""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

# both sides' waiting threads sleep rather than spin, so CPU seconds measure work (before numba loads)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import bench_dfsph  # noqa: E402  (the scene and our timing loop)

GL_PRELOAD = "/lib/x86_64-linux-gnu/libGLdispatch.so.0"


def run_splishsplash(job: dict, timeout: float = 3600, cache: bool = True) -> dict:
    """One splishsplash_run.py job in its own process (PEERS.md: LD_PRELOAD, 2 OpenMP threads). ``cache``:
    SPlisHSPlasH keeps its volume maps for the same tank and spacing in a folder under the system's temp dir
    (set-up, not timed: only for comparisons that exclude set-up)."""
    import hashlib
    import importlib.util
    if importlib.util.find_spec("pysplishsplash") is None:
        return {"skipped": "pysplishsplash is not installed (optional extra 'peers')"}
    if cache:
        geometry = json.dumps([job["tank_lo"], job["tank_hi"], job["spacing"], job.get("map_cell")])
        job = dict(job, cache_dir=str(Path(tempfile.gettempdir()) / "splishsplash_cache"
                                      / hashlib.sha1(geometry.encode()).hexdigest()[:12]))
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as fh:
        json.dump(job, fh)
    env = dict(os.environ, OMP_NUM_THREADS="2", LD_PRELOAD=GL_PRELOAD, OMP_WAIT_POLICY="PASSIVE")
    try:
        r = subprocess.run([sys.executable, str(HERE / "splishsplash_run.py"), fh.name], env=env,
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"skipped": f"SPlisHSPlasH did not finish in {timeout:.0f} s"}
    finally:
        os.unlink(fh.name)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if line is None:
        return {"skipped": f"SPlisHSPlasH failed (exit {r.returncode}): {r.stderr.strip()[-300:]}"}
    return json.loads(line[len("RESULT "):])


def dam_break_job(method: str, sim_time: float, **kw) -> dict:
    """The bench_dfsph.py scene as a splishsplash_run.py job."""
    l0 = bench_dfsph.L0
    return {"tank_lo": [-1.5, -1.0, 0.0], "tank_hi": [1.5, 1.0, 1.2], "fluid_lo": [-1.5, -1.0, 0.0],
            "fluid_hi": [-0.5, 0.0, 1.0], "spacing": l0, "method": method, "stop": sim_time, "fps": 30,
            "viscosity": bench_dfsph.MU, **kw}


def peer_at_error(points: list[tuple[float, float]], err: float) -> tuple[float, bool]:
    """SPlisHSPlasH's wall s per simulated s at density error ``err``: log-log interpolation between its
    (error, wall) points; also whether ``err`` lies outside them (then the nearest end's slope extrapolates)."""
    pts = sorted(p for p in points if p[0] > 0)
    le, lw = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    x = math.log(err)
    outside = bool(x < le[0] or x > le[-1])
    if len(pts) == 1:
        return float(pts[0][1]), outside
    i = int(np.clip(np.searchsorted(le, x) - 1, 0, len(pts) - 2))
    slope = (lw[i + 1] - lw[i]) / (le[i + 1] - le[i]) if le[i + 1] > le[i] else 0.0
    return float(math.exp(lw[i] + slope * (x - le[i]))), outside


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim-time", type=float, default=0.5)
    ap.add_argument("--100k", dest="big", action="store_true", help="97,336 particles (slow on 2 cores)")
    ap.add_argument("--solvers", default="sph,dfsph,mps")
    ap.add_argument("--peer-tolerances", default="0.1,0.05,0.02", help="SPlisHSPlasH DFSPH maxError, percent")
    a = ap.parse_args()
    if a.big:
        bench_dfsph.L0 = 1.0 / 46
    from stages.simulate.dfsph import DFSPHParams
    from stages.simulate.sph import SPHParams
    dp, sp = DFSPHParams(), SPHParams()
    res = {"scene": f"PEERS.md dam break, {'97,336' if a.big else '19,683'} particles", "command": " ".join(sys.argv),
           "sim_time": a.sim_time, "load_average_1min_start": os.getloadavg()[0],
           "note": "one run on a shared 2-core machine; SPlisHSPlasH starts 1.5 l0 off the walls "
                   "(splishsplash_run.py), ours at l0/2", "ours": {}, "splishsplash": {}}
    for kind in a.solvers.split(","):
        r = bench_dfsph.run_ours(kind, a.sim_time, trace_memory=False)
        res["ours"][kind] = r
        print(f"ours {kind:6s} {r['wall_s_per_simulated_s']:7.2f} wall s/sim s  {r['ms_per_step']:6.1f} ms/step  "
              f"dt {1e3 * r['mean_dt']:.2f} ms  density error mean {100 * r['density_error_mean']:.3f} % "
              f"max {100 * r['density_error_max']:.3f} %  CPU {r['cpu_s_per_simulated_s']:.2f} s/sim s", flush=True)
    runs = [("DFSPH", "dfsph", dict(cfl_factor=dp.cfl / 0.4, dt_max=dp.dt_max, max_error=float(tol),
                                    max_error_v=100 * dp.max_divergence_error)) for tol in a.peer_tolerances.split(",")]
    runs.append(("WCSPH", "wcsph", dict(cfl_factor=sp.cfl / 0.4, dt_max=0.0005, dt=0.0005, stiffness=50000)))
    for name, method, kw in runs:
        r = run_splishsplash(dam_break_job(method, a.sim_time, **kw))
        r.pop("frames", None)
        key = f"{name} maxError {kw['max_error']} %" if method == "dfsph" else name
        res["splishsplash"][key] = {**r, "job": kw}
        if "skipped" in r:
            print(f"SPlisHSPlasH {key}: skipped: {r['skipped']}", flush=True)
            continue
        print(f"SPlisHSPlasH {key:24s} {r['wall_s_per_simulated_s']:7.2f} wall s/sim s  {r['ms_per_step']:6.1f} "
              f"ms/step  dt {1e3 * r['mean_dt']:.2f} ms  density error mean {100 * r['density_error_mean']:.3f} % "
              f"max {100 * r['density_error_max']:.3f} %  CPU {r['cpu_s_per_simulated_s']:.2f} s/sim s  "
              f"(set-up {r['setup_s']:.0f} s)", flush=True)
    dfsph_peer = [r for k, r in res["splishsplash"].items() if k.startswith("DFSPH") and "skipped" not in r]
    if dfsph_peer:
        pts = [(r["density_error_mean"], r["wall_s_per_simulated_s"]) for r in dfsph_peer]
        cpu_pts = [(r["density_error_mean"], r["cpu_s_per_simulated_s"]) for r in dfsph_peer]
        cmp = {}
        for kind, r in res["ours"].items():
            peer, outside = peer_at_error(pts, r["density_error_mean"])
            peer_cpu, _ = peer_at_error(cpu_pts, r["density_error_mean"])
            cmp[kind] = {"ours_wall_s_per_sim_s": r["wall_s_per_simulated_s"], "peer_dfsph_at_equal_error": peer,
                         "ratio": r["wall_s_per_simulated_s"] / peer, "extrapolated": outside,
                         "ours_cpu_s_per_sim_s": r["cpu_s_per_simulated_s"], "peer_dfsph_cpu_at_equal_error": peer_cpu,
                         "cpu_ratio": r["cpu_s_per_simulated_s"] / peer_cpu}
        best = min(cmp, key=lambda k: cmp[k]["ratio"])
        same_tol = next((r for r in dfsph_peer if math.isclose(r["job"]["max_error"], 100 * dp.max_density_error)),
                        None)
        res["equal_accuracy"] = cmp
        res["goal"] = {"best_solver": best, "best_ratio": cmp[best]["ratio"], "best_cpu_ratio": cmp[best]["cpu_ratio"],
                       "ratio_goal": 0.5, "ratio_met": cmp[best]["ratio"] <= 0.5}
        if same_tol and "dfsph" in res["ours"]:
            ratio = res["ours"]["dfsph"]["ms_per_step"] / same_tol["ms_per_step"]
            cpu_ratio = res["ours"]["dfsph"]["cpu_ms_per_step"] / same_tol["cpu_ms_per_step"]
            res["goal"].update(step_ratio_dfsph=ratio, step_cpu_ratio_dfsph=cpu_ratio, step_met=ratio <= 1.0)
        for kind, c in cmp.items():
            print(f"{kind:6s} {c['ours_wall_s_per_sim_s']:7.2f} vs SPlisHSPlasH DFSPH at equal density error "
                  f"{c['peer_dfsph_at_equal_error']:7.2f} wall s/sim s: ratio {c['ratio']:.2f} (CPU s: "
                  f"{c['ours_cpu_s_per_sim_s']:.2f} vs {c['peer_dfsph_cpu_at_equal_error']:.2f}, {c['cpu_ratio']:.2f})"
                  f"{' (extrapolated)' if c['extrapolated'] else ''}")
        print("goal:", json.dumps(res["goal"]))
    res["load_average_1min_end"] = os.getloadavg()[0]
    out = HERE / "results" / ("peers_100k.json" if a.big else "peers.json")
    out.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
