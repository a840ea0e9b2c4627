"""Surface extraction per frame, ours against splashsurf in the same run, plus wall snapping.

    .venv/bin/python benchmarks/bench_surface.py [--repeats 3] [--small]

Particle sets (particle radius r, spacing l0 = 2 r, positions as float32 for both tools):
  block_20k / block_100k : 27^3 / 46^3 particles on a jittered lattice (+-0.1 l0, seed 0): a compact
                           block whose whole outside is free surface (as ../shared/peers/bench_surf.py);
  splash_20k / splash_100k: a fluid layer on a floor plus a spray cloud above it (droplets of 4-40
                           particles and single particles, seed 1), a stand-in for a dam break's splash.
Equal resolution: splashsurf with its peers settings (smoothing length 2.0 r, i.e. compact support
4 r = 2 l0, cubic spline; cube size 0.5 r; iso 0.6; no post-processing); ours with its defaults (Poly6
of support 1.7 l0, whose width, the rms distance along an axis 0.51 l0, is within 7 % of splashsurf's
kernel's 0.55 l0; particle volumes by SPH summation as splashsurf's; iso 0.63), cell 0.25 l0 (= 0.5 r),
no smoothing. Our default cell (0.5 l0) and our anisotropic option (cell 0.25 l0) are timed as well.
Each time is the median of ``repeats`` calls after one warm-up call. Both use 2 threads (numba; rayon).
Volume: enclosed volume of the closed mesh / (N l0^3). Closed: count of boundary edges (0 = closed).
Wall snap: a fluid block resting in a box tank (analytic SDF on a 0.5 l0 grid, exact finish on the
tank's mesh); the share of snapped vertices on the wall to 1e-3 l0 (exact distance), and the time.
Writes benchmarks/results/surface.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("RAYON_NUM_THREADS", "2")
os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import numpy as np  # noqa: E402

from stages.common.formats import WallMesh  # noqa: E402
from stages.common.meshes import boundary_edge_count, signed_volume  # noqa: E402
from stages.common.sdf import box_interior_sdf, grid_from_function  # noqa: E402
from stages.surface_extract.marching_cubes import MarchingCubesParams, extract  # noqa: E402
from stages.wall_snap.distance import DistanceSnapParams, snap_mesh  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "surface.json"
R_PARTICLE = 0.01
L0 = 2 * R_PARTICLE


def jittered_lattice(counts, origin, rng) -> np.ndarray:
    g = np.stack(np.meshgrid(*[np.arange(c) * L0 for c in counts], indexing="ij"), -1).reshape(-1, 3)
    return g + np.asarray(origin) + rng.uniform(-0.1 * L0, 0.1 * L0, g.shape)


def block(n: int) -> np.ndarray:
    return jittered_lattice((n, n, n), (0, 0, 0), np.random.default_rng(0))


def splash(n_total: int) -> np.ndarray:
    """A layer of fluid on a floor (75 %) and, above it, droplets (15 %) and single drops (10 %)."""
    rng = np.random.default_rng(1)
    n_layer = int(0.75 * n_total)
    side = int(round((n_layer / 12) ** 0.5))
    layer = jittered_lattice((side, side, 12), (0, 0, 0), rng)
    w = side * L0
    parts = [layer]
    n_drops = int(0.15 * n_total)
    made = 0
    while made < n_drops:  # droplets: small jittered balls in a cloud up to 2.5 layer widths high
        radius = rng.uniform(0.8, 2.2) * L0
        c = rng.uniform((-0.2 * w, -0.2 * w, 14 * L0), (1.2 * w, 1.2 * w, 0.6 * w))
        k = int(np.ceil(radius / L0)) + 1
        ball = jittered_lattice((2 * k + 1,) * 3, c - k * L0, rng)
        ball = ball[np.linalg.norm(ball - c, axis=1) <= radius]
        parts.append(ball)
        made += len(ball)
    n_single = n_total - sum(len(p) for p in parts)
    parts.append(rng.uniform((-0.3 * w, -0.3 * w, 12 * L0), (1.3 * w, 1.3 * w, 0.7 * w), (max(n_single, 0), 3)))
    return np.concatenate(parts)[:n_total]


def timed(fn, repeats: int):
    fn()  # warm-up (numba cache load, page faults)
    ts, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts), out


def ours(x: np.ndarray, cell: float, repeats: int, anisotropic: bool = False) -> dict:
    params = MarchingCubesParams(cell=cell, anisotropic=anisotropic)
    vol = np.full(len(x), L0 ** 3)
    timings: dict = {}
    t, mesh = timed(lambda: extract(x, vol, L0, params, timings=timings), repeats)
    v = mesh.vertices.astype(np.float64)
    return {"s_per_frame": round(t, 4), "triangles": int(len(mesh.faces)),
            "boundary_edges": boundary_edge_count(mesh.faces),
            "volume_ratio": round(signed_volume(v, mesh.faces) / (len(x) * L0 ** 3), 4),
            "split_s": {k: round(s, 4) for k, s in timings.items()}}


def splashsurf(x: np.ndarray, repeats: int) -> dict:
    import pysplashsurf as ps

    xf = np.ascontiguousarray(x, np.float32)
    t, res = timed(lambda: ps.reconstruction_pipeline(xf, particle_radius=R_PARTICLE, smoothing_length=2.0,
                                                      cube_size=0.5, iso_surface_threshold=0.6,
                                                      rest_density=1000.0), repeats)
    mesh = res.mesh if hasattr(res, "mesh") else res[0].mesh
    v = np.asarray(mesh.vertices, np.float64)
    f = np.ascontiguousarray(np.asarray(mesh.triangles), dtype=np.int64)
    return {"s_per_frame": round(t, 4), "triangles": int(len(f)), "boundary_edges": boundary_edge_count(f),
            "volume_ratio": round(signed_volume(v, f) / (len(x) * L0 ** 3), 4)}


def wall_snap_case(repeats: int) -> dict:
    """A 30 x 30 x 15 l0 block filling the floor of a 30 x 30 x 30 l0 box tank; the SDF and the tank's
    mesh (for the exact finish) as the pipeline would bake them."""
    import trimesh

    lo, hi = np.zeros(3), np.array([30, 30, 30]) * L0
    x = jittered_lattice((30, 30, 15), (0.5 * L0,) * 3, np.random.default_rng(2))
    exact = box_interior_sdf(lo, hi)
    sdf = grid_from_function(exact, lo, hi, 0.5 * L0, band=4 * L0)
    box = trimesh.creation.box(bounds=[lo, hi])
    walls = WallMesh(np.asarray(box.vertices), np.asarray(box.faces, np.int32), np.zeros(len(box.faces), np.int32), [])
    raw = extract(x, np.full(len(x), L0 ** 3), L0, MarchingCubesParams(wall_term=False))
    params = DistanceSnapParams()
    t, (snapped, report) = timed(lambda: snap_mesh(raw, sdf, L0, params, walls), repeats)
    moved = np.linalg.norm(snapped.vertices - raw.vertices, axis=1) > 0
    d1 = exact(snapped.vertices.astype(np.float64))
    return {"particles": int(len(x)), "vertices": int(len(raw.vertices)), "snapped": report["snapped"],
            "snap_s_per_frame": round(t, 4), "damped_vertices": report["damped"],
            "snapped_on_wall_within_1e-3_l0": float((np.abs(d1[moved]) < 1e-3 * L0).mean()),
            "min_exact_distance_l0": float(d1.min() / L0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--small", action="store_true", help="20k sets only")
    args = ap.parse_args()
    load_start = os.getloadavg()[0]  # a shared machine: say how busy it was
    sets = {"block_20k": block(27), "splash_20k": splash(19683)}
    if not args.small:
        sets.update({"block_100k": block(46), "splash_100k": splash(97336)})
    rows = []
    print(f"{'set':12s} {'N':>7s} | {'ours s':>7s} {'tris':>8s} {'vol':>6s} {'open':>4s} | "
          f"{'splashsurf s':>12s} {'tris':>8s} {'vol':>6s} {'open':>4s} | {'ratio':>5s} | {'ours cell 0.5 s':>15s} | "
          f"{'anisotropic s':>13s} {'vol':>6s}")
    for name, x in sets.items():
        a = ours(x, 0.25, args.repeats)
        b = splashsurf(x, args.repeats)
        c = ours(x, 0.5, args.repeats)
        d = ours(x, 0.25, args.repeats, anisotropic=True)
        ratio = a["s_per_frame"] / b["s_per_frame"]
        rows.append({"set": name, "particles": int(len(x)), "ours_cell_0.25": a, "splashsurf_raw": b,
                     "ratio_ours_over_splashsurf": round(ratio, 3), "ours_cell_0.5": c,
                     "ours_anisotropic_cell_0.25": d,
                     "ratio_anisotropic_over_splashsurf": round(d["s_per_frame"] / b["s_per_frame"], 3)})
        print(f"{name:12s} {len(x):7d} | {a['s_per_frame']:7.3f} {a['triangles']:8d} {a['volume_ratio']:6.3f} "
              f"{a['boundary_edges']:4d} | {b['s_per_frame']:12.3f} {b['triangles']:8d} {b['volume_ratio']:6.3f} "
              f"{b['boundary_edges']:4d} | {ratio:5.2f} | {c['s_per_frame']:7.3f} ({c['triangles']} tris) | "
              f"{d['s_per_frame']:13.3f} {d['volume_ratio']:6.3f}", flush=True)
    snap = wall_snap_case(args.repeats)
    print("wall_snap:", json.dumps(snap))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "cores": os.cpu_count(),
                    "load_average_1min_start_end": [round(load_start, 2), round(os.getloadavg()[0], 2)]},
        "settings": {"particle_radius": R_PARTICLE, "l0": L0, "ours": {"radius_l0": MarchingCubesParams().radius, "cell_l0": 0.25,
                                                                  "iso": MarchingCubesParams().iso},
                     "splashsurf": {"smoothing_length_r": 2.0, "cube_size_r": 0.5, "iso": 0.6, "post": "none"},
                     "repeats": args.repeats, "statistic": "median after one warm-up"},
        "sets": rows, "wall_snap": snap}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
