"""The seed paper's table: about 20,000 particles poured onto the dragon, the Buddha and the gargoyle.

    .venv/bin/python benchmarks/bench_walls.py [--solver sph] [--frames 31] [--models dragon,buddha,gargoyle]

Runs configs/seed_<model>.yaml through the pipeline (its own cache in benchmarks/.cache, so a re-run
only reports), and per model prints: fluid particles, time per step, steps, wall seconds per simulated
second, particles that ever ended inside a wall (SDF < -0.01 l0) or left the domain, and the number of
wall particles a particle boundary would have needed: lattice points at the particle spacing l0 inside
the walls within the kernel support h of their surface (-h <= d < 0), split into the model's and the
tank's (by the closest triangle). This method needs none of them. Harada et al. 2007 (2007 hardware):
309 / 281 / 297 ms per step (gargoyle / dragon / Buddha) and 26,688 / 18,582 / 12,084 wall particles.
The gargoyle is read from ../shared/assets (not redistributable); it is skipped where that is missing.
Writes benchmarks/results/walls.json.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import pipeline
from stages.common.formats import WallMesh
from stages.common.sdf import SDFGrid

ROOT = Path(__file__).resolve().parents[1]
PAPER = {"gargoyle": (309, 26688), "dragon": (281, 18582), "buddha": (297, 12084)}


def wall_particle_count(sdf: SDFGrid, walls: WallMesh, l0: float, h: float) -> dict:
    """Lattice points (spacing l0) inside the walls within h of their surface, by closest wall."""
    import open3d as o3d

    axes = [np.arange(sdf.origin[a] + 0.5 * l0, sdf.upper[a], l0) for a in range(3)]
    counts = {"model": 0, "tank": 0}
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(walls.vertices.astype(np.float32)), o3d.core.Tensor(walls.faces.astype(np.uint32)))
    for z in axes[2]:  # slab by slab: bounded memory
        X, Y = np.meshgrid(axes[0], axes[1], indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
        d, _ = sdf.sample(pts)
        shell = pts[(d < 0) & (d >= -h)]
        if len(shell) == 0:
            continue
        tri = scene.compute_closest_points(o3d.core.Tensor(shell.astype(np.float32)))["primitive_ids"].numpy()
        is_model = walls.wall_id[tri] > 0
        counts["model"] += int(is_model.sum())
        counts["tank"] += int((~is_model).sum())
    return counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solver", default="sph", help="simulate implementation (sph, dfsph, mps)")
    ap.add_argument("--frames", type=int, default=31, help="output frames at 30 fps (31 = 1 s)")
    ap.add_argument("--models", default="dragon,buddha,gargoyle")
    args = ap.parse_args()
    rows = []
    for model in args.models.split(","):
        config = ROOT / "configs" / f"seed_{model}.yaml"
        try:
            report = pipeline.run(config, overrides=(f"simulate.use={args.solver}", f"scene.frames.count={args.frames}",
                                                     "outputs=[particles, sdf, walls]"),
                                  cache_dir=ROOT / "benchmarks" / ".cache", out_dir=ROOT / "out" / f"bench_{model}",
                                  progress=True)
        except pipeline.PipelineError as e:  # e.g. the gargoyle where ../shared is missing
            if e.exit_code != 2:
                raise
            print(f"{model}: skipped ({e})")
            continue
        meta = json.loads((Path(report.outputs["particles"]) / "meta.json").read_text())
        st = meta["stats"]
        sdf = SDFGrid.load(Path(report.outputs["sdf"]))
        walls = WallMesh.load(Path(report.outputs["walls"]))
        wp = wall_particle_count(sdf, walls, meta["spacing"], meta["support"])
        paper_ms, paper_wp = PAPER[model]
        rows.append({"model": model, "solver": args.solver, "particles": st["particles"],
                     "ms_per_step": st["summary"]["ms_per_step"], "steps": st["steps"],
                     "wall_s_per_sim_s": st["summary"]["wall_seconds_per_simulated_second"],
                     "inside_wall_max": st["summary"]["inside_wall_max"], "left_domain": st["left_domain"],
                     "density_error_mean": st["summary"]["density_error_mean"],
                     "wall_particles_model": wp["model"], "wall_particles_tank": wp["tank"],
                     "paper_ms_per_step": paper_ms, "paper_wall_particles": paper_wp,
                     "sdf_seconds": report.stage("sdf_bake").seconds})
    print(f"{'model':9s} {'N':>6s} {'ms/step':>8s} {'paper':>6s} {'inside':>6s} {'left':>5s} "
          f"{'wall particles (model + tank)':>30s} {'paper':>6s}")
    for r in rows:
        print(f"{r['model']:9s} {r['particles']:6d} {r['ms_per_step']:8.1f} {r['paper_ms_per_step']:6d} "
              f"{r['inside_wall_max']:6d} {r['left_domain']:5d} "
              f"{r['wall_particles_model']:>14d} + {r['wall_particles_tank']:<13d} {r['paper_wall_particles']:6d}")
    out = ROOT / "benchmarks" / "results" / "walls.json"
    out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
