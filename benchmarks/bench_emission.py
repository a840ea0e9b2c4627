"""What the emitters' wall-band packing costs and what it holds (emitters._fill_wall_band).

Run: ``python benchmarks/bench_emission.py [--spacings 0.025,0.0125,0.00625] [--big]``.
Three tanks filled 0.2 m deep, their walls off the lattice: a cylinder of radius 0.12 m, a hemispherical bowl of
radius 0.15 m and a 0.2 m box turned 30 degrees (tests/test_emission.py's TANKS, imported). For each spacing: the
particles, the band re-packed (within 2.5 l0 of a wall), the water held (N l0^3 / V), the closest pair, and the time
of drop_inside_walls (the packing and the rest of the wall checks; numba compiled first). ``--big`` adds a cylinder
of radius 0.3 m at 0.5 cm (about 900,000 particles). Writes benchmarks/results/emission.json and prints a Markdown
table.
"""
from __future__ import annotations

import argparse
import json
import logging
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from stages.common.sdf import grid_from_function  # noqa: E402
from stages.simulate.emitters import FILL_BAND, drop_inside_walls, lattice  # noqa: E402
from test_emission import FILL, TANKS  # noqa: E402  (the tests' tanks: the same figures)

RESULTS = Path(__file__).resolve().parent / "results"


def _big_cylinder(p):  # radius 0.3 m about the origin
    return np.minimum(np.minimum(0.3 - np.hypot(p[:, 0], p[:, 1]), p[:, 2]), 0.35 - p[:, 2])


def measure(name, fn, box, volume, l0) -> dict:
    lo, hi = (np.asarray(b, float) for b in box)
    sdf = grid_from_function(fn, lo, hi, 0.5 * l0)
    pts = lattice(lo, [hi[0], hi[1], FILL], l0)
    quiet = logging.getLogger("bench_emission")
    quiet.setLevel(logging.ERROR)
    t = time.perf_counter()
    x, _, _ = drop_inside_walls(pts, np.zeros_like(pts), sdf, l0, quiet)
    seconds = time.perf_counter() - t
    d, _ = sdf.sample(x)
    closest = cKDTree(x).query(x, k=2)[0][:, 1].min() / l0
    return {"tank": name, "spacing": l0, "particles": len(x), "band": int((d < FILL_BAND * l0).sum()),
            "held": len(x) * l0 ** 3 / volume, "closest_pair_l0": float(closest), "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", default="0.025,0.0125,0.00625")
    ap.add_argument("--big", action="store_true", help="also a cylinder of radius 0.3 m at 0.5 cm (~900k particles)")
    args = ap.parse_args()
    measure("warm-up", *TANKS["cylinder"], 0.025)  # numba compiles the kernel sums
    rows = [measure(name, *TANKS[name], float(l0)) for l0 in args.spacings.split(",") for name in TANKS]
    if args.big:
        rows.append(measure("cylinder r 0.3 m", _big_cylinder, ([-0.31, -0.31, 0], [0.31, 0.31, 0.35]),
                            np.pi * 0.3 ** 2 * FILL, 0.005))
    print("| tank | spacing, cm | particles | band | held | closest pair, l0 | s | ms per band particle |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['tank']} | {100 * r['spacing']:g} | {r['particles']} | {r['band']} | {r['held']:.3f} | "
              f"{r['closest_pair_l0']:.2f} | {r['seconds']:.2f} | {1000 * r['seconds'] / max(r['band'], 1):.3f} |")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "emission.json").write_text(json.dumps({"machine": platform.node(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
