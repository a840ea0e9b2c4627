"""Inside/outside of solid walls: the generalized winding number (libigl's fast approximation, Barill
et al. 2018) against the grid-line parity vote (mesh_distance.inside_votes, open3d rays on ties).

Run: ``python benchmarks/bench_sign.py [--size 128] [--models NAME ...] [--ref-rays 31]``.
Each model of ../shared/assets (read in place, never copied) is cleaned as mesh_import does and baked
as a solid obstacle on a grid about ``size`` nodes along its longest side (cell 0.5 l0, band 4 l0: the
stage defaults) once with each sign. Reference: the majority of ``ref-rays`` random-direction ray
parities (open3d) at every band node farther than half a grid spacing from the mesh, and at up to
20,000 nodes beyond the band (a parity reference: like the parity vote it calls the overlap of two
interpenetrating closed parts outside); for the synthetic overlapping spheres, the exact union. A sign error is a node whose baked sign differs from the reference.
Times: the sign's share of the bake (numba kernels loaded first). Writes
benchmarks/results/sign.json and prints a Markdown table.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from stages.common.formats import WallMesh
from stages.mesh_import.cleanup import clean_mesh
from stages.sdf_bake.open3d_bake import bake

ROOT = Path(__file__).resolve().parents[1]
ASSETS = next((p / "shared" / "assets" for p in ROOT.parents if (p / "shared" / "assets").is_dir()),
              ROOT.parent / "shared" / "assets")  # ../shared beside the repository (or a worktree's parents)
MODELS = {  # name: (path under ASSETS, what it is)
    "dragon_50k": ("dragon/Dragon_50k.obj", "not watertight: 21 components, 16 non-manifold edges, duplicates"),
    "happy_buddha_100k": ("happy_buddha/happy_buddha_100k.obj", "not watertight: 36 components, 50 non-manifold edges"),
    "bunny_zipper_69k": ("bunny/stanford_bunny_zipper_69k.obj", "5 holes (223 boundary edges)"),
    "bunny_closed_60k": ("bunny/bunny_closed_60k.obj", "watertight"),
    "dragon_100k_watertight": ("dragon/dragon_100k_watertight.obj", "watertight, genus 1"),
    "armadillo_50k": ("armadillo/armadillo_50k.obj", "watertight"),
    "two_spheres_overlapping": (None, "synthetic: two closed spheres that intersect (overlapping parts), analytic reference"),
}
SPHERES = ((np.array([-0.2, 0.0, 0.0]), 0.5), (np.array([0.2, 0.05, 0.0]), 0.5))


def overlapping_spheres() -> trimesh.Trimesh:
    """Two closed icospheres that intersect, as one triangle soup (a model built of interpenetrating
    parts): inside is their union."""
    parts = [trimesh.creation.icosphere(subdivisions=4, radius=r).apply_translation(c) for c, r in SPHERES]
    return trimesh.util.concatenate(parts)


def reference_inside(tri: np.ndarray, pts: np.ndarray, rays: int, seed: int = 7) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(tri.reshape(-1, 3).astype(np.float32)),
                        o3d.core.Tensor(np.arange(3 * len(tri), dtype=np.uint32).reshape(-1, 3)))
    dirs = np.random.default_rng(seed).normal(size=(rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    votes = np.zeros(len(pts), np.int32)
    p32 = pts.astype(np.float32)
    for d in dirs:
        r = np.concatenate([p32, np.broadcast_to(d.astype(np.float32), p32.shape)], axis=1)
        votes += scene.count_intersections(o3d.core.Tensor(r)).numpy() % 2
    return 2 * votes > rays


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--models", nargs="+", default=list(MODELS))
    ap.add_argument("--ref-rays", type=int, default=31)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sign.json")
    args = ap.parse_args()

    tiny = WallMesh(np.eye(3), np.array([[0, 1, 2]], np.int32), np.zeros(1, np.int32), [{"name": "t", "fluid": "outside"}])
    for sign in ("parity", "winding"):  # load the kernels
        bake(tiny, np.full(3, -1.0), np.full(3, 1.0), 0.25, 0.5, sign=sign)
    rows = []
    for name in args.models:
        path = MODELS[name][0]
        raw = overlapping_spheres() if path is None else trimesh.load(str(ASSETS / path), force="mesh", process=False)
        mesh, report = clean_mesh(raw, 1e-7 * float(np.linalg.norm(raw.extents)))
        wm = WallMesh(np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int32), np.zeros(len(mesh.faces), np.int32),
                      [{"name": name, "fluid": "outside", "report": report}])
        lo, hi = mesh.bounds
        h = float((hi - lo).max()) / (args.size - 17)
        band = 8 * h
        lo, hi = lo - 8.5 * h, hi + 8.5 * h
        grids, times = {}, {}
        for sign in ("parity", "winding"):
            t0 = time.perf_counter()
            grid, stats = bake(wm, lo, hi, h, band, sign=sign)
            times[sign] = {"bake_s": time.perf_counter() - t0, "sign_s": stats["sign_seconds"]}
            grids[sign] = grid.dist
        shape = grids["parity"].shape
        d = np.abs(grids["winding"]).reshape(-1)  # same magnitudes either way
        near = np.flatnonzero((d < band) & (d > 0.5 * h))
        far = np.flatnonzero(d >= band)
        far = np.random.default_rng(0).choice(far, min(len(far), 20000), replace=False)
        idx = np.concatenate([near, far])
        pts = lo + h * np.stack(np.unravel_index(idx, shape), axis=1)
        t0 = time.perf_counter()
        if path is None:
            ref = np.any([np.linalg.norm(pts - c, axis=1) < r for c, r in SPHERES], axis=0)
        else:
            ref = reference_inside(np.asarray(mesh.vertices)[np.asarray(mesh.faces)], pts, args.ref_rays)
        ref_s = time.perf_counter() - t0
        row = {"model": name, "what": MODELS[name][1], "faces": int(len(mesh.faces)), "watertight": report["watertight"],
               "grid": list(shape), "band_nodes_checked": int(len(near)), "far_nodes_checked": int(len(far)),
               "reference_seconds": ref_s}
        for sign in ("parity", "winding"):
            inside = grids[sign].reshape(-1)[idx] < 0
            wrong = inside != ref
            row[sign] = {**times[sign], "sign_errors_band": int(wrong[:len(near)].sum()),
                         "sign_errors_far": int(wrong[len(near):].sum())}
        rows.append(row)
        print(json.dumps(row), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "size": args.size, "ref_rays": args.ref_rays,
                                    "rows": rows}, indent=2))
    print("\n| model | faces | watertight | band nodes | parity: sign errors (band / far), sign s | "
          "winding: sign errors (band / far), sign s |\n|---|---|---|---|---|---|")
    for r in rows:
        p, w = r["parity"], r["winding"]
        print(f"| {r['model']} ({r['what']}) | {r['faces']:,} | {'yes' if r['watertight'] else 'no'} | "
              f"{r['band_nodes_checked']:,} | {p['sign_errors_band']} / {p['sign_errors_far']}, {p['sign_s']:.2f} | "
              f"{w['sign_errors_band']} / {w['sign_errors_far']}, {w['sign_s']:.2f} |")


if __name__ == "__main__":
    main()
