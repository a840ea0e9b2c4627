"""SPlisHSPlasH DFSPH on bench_rest.py's resting tank, headless (PEERS.md): a 0.3 x 0.2 m tank filled
0.25 m deep, particle radius 6.25 mm (1.25 cm spacing), volume maps, CFL steps (factor 0.5, at most
5 ms), water's viscosity (nu = 1e-6 m^2/s, mu = 0.001 Pa s), its own lattice start. Prints one JSON line: the mean and 99th percentile
speed at 0.5, 1, 1.5 and 3 s (up to STOP_AT). Run by bench_rest.py with
LD_PRELOAD=/lib/x86_64-linux-gnu/libGLdispatch.so.0 (the wheel's GL libraries clash otherwise)."""
import json
import os
import sys
import tempfile
import time

import numpy as np
import pysplishsplash as sph

TIMES = (0.5, 1.0, 1.5, 3.0)
# SPlisHSPlasH's standard viscosity takes the kinematic viscosity nu, m^2/s: water's is mu / rho = 1e-6
# (0.001 here, as before session 14, was 1,000 x water's)
NU = float(os.environ.get("NU", "1e-6"))
CUBE = """v -0.5 -0.5 -0.5\nv 0.5 -0.5 -0.5\nv 0.5 0.5 -0.5\nv -0.5 0.5 -0.5\nv -0.5 -0.5 0.5\nv 0.5 -0.5 0.5
v 0.5 0.5 0.5\nv -0.5 0.5 0.5\nf 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 4 8 7\nf 4 7 3\nf 1 5 8
f 1 8 4\nf 2 3 7\nf 2 7 6\n"""  # unit cube, outward-facing triangles


def scene(cube: str) -> dict:
    # y up: the tank is x 0.3, z 0.2, 0.35 tall; the fluid fills it 0.25 deep
    return {
        "Configuration": {"particleRadius": 0.00625, "simulationMethod": 4, "boundaryHandlingMethod": 2,
                          "gravitation": [0, -9.81, 0], "timeStepSize": 0.001, "cflMethod": 1, "cflFactor": 0.5,
                          "cflMaxTimeStepSize": 0.005, "enableZSort": True, "enablePartioExport": False,
                          "enableVTKExport": False, "enableRigidBodyExport": False, "enableStateExport": False,
                          "DFSPH": {"minIterations": 2, "maxIterations": 100, "maxError": 0.05, "maxIterationsV": 100,
                                    "maxErrorV": 0.1, "enableDivergenceSolver": True}},
        "Materials": [{"id": "Fluid", "density0": 1000, "viscosityMethod": 1,
                       "Standard viscosity": {"viscosity": NU}}],
        "RigidBodies": [{"geometryFile": cube, "translation": [0.15, 0.175, 0.1], "scale": [0.3, 0.35, 0.2],
                         "isDynamic": False, "isWall": True, "mapInvert": True, "mapThickness": 0.0,
                         "mapResolution": [30, 35, 20]}],
        "FluidBlocks": [{"denseMode": 0, "start": [0.0, 0.0, 0.0], "end": [0.3, 0.25, 0.2],
                         "translation": [0, 0, 0], "scale": [1, 1, 1]}],
    }


def main() -> None:
    stop = float(os.environ.get("STOP_AT", "3.0"))
    tmp = tempfile.mkdtemp(prefix="splish_rest_")
    cube = os.path.join(tmp, "cube.obj")
    with open(cube, "w") as f:
        f.write(CUBE)
    path = os.path.join(tmp, "rest.json")
    with open(path, "w") as f:
        json.dump(scene(cube), f)
    base = sph.Exec.SimulatorBase()
    base.init(sceneFile=path, useGui=False, outputDir=os.path.join(tmp, "out"), useCache=False, initialPause=False)
    base.initSimulation()
    sim = sph.Simulation.getCurrent()
    tm = sph.TimeManager.getCurrent()
    fm = sim.getFluidModel(0)
    rows = []
    todo = [t for t in TIMES if t <= stop + 1e-9]
    steps = [0]

    def on_step():
        steps[0] += 1
        if todo and tm.getTime() >= todo[0] - 1e-9:
            n = fm.numActiveParticles()
            v = np.array([fm.getVelocity(i) for i in range(n)], dtype=np.float64)
            sp = np.linalg.norm(v, axis=1)
            rows.append({"t": round(tm.getTime(), 4), "mean": float(sp.mean()), "p99": float(np.percentile(sp, 99)),
                         "max": float(sp.max()), "steps": steps[0]})
            todo.pop(0)

    base.setValueFloat(base.STOP_AT, stop + 0.003)
    base.setTimeStepCB(on_step)
    t0 = time.perf_counter()
    base.runSimulation()
    print(json.dumps({"particles": int(fm.numActiveParticles()), "rows": rows,
                      "wall_seconds": time.perf_counter() - t0}), flush=True)
    sys.stdout.flush()
    os._exit(0)  # skip the slow teardown


if __name__ == "__main__":
    main()
