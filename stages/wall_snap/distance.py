"""wall_snap.distance: surface vertices near a wall move onto it (PHYSICS.md eq. 19).

x' = x - d(x) n(x) with d and n from the baked SDF (numba sampler), repeated a few times (a Newton
iteration on d = 0) so the result lies on the wall to well below 1e-3 l0 of the sampled field. A
vertex whose move would flip one of its triangles is moved less (halved until no flip), so the
surface keeps its orientation.
"""
from __future__ import annotations

from typing import Mapping

import numba as nb
import numpy as np
from pydantic import Field

from pipeline.stage import Artifact, Context, Params, Stage
from stages.common.formats import ParticleMeta, SurfaceMesh, load_surface, save_surface
from stages.common.sdf import SDFGrid, sdf_sample
from stages.common.meshes import face_normals, vertex_normals


class DistanceSnapParams(Params):
    band: float = Field(1.0, gt=0, le=5.0, description="vertices with wall distance below band * l0 are snapped")
    only_contact: bool = Field(False, description="snap only vertices whose surface normal faces the wall "
                                                  "(the fluid's contact region), not a free surface passing near it")
    iterations: int = Field(4, ge=1, le=20, description="Newton iterations of x -= d n")


@nb.njit(cache=True, parallel=True)
def snap(v, normals, dist, origin, inv_h, band, only_contact, iterations, out, moved):
    """Project each vertex within ``band`` of a wall (or inside it) onto d = 0 (eq. 19)."""
    for i in nb.prange(v.shape[0]):
        x = v[i, 0]
        y = v[i, 1]
        z = v[i, 2]
        d, nx, ny, nz = sdf_sample(dist, origin[0], origin[1], origin[2], inv_h, x, y, z)
        ok = d < band
        if ok and only_contact and d > 0.0:
            # the surface normal points out of the fluid; at a contact it points into the wall (-n)
            ok = normals[i, 0] * nx + normals[i, 1] * ny + normals[i, 2] * nz < 0.0
        moved[i] = ok
        if ok:
            for _ in range(iterations):
                d, nx, ny, nz = sdf_sample(dist, origin[0], origin[1], origin[2], inv_h, x, y, z)
                x -= d * nx
                y -= d * ny
                z -= d * nz
        out[i, 0] = x
        out[i, 1] = y
        out[i, 2] = z


def snap_mesh(mesh: SurfaceMesh, sdf: SDFGrid, l0: float, params: DistanceSnapParams) -> tuple[SurfaceMesh, dict]:
    if len(mesh.vertices) == 0:
        return mesh, {"snapped": 0, "damped": 0}
    v = mesh.vertices.astype(np.float64)
    out = np.empty_like(v)
    moved = np.zeros(len(v), np.bool_)
    snap(v, mesh.normals.astype(np.float64), sdf.dist, sdf.origin, 1.0 / sdf.spacing, params.band * l0,
         params.only_contact, params.iterations, out, moved)
    f = mesh.faces
    before = face_normals(v, f)
    damped = 0
    for _ in range(8):  # halve the move of vertices of flipped triangles until none flips
        flipped = np.einsum("ij,ij->i", before, face_normals(out, f)) < 0
        if not flipped.any():
            break
        bad = np.unique(f[flipped])
        damped = len(bad)
        out[bad] = 0.5 * (out[bad] + v[bad])
    else:
        flipped = np.einsum("ij,ij->i", before, face_normals(out, f)) < 0
        out[np.unique(f[flipped])] = v[np.unique(f[flipped])]
    snapped = SurfaceMesh(out.astype(np.float32), f, vertex_normals(out, f).astype(np.float32))
    return snapped, {"snapped": int(moved.sum()), "damped": damped}


class DistanceSnap(Stage):
    kind = "wall_snap"
    name = "distance"
    version = "1"
    Params = DistanceSnapParams
    inputs = ("raw_surface", "sdf", "particles")
    outputs = ("surface",)
    per_frame = True
    default = True
    description = "x' = x - d(x) n(x) for vertices near the walls (eq. 19)"

    def run_frame(self, ctx: Context, inputs: Mapping[str, Artifact], params: DistanceSnapParams, frame: int) -> None:
        l0 = ParticleMeta.load(inputs["particles"].frame(frame)).spacing
        sdf = SDFGrid.load(inputs["sdf"].frame(frame))
        mesh = load_surface(inputs["raw_surface"].frame(frame), frame)
        snapped, report = snap_mesh(mesh, sdf, l0, params)
        ctx.log.debug("frame %d: %d vertices snapped, %d damped", frame, report["snapped"], report["damped"])
        save_surface(ctx.out_dir, frame, snapped)
