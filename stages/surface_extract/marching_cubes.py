"""surface_extract.marching_cubes: the fluid surface per frame (PHYSICS.md eq. 17-18).

The implicit function Phi of the particles (implicit.py) is evaluated on a grid covering the
particles plus the kernel radius, and its iso-surface Phi = iso is extracted with VTK's flying edges
(through pyvista). The grid is padded so the surface is closed; faces are oriented so normals point
out of the fluid. Optional Taubin smoothing (volume-preserving) is off by default.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np
from pydantic import Field

from pipeline.stage import Artifact, Context, Params, Stage
from stages.common.formats import ParticleMeta, SurfaceMesh, load_particle_frame, save_surface
from stages.common.meshes import signed_volume, vertex_normals

from .implicit import implicit_function, sort_into_cells


class MarchingCubesParams(Params):
    cell: float = Field(0.5, gt=0.05, le=2.0, description="grid spacing in units of the particle spacing l0")
    radius: float = Field(2.0, ge=1.0, le=4.0, description="kernel support of each particle's density, in l0")
    iso: float = Field(0.5, gt=0.0, lt=1.0, description="iso level of Phi (about 1 inside the fluid)")
    smoothing_iterations: int = Field(0, ge=0, le=200, description="Taubin smoothing passes (0 = off)")


def extract(x: np.ndarray, vol: np.ndarray, l0: float, params: MarchingCubesParams) -> SurfaceMesh:
    """The iso-surface of the particles ``x`` with volumes ``vol`` (m / rho)."""
    import pyvista as pv

    if len(x) == 0:
        return SurfaceMesh.empty()
    R = params.radius * l0
    h = params.cell * l0
    pad = R + 2 * h
    grid_lo = x.min(axis=0) - pad
    shape = np.ceil((x.max(axis=0) + pad - grid_lo) / h).astype(np.int64) + 1
    dims = np.maximum(np.ceil((shape * h) / R).astype(np.int64), 1)
    order, starts = sort_into_cells(x, grid_lo, R, dims)
    xs = np.ascontiguousarray(x[order], np.float64)
    vs = np.ascontiguousarray(vol[order], np.float64)
    phi = np.zeros(tuple(shape), np.float64)
    implicit_function(xs, vs, starts, grid_lo, R, dims, grid_lo, h, shape, R, phi)
    img = pv.ImageData(dimensions=tuple(int(s) for s in shape), spacing=(h, h, h), origin=tuple(grid_lo))
    img.point_data["phi"] = phi.ravel(order="F")
    surf = img.contour([params.iso], scalars="phi", method="flying_edges").triangulate().clean()
    if surf.n_points == 0:
        return SurfaceMesh.empty()
    if params.smoothing_iterations:
        surf = surf.smooth_taubin(n_iter=params.smoothing_iterations, pass_band=0.1)
    verts = np.asarray(surf.points, np.float64)
    faces = np.asarray(surf.faces).reshape(-1, 4)[:, 1:].astype(np.int32)
    if signed_volume(verts, faces) < 0:  # orient outwards (Phi falls off outside the fluid)
        faces = faces[:, ::-1].copy()
    return SurfaceMesh(verts.astype(np.float32), faces, vertex_normals(verts, faces).astype(np.float32))


class MarchingCubes(Stage):
    kind = "surface_extract"
    name = "marching_cubes"
    version = "1"
    Params = MarchingCubesParams
    inputs = ("particles",)
    outputs = ("raw_surface",)
    per_frame = True
    default = True
    description = "Phi = sum (m/rho) W on a grid around the particles, iso-surface by flying edges"

    def run_frame(self, ctx: Context, inputs: Mapping[str, Artifact], params: MarchingCubesParams, frame: int) -> None:
        folder = inputs["particles"].frame(frame)
        meta = ParticleMeta.load(folder)
        pf = load_particle_frame(folder, frame)
        rho = np.maximum(pf.rho.astype(np.float64), 0.5 * meta.density)  # isolated splashes: no blow-up
        vol = meta.mass / rho
        save_surface(ctx.out_dir, frame, extract(pf.x.astype(np.float64), vol, meta.spacing, params))
