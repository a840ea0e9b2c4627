"""SPlisHSPlasH (pip package pysplishsplash) on a box tank with a box of water, headless, for the peer
benchmarks (bench_peers.py, bench_shot.py, peers_accuracy_plot.py). One job per process:

    LD_PRELOAD=/lib/x86_64-linux-gnu/libGLdispatch.so.0 OMP_NUM_THREADS=2 python splishsplash_run.py JOB.json

JOB (all lengths in metres, in OUR frame: z up): tank_lo, tank_hi, fluid_lo, fluid_hi, spacing (particle
diameter), method "dfsph" | "wcsph", stop (simulated s), fps (frames sampled), cfl_factor, dt_max, dt (initial
or fixed step), cfl_method (1 adaptive, 0 fixed), max_error / max_error_v (DFSPH tolerances, percent as
SPlisHSPlasH takes them), stiffness (WCSPH), viscosity (Pa s = kinematic * 1000: SPlisHSPlasH's "Standard"
viscosity is a kinematic coefficient), frames_dir (optional: every frame's positions as frame_NNNN.npy, our
frame), map_cell (volume map cell in diameters, default 1.4 as PEERS.md's scenes), wall_gap (diameters, default 1),
cache_dir (optional: a folder where SPlisHSPlasH caches its volume maps between jobs; default none, no cache).

Its start differs from ours in one way: SPlisHSPlasH's volume maps blow a block up whose first layer is
d/2 or d from a wall (the column reached the far wall of a 1.25 m tank in 17 ms at d = 3.1 cm, with CFL
factors 0.5 and 2 alike, and with a volume map 3x finer); at 1.5 d it starts at rest (PEERS.md's own scenes
start 1.9 d off). So a block against a wall is moved off it by ``wall_gap`` diameters, or, when against
both opposite walls, shrunk by that on each side (the caller accounts for the shift).

SPlisHSPlasH is y up: our (x, y, z) is its (x, z, y); a box is unchanged by the swap. Its CFL step is
dt = cflFactor * 0.4 * diameter / max|v + a dt| (Simulation::updateTimeStepSizeCFL), ours cfl * l0 / v_max:
the same CFL number C is cflFactor = C / 0.4. The fluid block is sampled by SPlisHSPlasH (regular, denseMode 0):
the block handed to it is widened by one diameter so that it places as many particles as our lattice does.

Prints one line RESULT {...}: particles, steps, wall seconds of stepping (set-up: scene load, volume maps,
and the time spent here sampling frames excluded), ms per step, simulated seconds, and per frame the time,
the mean over particles of max(rho / rho0 - 1, 0) from SPlisHSPlasH's own density field (computed at the
start of its last step, its boundary volume included) and the fluid's extent (min, max per axis, our frame).
Wall set-up is reported separately (setup_s). Also the process's CPU seconds (all threads) of the same steps:
steadier than wall time when other work shares the cores (run with OMP_WAIT_POLICY=PASSIVE, so that waiting
threads do not spin)."""
import json
import math
import os
import sys
import tempfile
import time

import numpy as np
import pysplishsplash as sph

CUBE = """v -0.5 -0.5 -0.5\nv 0.5 -0.5 -0.5\nv 0.5 0.5 -0.5\nv -0.5 0.5 -0.5\nv -0.5 -0.5 0.5\nv 0.5 -0.5 0.5
v 0.5 0.5 0.5\nv -0.5 0.5 0.5\nf 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 4 8 7\nf 4 7 3\nf 1 5 8
f 1 8 4\nf 2 3 7\nf 2 7 6\n"""  # unit cube, outward-facing triangles
SWAP = [0, 2, 1]  # ours <-> SPlisHSPlasH's axes (an involution)


def scene(job: dict, cube: str) -> dict:
    d = float(job["spacing"])
    lo, hi = np.asarray(job["tank_lo"], float)[SWAP], np.asarray(job["tank_hi"], float)[SWAP]
    flo, fhi = np.asarray(job["fluid_lo"], float)[SWAP], np.asarray(job["fluid_hi"], float)[SWAP]
    gap = job.get("wall_gap", 1.0) * d
    at_lo, at_hi = np.isclose(flo, lo), np.isclose(fhi, hi)
    # a block against a wall moves off it by the gap, or shrinks by it on both sides if against both walls
    flo, fhi = (np.where(at_lo, flo + gap, np.where(at_hi, flo - gap, flo)),
                np.where(at_hi, fhi - gap, np.where(at_lo, fhi + gap, fhi)))
    size = hi - lo
    cell = job.get("map_cell", 1.4) * d
    method = {"wcsph": 0, "dfsph": 4}[job["method"]]
    cfg = {"particleRadius": d / 2, "simulationMethod": method, "boundaryHandlingMethod": 2,
           "gravitation": [0, -9.81, 0], "timeStepSize": job.get("dt", 0.001), "cflMethod": job.get("cfl_method", 1),
           "cflFactor": job.get("cfl_factor", 1.0), "cflMaxTimeStepSize": job.get("dt_max", 0.005),
           "enableZSort": True, "enablePartioExport": False, "enableVTKExport": False,
           "enableRigidBodyExport": False, "enableStateExport": False,
           "WCSPH": {"stiffness": job.get("stiffness", 50000), "exponent": 7},
           "DFSPH": {"minIterations": 2, "maxIterations": 100, "maxError": job.get("max_error", 0.1),
                     "maxIterationsV": 100, "maxErrorV": job.get("max_error_v", 0.1), "enableDivergenceSolver": True}}
    return {"Configuration": cfg,
            "Materials": [{"id": "Fluid", "density0": 1000, "viscosityMethod": 1,
                           "Standard viscosity": {"viscosity": job.get("viscosity", 0.001) / 1000.0}}],
            "RigidBodies": [{"geometryFile": cube, "translation": list((lo + hi) / 2), "scale": list(size),
                             "isDynamic": False, "isWall": True, "mapInvert": True, "mapThickness": 0.0,
                             "mapResolution": [max(4, math.ceil(s / cell)) for s in size]}],
            "FluidBlocks": [{"denseMode": 0, "start": list(flo - d / 2), "end": list(fhi + d / 2),
                             "translation": [0, 0, 0], "scale": [1, 1, 1]}]}


def main() -> None:
    job = json.loads(open(sys.argv[1]).read())
    # cache_dir: a folder kept between jobs of the same tank and spacing, where SPlisHSPlasH caches its volume
    # maps (useCache): set-up is not timed, and building them took minutes on a busy machine
    tmp = job.get("cache_dir") or tempfile.mkdtemp(prefix="splish_")
    os.makedirs(tmp, exist_ok=True)
    cube = os.path.join(tmp, "cube.obj")
    with open(cube, "w") as f:
        f.write(CUBE)
    path = os.path.join(tmp, f"scene_{os.getpid()}.json")
    with open(path, "w") as f:
        json.dump(scene(job, cube), f)
    t0 = time.perf_counter()
    base = sph.Exec.SimulatorBase()
    base.init(sceneFile=path, useGui=False, outputDir=os.path.join(tmp, f"out_{os.getpid()}"),
              useCache=bool(job.get("cache_dir")), initialPause=False)
    base.initSimulation()
    t_init = time.perf_counter() - t0
    sim = sph.Simulation.getCurrent()
    tm = sph.TimeManager.getCurrent()
    fm = sim.getFluidModel(0)
    fps, stop = float(job.get("fps", 30)), float(job["stop"])
    frames_dir = job.get("frames_dir")
    if frames_dir:
        os.makedirs(frames_dir, exist_ok=True)
    state = {"next": 0, "sampling": [], "stamps": [], "t": [], "cpu": [], "cpu_sampling": []}
    rows = []

    def sample(k: int) -> None:
        n = fm.numActiveParticles()
        x = np.array(fm.getFieldBuffer("position"), copy=False)[:n][:, SWAP].astype(np.float64)
        rho = np.array(fm.getFieldBuffer("density"), copy=False)[:n].astype(np.float64)
        rows.append({"t": tm.getTime(), "density_error": float(np.maximum(rho / 1000.0 - 1.0, 0.0).mean()),
                     "extent_min": x.min(0).tolist(), "extent_max": x.max(0).tolist(),
                     "n_nan": int(np.isnan(x).sum())})
        if frames_dir:
            np.save(os.path.join(frames_dir, f"frame_{k:04d}.npy"), x.astype(np.float32))

    def on_step():
        now = time.perf_counter()
        state["stamps"].append(now)
        state["cpu"].append(time.process_time())
        state["t"].append(tm.getTime())
        while state["next"] * (1.0 / fps) <= tm.getTime() + 1e-9:
            sample(state["next"])
            state["next"] += 1
        state["sampling"].append(time.perf_counter() - now)
        state["cpu_sampling"].append(time.process_time() - state["cpu"][-1])

    sample(0)
    state["next"] = 1
    base.setValueFloat(base.STOP_AT, stop)
    base.setTimeStepCB(on_step)
    t1 = time.perf_counter()
    base.runSimulation()
    st = state["stamps"]
    # the first step includes deferredInit (volume maps): set-up, excluded, and so are the next few (up to 5,
    # a tenth of the run: the first ones after the maps were slow on a busy machine) and the sampling above
    # (each callback's sampling falls between its stamp and the next one)
    k = min(5, (len(st) - 1) // 10)
    wall = st[-1] - st[k] - sum(state["sampling"][k:-1])
    steps = len(st) - 1 - k
    cpu = state["cpu"][-1] - state["cpu"][k] - sum(state["cpu_sampling"][k:-1])
    simulated = state["t"][-1] - state["t"][k]
    res = {"method": job["method"], "particles": int(fm.numActiveParticles()), "steps": steps,
           "setup_s": t_init + (st[0] - t1), "warm_up_steps_excluded": k + 1, "wall_s": wall, "ms_per_step": 1e3 * wall / max(steps, 1),
           "cpu_ms_per_step": 1e3 * cpu / max(steps, 1), "cpu_s_per_simulated_s": cpu / simulated if simulated > 0 else None,
           "simulated_s": simulated, "mean_dt": simulated / max(steps, 1),
           "wall_s_per_simulated_s": wall / simulated if simulated > 0 else None, "frames": rows,
           "density_error_mean": float(np.mean([r["density_error"] for r in rows[1:]])) if len(rows) > 1 else None,
           "density_error_max": float(np.max([r["density_error"] for r in rows[1:]])) if len(rows) > 1 else None}
    print("RESULT " + json.dumps(res), flush=True)
    os._exit(0)  # skip the slow teardown


if __name__ == "__main__":
    main()
