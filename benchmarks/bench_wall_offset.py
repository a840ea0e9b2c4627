"""A flat wall off the wall map's grid (issue 17): the first row's density beside a floor that lies on the
map's nodes and a quarter of a node spacing off them, for both WCSPH kernels and for MPS.

    .venv/bin/python benchmarks/bench_wall_offset.py

The wall maps hold the wall's density terms at nodes l0 / 2 apart and interpolate them trilinearly; the flat
wall's density profile is curved, so between nodes the interpolation reads it too high. A 10-row lattice over
a floor, the SDF's origin shifted under it; the first row's density (in rho0) of a particle away from the side
walls, and MPS's number density over n0 there. Writes benchmarks/results/wall_offset.json."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages.common.sdf import box_interior_sdf, grid_from_function  # noqa: E402
from stages.simulate.emitters import lattice  # noqa: E402
from stages.simulate.sph import SPHParams, SPHSolver  # noqa: E402

L0 = 0.004


def floor_lattice(cell: float, shift: float) -> tuple:
    """(SDF, lattice): a 10-row lattice over a floor whose SDF of ``cell`` l0 has its nodes ``shift`` l0 off the
    floor's (grid_from_function pads the box by one cell)."""
    lo, hi = np.zeros(3), np.array([0.4, 0.02, 0.04])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo - shift * L0, hi, cell * L0)
    return sdf, lattice([0.0, 0.0, 0.0], [0.1, 0.02, 10 * L0], L0)


def first_particle(x: np.ndarray) -> int:
    """A first-row particle away from the side walls."""
    return int(np.argmin(np.linalg.norm(x - np.array([5.5, 2.5, 0.5]) * L0, axis=1)))


def first_row(cell: float, shift: float, kernel: str) -> float:
    """The first row's density over rho0 (WCSPH with ``kernel``)."""
    sdf, x = floor_lattice(cell, shift)
    s = SPHSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0,
                  params=SPHParams(kernel=kernel, sound_speed=2.0))
    s.sort_and_density(rebuild=True)
    return float(s.rho[first_particle(s.x)] / 1000.0)


def first_row_mps(cell: float, shift: float) -> float:
    """MPS's first row over the same floor: its number density over n0 (walls/mps.py's maps of the SDF distance)."""
    from stages.simulate.mps import MPSParams, MPSSolver
    sdf, x = floor_lattice(cell, shift)
    s = MPSSolver(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=L0, rho0=1000.0, params=MPSParams())
    s.sort_and_neighbours()
    s.number_density(s.x)
    return float(s.n[first_particle(s.x)] / s.n0)


def main() -> None:
    rows = []
    for cell, shift in ((0.5, 0.0), (0.25, 0.0), (0.25, 0.25), (0.5, 0.25)):
        offset = (cell + shift) % 0.5  # the floor's distance from the map's nearest node plane, in l0
        row = {"sdf_cell_l0": cell, "floor_off_map_nodes_l0": offset,
               **{k: first_row(cell, shift, k) for k in ("poly6_spiky", "spline")}, "mps": first_row_mps(cell, shift)}
        rows.append(row)
        print(f"SDF cell {cell} l0, floor {offset:.2f} l0 off the map's nodes: first row "
              f"{row['poly6_spiky']:.4f} rho0 (Poly6/Spiky), {row['spline']:.4f} (spline), "
              f"MPS n/n0 {row['mps']:.4f}", flush=True)
    (ROOT / "benchmarks" / "results" / "wall_offset.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
