"""How long the SPH wall map takes to build (walls.maps.BrickWallMaps): the demo's dam-break tank (a 3 x 2 x 1.2 m
box, l0 = 1/27 m, support 2 l0, the SDF at l0 / 2 with a 4 l0 margin), warm (numba compiled by a first build),
best of three, wall and CPU seconds. Writes benchmarks/results/wall_maps.json.

    .venv/bin/python benchmarks/bench_wall_maps.py
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.kernels import lattice_mass
from stages.simulate.walls.maps import BrickWallMaps

OUT = Path(__file__).resolve().parent / "results" / "wall_maps.json"


def main() -> None:
    l0, rho0 = 1.0 / 27.0, 1000.0
    h = 2.0 * l0
    lo, hi = np.array([-1.5, -1.0, 0.0]), np.array([1.5, 1.0, 1.2])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo - 4 * l0, hi + 4 * l0, 0.5 * l0)
    mass = lattice_mass(rho0, l0, h)
    BrickWallMaps(sdf, l0, h, mass, rho0)  # compile
    runs = []
    for _ in range(3):
        w, c = time.perf_counter(), time.process_time()
        maps = BrickWallMaps(sdf, l0, h, mass, rho0)
        runs.append((time.perf_counter() - w, time.process_time() - c))
    best = min(runs)
    res = {"sdf_nodes": list(sdf.dist.shape), "bricks": int(len(maps.bricks)), "wall_seconds": round(best[0], 3),
           "cpu_seconds": round(best[1], 3)}
    print(f"wall map: SDF {sdf.dist.shape}, {len(maps.bricks)} bricks: {best[0]:.2f} s wall, {best[1]:.2f} s CPU")
    OUT.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
