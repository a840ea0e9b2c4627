"""Render and export timings: seconds per frame at 1280x720 for a ~20k-triangle fluid surface inside a
box tank, the movie encode, and the USD export of the same frames with particles.

    .venv/bin/python benchmarks/bench_render.py [--frames 6]

Writes benchmarks/results/render.json. Synthetic inputs (a wobbling sphere), so it runs without the
upstream stages.
"""
from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from pipeline.testing import run_stage
from stages.common.formats import (ParticleFrame, ParticleMeta, SurfaceMesh, WallMesh, save_particle_frame,
                                   save_surface)
from stages.export.usd_export import UsdExport
from stages.movie.ffmpeg_movie import FfmpegMovie
from stages.render.pyvista_render import PyvistaRender, choose_offscreen_backend

RESULTS = Path(__file__).parent / "results" / "render.json"


def make_inputs(root: Path, frames: int, particles: int) -> dict[str, Path]:
    dirs = {n: root / n for n in ("walls", "surface", "particles")}
    for d in dirs.values():
        d.mkdir()
    box = trimesh.creation.box(extents=(3.0, 1.2, 2.0))
    box.apply_translation((0, 0, 1.0))
    WallMesh(box.vertices, box.faces, np.zeros(len(box.faces), np.int32),
             [{"name": "tank", "fluid": "inside", "source": "builtin:box_tank"}]).save(dirs["walls"])
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.5)  # 20,480 triangles
    rng = np.random.default_rng(0)
    ParticleMeta(spacing=0.0356, mass=0.045, density=1000.0, support=0.0712, fps=30, frame_count=frames,
                 up_axis="Z", meters_per_unit=1.0, solver="synthetic").save(dirs["particles"])
    for f in range(frames):
        wobble = 1.0 + 0.1 * np.sin(3 * ball.vertices[:, 0] + f)[:, None]
        v = ball.vertices * wobble + (-0.6 + 0.05 * f, 0.0, 0.6)
        m = trimesh.Trimesh(v, ball.faces, process=False)
        save_surface(dirs["surface"], f, SurfaceMesh(v, ball.faces, m.vertex_normals))
        x = rng.uniform((-1.4, -0.5, 0.05), (-0.4, 0.5, 1.05), (particles, 3))
        save_particle_frame(dirs["particles"], f, ParticleFrame(x, rng.normal(size=x.shape), np.full(particles, 1000.0),
                                                                rng.uniform(0, 1e4, particles), np.arange(particles)))
    return dirs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--particles", type=int, default=20_000)
    args = ap.parse_args()
    backend = choose_offscreen_backend()
    scene = {"scene": {"name": "bench", "frames": {"fps": 30, "count": args.frames}}}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        inputs = make_inputs(root, args.frames, args.particles)
        # warm-up frame: VTK/EGL start-up is paid once per worker process
        t0 = time.perf_counter()
        run_stage(PyvistaRender, root / "warm", scene=scene, params={"resolution": [1280, 720]}, inputs=inputs, frames=(0,))
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_stage(PyvistaRender, root / "frames", scene=scene, params={"resolution": [1280, 720]}, inputs=inputs)
        surface_s = (time.perf_counter() - t0) / args.frames
        t0 = time.perf_counter()
        run_stage(PyvistaRender, root / "pframes", scene=scene, inputs=inputs,
                  params={"resolution": [1280, 720], "show": "particles"})
        particles_s = (time.perf_counter() - t0) / args.frames
        t0 = time.perf_counter()
        run_stage(FfmpegMovie, root / "movie", scene=scene, inputs={"frames": root / "frames"})
        movie_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        out = run_stage(UsdExport, root / "usd", scene=scene, inputs=inputs)
        export_s = time.perf_counter() - t0
        usd_bytes = sum(f.stat().st_size for f in out.iterdir())
    result = {
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "python": platform.python_version()},
        "offscreen_backend": backend,
        "resolution": [1280, 720],
        "frames": args.frames,
        "surface_triangles": 20480,
        "particles": args.particles,
        "first_frame_s_incl_startup": round(first, 3),
        "render_surface_s_per_frame": round(surface_s, 3),
        "render_particles_s_per_frame": round(particles_s, 3),
        "movie_encode_s": round(movie_s, 3),
        "export_usd_s": round(export_s, 3),
        "export_usd_s_per_frame": round(export_s / args.frames, 3),
        "usd_folder_bytes": usd_bytes,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
