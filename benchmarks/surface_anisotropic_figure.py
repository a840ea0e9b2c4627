"""One splash frame three ways, side by side: ours isotropic | ours anisotropic | splashsurf smoothed.

    .venv/bin/python benchmarks/surface_anisotropic_figure.py [--particles FOLDER --frame N [--label TEXT]]

The committed picture: configs/dam_break.yaml's particles (SPH, 19,683 particles), frame 22 (0.73 s,
the wave running up the far wall), ``--particles .pipeline/simulate/<key> --frame 22``.

FOLDER: a simulate stage's particles artifact (e.g. the dam break's, from the pipeline cache); without
it, bench_surface.py's splash_20k set. All three at the same grid (cube 0.25 l0 = 0.5 r). Ours: the
stage's defaults, then ``anisotropic: true``. splashsurf: smoothing length 2 r, iso 0.6, with its
recommended post-processing (mesh cleanup, weighted Laplacian smoothing of the mesh, 25 iterations,
smoothed normals). Offscreen pyvista. Writes benchmarks/results/images/surface_anisotropic.png and
benchmarks/results/surface_anisotropic.json (times, triangles, enclosed volume / N l0^3).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("RAYON_NUM_THREADS", "2")

import numpy as np  # noqa: E402

from stages.common.formats import ParticleMeta, load_particle_frame  # noqa: E402
from stages.common.meshes import signed_volume, vertex_normals  # noqa: E402
from stages.surface_extract.marching_cubes import MarchingCubesParams, extract  # noqa: E402

HERE = Path(__file__).parent
IMAGE = HERE / "results" / "images" / "surface_anisotropic.png"
RESULTS = HERE / "results" / "surface_anisotropic.json"
CELL = 0.25


def splashsurf_smoothed(x: np.ndarray, l0: float):
    import pysplashsurf as ps

    res = ps.reconstruction_pipeline(np.ascontiguousarray(x, np.float32), particle_radius=l0 / 2, smoothing_length=2.0,
                                     cube_size=2 * CELL, iso_surface_threshold=0.6, rest_density=1000.0,
                                     mesh_cleanup=True, mesh_smoothing_weights=True, mesh_smoothing_iters=25,
                                     compute_normals=True, normals_smoothing_iters=10)
    mesh = res.mesh if hasattr(res, "mesh") else res[0].mesh
    v = np.asarray(mesh.vertices, np.float64)
    f = np.ascontiguousarray(np.asarray(mesh.triangles), dtype=np.int64)
    return v, f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=Path, help="a particles artifact folder (meta.json + frames)")
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--label", help="where the particles come from, for the results file")
    args = ap.parse_args()
    if args.particles:
        meta = ParticleMeta.load(args.particles)
        x = load_particle_frame(args.particles, args.frame).x.astype(np.float64) * meta.meters_per_unit
        l0 = meta.spacing * meta.meters_per_unit
        source = f"{args.label or args.particles} frame {args.frame}"
    else:
        from bench_surface import L0, splash

        x, l0, source = splash(19683), L0, "bench_surface.py splash_20k"
    vol = np.full(len(x), l0 ** 3)
    meshes, rows = {}, {}
    for name, params in (("ours isotropic", MarchingCubesParams(cell=CELL)),
                         ("ours anisotropic", MarchingCubesParams(cell=CELL, anisotropic=True))):
        extract(x, vol, l0, params)  # warm-up
        t = time.perf_counter()
        m = extract(x, vol, l0, params)
        rows[name] = {"s": round(time.perf_counter() - t, 3)}
        meshes[name] = (m.vertices.astype(np.float64), m.faces.astype(np.int64))
    splashsurf_smoothed(x, l0)
    t = time.perf_counter()
    meshes["splashsurf smoothed"] = splashsurf_smoothed(x, l0)
    rows["splashsurf smoothed"] = {"s": round(time.perf_counter() - t, 3)}
    for name, (v, f) in meshes.items():
        rows[name].update(triangles=int(len(f)), volume_ratio=round(signed_volume(v, f) / (len(x) * l0 ** 3), 4))
        print(f"{name:20s} {rows[name]}")

    import pyvista as pv

    lo, hi = x.min(axis=0), x.max(axis=0)
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    plotter = pv.Plotter(off_screen=True, shape=(1, 3), window_size=(1800, 640), lighting="three lights",
                         border=False)
    for k, (name, (v, f)) in enumerate(meshes.items()):
        plotter.subplot(0, k)
        poly = pv.PolyData(v, np.hstack([np.full((len(f), 1), 3), f]).ravel())
        poly.point_data["Normals"] = vertex_normals(v, f.astype(np.int32))
        plotter.add_mesh(poly, color=(0.55, 0.75, 0.95), smooth_shading=True, ambient=0.15, diffuse=0.7,
                         specular=0.4, specular_power=30)
        plotter.add_text(f"{name}: {rows[name]['triangles']:,} triangles, {rows[name]['s']:.2f} s, "
                         f"volume {rows[name]['volume_ratio']:.3f} N l0^3", font_size=8)
        plotter.camera.focal_point = tuple(centre)
        plotter.camera.position = tuple(centre + size * np.array([0.3, -1.25, 0.6]))
        plotter.camera.up = (0.0, 0.0, 1.0)
    IMAGE.parent.mkdir(parents=True, exist_ok=True)
    plotter.screenshot(str(IMAGE))
    plotter.close()
    RESULTS.write_text(json.dumps({"source": source, "particles": int(len(x)), "cell_l0": CELL, "rows": rows},
                                  indent=2))
    print(f"wrote {IMAGE} and {RESULTS}")


if __name__ == "__main__":
    main()
