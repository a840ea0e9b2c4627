"""What shells changed in the seed scenes' SDFs: each config baked with the defaults (thin parts of
watertight solids thickened to the least leak-free thickness) and with ``sdf_bake.min_thickness=0``
(the bake before shells), node by node.

Run: ``python benchmarks/check_sdf_unchanged.py`` (caches in /tmp/sdf_unchanged). Prints one line per
scene: grid, changed nodes, largest change in grid spacings.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

import pipeline
from pipeline import Registry

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
CASES = [("dam_break.yaml", ()), ("dragon.yaml", ()), ("seed_dragon.yaml", ()), ("seed_buddha.yaml", ()),
         ("seed_dragon.yaml", ("walls.1.file=assets/bunny_closed_6k.obj",)),
         ("seed_dragon.yaml", ("walls.1.file=assets/armadillo_29k_remeshed.obj",))]


def main() -> None:
    registry = Registry.from_entry_points()
    for config, sets in CASES:
        dist = {}
        for extra in ((), ("sdf_bake.min_thickness=0",)):
            report = pipeline.run(CONFIGS / config, registry=registry, overrides=sets + ("outputs=[sdf]",) + extra,
                                  cache_dir=Path("/tmp/sdf_unchanged/cache"), out_dir=Path("/tmp/sdf_unchanged/out"))
            with np.load(Path(report.outputs["sdf"]) / "sdf.npz") as z:
                dist[extra], h = z["dist"].copy(), float(z["spacing"])
        d = dist[()] - dist[("sdf_bake.min_thickness=0",)]
        print(f"{config} {' '.join(sets)}: grid {d.shape}, changed nodes {int((d != 0).sum())}, "
              f"largest change {float(np.abs(d).max()) / h:.3f} spacings", flush=True)


if __name__ == "__main__":
    main()
