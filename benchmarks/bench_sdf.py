"""Benchmark of sdf_bake.open3d on the Stanford dragon: narrow-band bake vs dense open3d, and accuracy.

Run: ``python benchmarks/bench_sdf.py [--sizes 128 256] [--dense-max 256] [--band-cells 8] [--exact-reach 4]``.
For each box size N the node spacing is chosen so the dragon's padded bounding box is about N nodes
long; the particle spacing is l0 = 2 h (cell = 0.5) and the band 4 l0 = 8 h (the stage defaults).
A tiny bake first loads the numba kernels (cache), so the times are of the bake alone. Node values are
compared with open3d's dense compute_signed_distance (magnitudes: its sign is one ray) and sampled
(trilinear) values with the exact distance at random band points (open3d closest points, sign by
7-ray voting). Prints a table and writes benchmarks/results/sdf.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from stages.common.formats import WallMesh
from stages.mesh_import.cleanup import clean_mesh
from stages.sdf_bake.open3d_bake import accuracy, bake, wall_fields

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = ROOT.parent / "shared" / "assets" / "dragon" / "Dragon_50k.obj"
if not DEFAULT_MODEL.is_file():
    DEFAULT_MODEL = ROOT / "configs" / "assets" / "Dragon_50k.obj"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--dense-max", type=int, default=256, help="run the dense open3d comparison up to this size")
    ap.add_argument("--points", type=int, default=20000, help="random band points for the accuracy figures")
    ap.add_argument("--band-cells", type=float, default=8.0, help="band half width in grid spacings (8 = 4 l0 at cell 0.5)")
    ap.add_argument("--exact-reach", type=float, default=4.0, help="brute-force reach in grid spacings (stage default 4)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sdf.json")
    args = ap.parse_args()

    raw = trimesh.load(str(args.model), force="mesh", process=False)
    diag = float(np.linalg.norm(raw.extents))
    mesh, report = clean_mesh(raw, 1e-7 * diag)
    wm = WallMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int32), np.zeros(len(mesh.faces), np.int32),
                  [{"name": "dragon", "fluid": "outside", "report": report}])
    lo, hi = mesh.bounds
    h0 = float((hi - lo).max()) / 30
    bake(wm, lo - 10 * h0, hi + 10 * h0, h0, 8 * h0, args.exact_reach)  # load the numba kernels
    rows = []
    for n in args.sizes:
        cell_band = args.band_cells
        h = float((hi - lo).max()) / (n - 1 - 2 * (int(np.ceil(cell_band)) + 2))
        pad = (int(np.ceil(cell_band)) + 2) * h
        cpu0 = time.process_time()
        grid, stats = bake(wm, lo - pad, hi + pad, h, cell_band * h, args.exact_reach, 7)
        cpu = time.process_time() - cpu0
        acc = accuracy(grid, wall_fields(wm, 7), wm, n_points=args.points)
        row = {"size": n, "shape": stats["shape"], "spacing": h, "band_cells": cell_band, "exact_reach_cells": args.exact_reach,
               "bake_seconds": stats["seconds"], "bake_cpu_seconds": cpu, "distance_seconds": stats["distance_seconds"],
               "sign_seconds": stats["sign_seconds"], "exact_nodes": stats["exact_nodes"],
               "propagated_nodes": stats["propagated_nodes"], "sign_ties": stats["sign_ties"], "nodes": stats["nodes"], **acc}
        if n <= args.dense_max:
            axes = [grid.origin[a] + h * np.arange(grid.shape[a]) for a in range(3)]
            pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).astype(np.float32)
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(wm.vertices.astype(np.float32)), o3d.core.Tensor(wm.faces.astype(np.uint32)))
            t0 = time.perf_counter()
            dense = scene.compute_signed_distance(o3d.core.Tensor(pts)).numpy()
            row["dense_seconds"] = time.perf_counter() - t0
            inband = np.abs(dense) < grid.band
            # open3d's sign is -inside (one ray); ours +outside for an obstacle: compare magnitudes and signs
            diff = (np.abs(grid.dist[inband]) - np.abs(dense[inband])) / h
            row["dense_max_abs_diff_cells"] = float(np.abs(diff).max())
            row["dense_rms_diff_cells"] = float(np.sqrt(np.mean(diff ** 2)))
            row["dense_nodes_off_1e-3_cells"] = float(np.mean(np.abs(diff) > 1e-3))
            row["dense_sign_disagreement"] = float(np.mean(np.sign(grid.dist) != np.sign(dense)))
            del pts, dense
        rows.append(row)
        print(f"{n}^3 done: {row['bake_seconds']:.2f} s", flush=True)

    print(f"\nmodel {args.model.name}: {len(wm.faces)} triangles, watertight={report['watertight']}; "
          f"{os.cpu_count()} cpus, {platform.processor() or platform.machine()}")
    head = ("box", "nodes", "band n.", "bake s", "cpu s", "dist s", "sign s", "dense s", "node err", "max err", "rms err",
            "p99 err", "sign err")
    print(" | ".join(f"{h:>9}" for h in head))
    for r in rows:
        vals = ("x".join(map(str, r["shape"])), f"{r['nodes']:,}", f"{r['exact_nodes'] + r['propagated_nodes']:,}",
                f"{r['bake_seconds']:.2f}", f"{r['bake_cpu_seconds']:.2f}", f"{r['distance_seconds']:.2f}", f"{r['sign_seconds']:.2f}",
                f"{r['dense_seconds']:.2f}" if "dense_seconds" in r else "-",
                f"{r['dense_max_abs_diff_cells']:.3f}" if "dense_seconds" in r else "-", f"{r['max_error_cells']:.3f}",
                f"{r['rms_error_cells']:.4f}", f"{r['p99_error_cells']:.3f}", str(r["sign_errors"]))
        print(" | ".join(f"{v:>9}" for v in vals))
    print("node err: max | |d| - |open3d dense| | over band nodes; errors: |trilinear sample - exact| at random band "
          "points; all in grid spacings. cpu s: process CPU time of the bake (both threads)")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"model": str(args.model.name), "triangles": int(len(wm.faces)), "cpus": os.cpu_count(),
                                    "watertight": bool(report["watertight"]), "load_average_at_end": os.getloadavg(),
                                    "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
