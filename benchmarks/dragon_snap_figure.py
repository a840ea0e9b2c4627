"""Before / after wall snapping: the fluid surface where it touches the Stanford dragon.

    .venv/bin/python benchmarks/dragon_snap_figure.py [--frame 20]

Runs configs/dragon.yaml (through the cache: only what is missing is computed) up to the raw and the
snapped surface, then draws a section of both with the dragon at one frame and prints the distance
figures of the contact region against the exact wall meshes (open3d closest points, not the grid).
The same frame is also snapped in this process twice, side by side: without the fold passes
(relax_rounds=0, collapse=False: projection, exact finish and undo_flips, wall_snap version 4) and
with the defaults, for the flips, boundary edges and seconds per frame of each. Writes
benchmarks/results/images/dragon_snap_before_after.png and benchmarks/results/dragon_snap.json.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from stages.common.formats import SurfaceMesh, WallMesh, load_surface
from stages.common.meshes import boundary_edge_count, face_normals
from stages.common.sdf import SDFGrid
from stages.wall_snap.distance import DistanceSnapParams, snap_mesh

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "dragon.yaml"
OUT = ROOT / "out" / "dragon_snap"
IMAGE = ROOT / "benchmarks" / "results" / "images" / "dragon_snap_before_after.png"
RESULTS = ROOT / "benchmarks" / "results" / "dragon_snap.json"


def run_pipeline() -> None:
    cmd = [str(Path(sys.executable).with_name("pipeline")), "run", str(CONFIG), "--out", str(OUT), "-q",
           "--set", "outputs=[particles, sdf, raw_surface, surface, walls]"]
    subprocess.run(cmd, check=True)


def wall_distance(walls: WallMesh, mesh: SurfaceMesh, wall: int | None = None) -> np.ndarray:
    """Distance of each surface vertex to the exact wall mesh (one wall, or all: 0 tank, 1 dragon)."""
    if wall is not None:
        keep = walls.wall_id == wall
        walls = WallMesh(walls.vertices, walls.faces[keep], walls.wall_id[keep], walls.walls)
    import open3d as o3d  # open3d's closest points: a reference apart from wall_snap's own (stages.common.closest)

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(walls.vertices.astype(np.float32)), o3d.core.Tensor(walls.faces.astype(np.uint32)))
    v = mesh.vertices.astype(np.float64)
    near = scene.compute_closest_points(o3d.core.Tensor(v.astype(np.float32)))["points"].numpy().astype(np.float64)
    return np.linalg.norm(near - v, axis=1)


def section_segments(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(K, 2, 3) line segments where the plane (origin, normal) cuts the triangle mesh."""
    import trimesh

    return trimesh.intersections.mesh_plane(trimesh.Trimesh(vertices, faces, process=False), normal, origin)


def section_figure(walls: WallMesh, raw: SurfaceMesh, snapped: SurfaceMesh, contact: np.ndarray, gap: np.ndarray,
                   l0: float, frame: int) -> None:
    """A vertical cut (x-z plane) through the dragon and the fluid where most contact vertices are:
    the dragon's outline, the raw surface and the snapped surface, with a zoom on the contact vertex
    of that cut whose raw surface was furthest off the dragon (``gap``)."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    y = float(np.median(contact[:, 1]))
    origin, normal = np.array([0.0, y, 0.0]), np.array([0.0, 1.0, 0.0])
    keep = walls.wall_id == 1
    cuts = {"dragon (exact mesh)": (section_segments(walls.vertices, walls.faces[keep], origin, normal), "0.35", 2.0),
            "raw marching-cubes surface": (section_segments(raw.vertices, raw.faces, origin, normal), "tab:orange", 1.2),
            "after wall_snap": (section_segments(snapped.vertices, snapped.faces, origin, normal), "tab:blue", 1.2)}
    slab = np.abs(contact[:, 1] - y) < 0.25 * l0
    centre = contact[slab][np.argmax(gap[slab]), [0, 2]] if slab.any() else contact[:, [0, 2]].mean(axis=0)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), dpi=110)
    for ax, half in zip(axes, (None, 3.0 * l0)):
        for label, (seg, color, width) in cuts.items():
            ax.add_collection(LineCollection(seg[:, :, [0, 2]], colors=color, linewidths=width, label=label))
        ax.set_aspect("equal")
        if half is None:
            dv = walls.vertices[np.unique(walls.faces[keep])]
            lo, hi = dv.min(axis=0), dv.max(axis=0)
            ax.set_xlim(lo[0] - 0.05, hi[0] + 0.05)
            ax.set_ylim(lo[2] - 0.02, hi[2] + 0.1)
            ax.add_patch(plt.Rectangle(centre - 3.0 * l0, 6.0 * l0, 6.0 * l0, fill=False, ls=":", color="k"))
            ax.set_title(f"cut at y = {y:.3f} m, frame {frame}")
            ax.legend(loc="upper right", fontsize=8)
        else:
            ax.set_xlim(centre[0] - half, centre[0] + half)
            ax.set_ylim(centre[1] - half, centre[1] + half)
            ax.set_title(f"zoom: {2 * half / l0:.0f} x {2 * half / l0:.0f} particle spacings")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
    fig.tight_layout()
    IMAGE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGE)
    plt.close(fig)


def snap_variants(walls: WallMesh, raw: SurfaceMesh, l0: float, repeats: int) -> dict:
    """The frame snapped without and with the fold passes, in this process: mesh, report, best time."""
    sdf = SDFGrid.load(OUT / "sdf")
    out = {}
    for name, params in (("v4_no_fold_passes", DistanceSnapParams(relax_rounds=0, collapse=False)),
                         ("v6_default", DistanceSnapParams())):
        snap_mesh(raw, sdf, l0, params, walls)  # numba compile
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            mesh, report = snap_mesh(raw, sdf, l0, params, walls)
            best = min(best, time.perf_counter() - t0)
        out[name] = (mesh, report, best)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    run_pipeline()
    walls = WallMesh.load(OUT / "walls")
    l0 = json.loads((OUT / "particles" / "meta.json").read_text())["spacing"]
    raw = load_surface(OUT / "raw_surface", args.frame)
    snapped = load_surface(OUT / "surface", args.frame)
    variants = snap_variants(walls, raw, l0, args.repeats)
    assert np.array_equal(variants["v6_default"][0].vertices, snapped.vertices), "stage output differs"
    d_raw = wall_distance(walls, raw)
    # the contact region: vertices either variant moved; the dragon's part: closer to it than to the tank
    moved = np.zeros(len(raw.vertices), bool)
    for mesh, _, _ in variants.values():
        moved |= np.linalg.norm(mesh.vertices - raw.vertices, axis=1) > 1e-7
    on_dragon = wall_distance(walls, raw, 1) <= wall_distance(walls, raw, 0)
    n_raw = face_normals(raw.vertices.astype(np.float64), raw.faces)
    figures = {"frame": args.frame, "spacing": l0, "raw_vertices": len(raw.vertices), "raw_faces": len(raw.faces),
               "raw_boundary_edges": boundary_edge_count(raw.faces)}
    for variant, (mesh, report, seconds) in variants.items():
        d_snap = wall_distance(walls, mesh)
        kept = report["kept_faces"]
        n = face_normals(mesh.vertices.astype(np.float64), mesh.faces)
        row = {"seconds_per_frame": round(seconds, 3),
               "flipped_faces": int((np.einsum("ij,ij->i", n_raw[kept], n) < 0).sum()),
               "boundary_edges": boundary_edge_count(mesh.faces),
               **{k: int(x) for k, x in report.items() if k != "kept_faces"}}
        for name, sel in (("dragon_contact", moved & on_dragon), ("all_contact", moved)):
            row[name] = {"vertices": int(sel.sum()),
                         "raw_distance_mean_l0": float(d_raw[sel].mean() / l0),
                         "raw_distance_max_l0": float(d_raw[sel].max() / l0),
                         "snapped_distance_max_l0": float(d_snap[sel].max() / l0),
                         "snapped_within_1e-3_l0": float((d_snap[sel] < 1e-3 * l0).mean()),
                         "snapped_off_1e-3_l0": int((d_snap[sel] >= 1e-3 * l0).sum())}
        figures[variant] = row
    contact = moved & on_dragon
    print(json.dumps(figures, indent=2))
    RESULTS.write_text(json.dumps(figures, indent=2) + "\n")

    section_figure(walls, raw, snapped, raw.vertices[contact], d_raw[contact], l0, args.frame)
    print(f"wrote {IMAGE}")


if __name__ == "__main__":
    main()
