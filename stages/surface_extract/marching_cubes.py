"""surface_extract.marching_cubes: the fluid surface per frame (PHYSICS.md eq. 17-18).

The rule (splashsurf's, with our Poly6 kernel): Phi(x) = sum_j V_j W(|x - x_j|), W the Poly6 kernel
of support R = 1.7 l0, V_j = m_j / rho_j with rho_j summed by SPH over the same kernel and the
particles present in the frame (not the solver's density, which a solver may clamp at the free
surface), surface at Phi = 0.63. Inside the fluid Phi = 1. A lone particle has Phi = W(r) / W(0) =
(1 - r^2 / R^2)^3: its 0.63 level is a sphere of 0.64 l0 (1.11 l0^3; marching cubes' facets take
back 10 % at cell 0.25 l0, 37 % at 0.5), so a droplet keeps about its own volume instead of dropping
below the iso level. Small clusters keep 0.74 (a tetrahedron) to 1.0 (three in a row) of their
volume at cell 0.25. With the same R and iso a flat free surface lies within a few hundredths of l0
of half a spacing above the top layer, so a still block keeps its volume (R = 2 l0 would need iso
0.74 for the droplet and then put a flat surface 0.14 l0 too low; 1.7 is the smallest support that
keeps a lattice sphere's normals as smooth as before). Only mass ratios enter, so it holds in any
length unit. Before (R = 2 l0, iso 0.5, V = m / rho with the solver's rho floored at rho0 / 2) a lone
particle's Phi peaked at 0.2-0.4 and it vanished, while the solver's low densities at the free
surface inflated the rest: a dam-break frame enclosed 1.01-1.06 N l0^3 (now 0.96-1.01, splashsurf
0.97-1.02), bench_surface.py's splash with V = l0^3 0.87 (now 1.00).

The implicit function (implicit.py, numba, scattered only onto the grid nodes inside each particle's
kernel sphere) is evaluated on a grid covering the particles plus the kernel radius, and its
iso-surface Phi = iso is extracted with VTK's flying edges (through pyvista). The grid is padded, so
the surface is closed; faces are oriented so that normals point out of the fluid. Optional Taubin
smoothing (which keeps the volume) is off by default.

With ``anisotropic`` each particle's kernel is an ellipsoid fitted to its neighbours (anisotropic.py,
Yu and Turk 2013), for smooth sheets and flat surfaces.

With an SDF upstream the wall's share of the density is added near walls (mirror images of the
particles within R of a wall) and the fluid is cut by the wall (Phi' = iso + min(Phi - iso, d / R)),
so where the fluid touches a wall the raw surface already lies on it instead of floating about half a
kernel radius off; wall_snap then only has the contact line left to do. Moving walls (sdf_bake's
bodies) are folded into the field at the frame's time (sdf.posed_field).

A Y-up scene is extracted in the Z-up frame (``extract_in_z_up``): the grid is laid out along the axes
from the particles' lowest corner, which a Y-up scene has at another place relative to the fluid, so the
same scene set up Y-up was sampled at other points (2836 against 2842 vertices on a splash frame).
"""
from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path
from typing import Mapping

import numba as nb
import numpy as np
from pydantic import Field, field_validator

from pipeline.stage import Artifact, Context, Params, Stage
from stages.common.formats import ParticleMeta, SurfaceMesh, load_particle_frame, position_dtype, save_surface
from stages.common.meshes import signed_volume, vertex_normals
from stages.common.sdf import SDFGrid, field, file_stamps, posed_field

from .anisotropic import anisotropic_kernels, scatter_anisotropic
from .implicit import (add_seen_images, cell_grid, cut_by_walls, ghost_particles, order_and_chunks, particle_volumes,
                       scatter_clipped, scatter_implicit)

SLABS_PER_CHUNK = 4  # z slabs per parallel task: many tasks for balance, each particle in ~ 2R / (4 h) of them
_kept = threading.local()  # per thread: the grid buffer kept across frames (grid_buffer)


def vtk_threads(n: int) -> None:
    """Run VTK's filters (flying edges) on ``n`` threads, as many as numba's: the VTK wheel's default SMP
    backend is Sequential, one core (the splash's contour took 0.50 s on one core, 0.39 s on two). Flying
    edges writes the same triangles in the same order on any number of threads."""
    from vtkmodules.vtkCommonCore import vtkSMPTools
    if vtkSMPTools.GetBackend() != "STDThread":
        vtkSMPTools.SetBackend("STDThread")
    if vtkSMPTools.GetEstimatedNumberOfThreads() != n:
        vtkSMPTools.Initialize(n)


def grid_buffer(shape) -> np.ndarray:
    """An uninitialised float32 (nz, ny, nx) grid, a view of a buffer this thread keeps across frames. A
    fresh array as large (220 MB for a 100k-particle splash at cell 0.25 l0) paid its page faults again on
    every frame: a tenth of a second, and most of the run-to-run spread of the surface's time."""
    n = int(np.prod(shape))
    buf = getattr(_kept, "phi", None)
    if buf is None or buf.size < n:
        _kept.phi = None  # let the old one go before the new one is made
        buf = _kept.phi = np.empty(n, np.float32)
    return buf[:n].reshape(tuple(int(s) for s in shape))


def keep_piece_volumes(raw: np.ndarray, smooth: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The smoothed vertices with each connected piece of water scaled about its centre back to its raw
    volume: a low-pass filter shrinks what is small against its pass band, and a drop of one particle
    went to 2 % of its volume in 50 passes, to nothing in 200. A piece shrunk below a quarter is kept raw."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(raw)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    _, label = connected_components(coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n)),
                                    directed=False)
    k = int(label.max()) + 1 if n else 0
    count = np.bincount(label, minlength=k)[:, None]

    def volumes(v):  # per piece, in float64 about each piece's centre
        v = v.astype(np.float64)
        centre = np.stack([np.bincount(label, v[:, a], minlength=k) for a in range(3)], axis=1) / count
        q = v - centre[label]
        a, b, c = q[faces[:, 0]], q[faces[:, 1]], q[faces[:, 2]]
        return np.bincount(label[faces[:, 0]], np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0, minlength=k), centre

    before, _ = volumes(raw)
    after, centre = volumes(smooth)
    ok = (before > 0) & (after > 0.25 * before)
    scale = np.where(ok, np.cbrt(np.where(ok, before, 1.0) / np.where(ok, after, 1.0)), 1.0)
    out = centre[label] + (smooth.astype(np.float64) - centre[label]) * scale[label][:, None]
    out[~ok[label]] = raw[~ok[label]]
    return out.astype(smooth.dtype)


class MarchingCubesParams(Params):
    @field_validator("smoothing_iterations")
    @classmethod
    def _not_one(cls, n: int) -> int:
        if n == 1:  # VTK's windowed sinc filter needs two: with one it shrank the surface to 0.3 % of its volume
            raise ValueError("1 pass is no Taubin filter: use 0 (off) or 2 and more")
        return n

    cell: float = Field(0.5, gt=0.05, le=2.0, description="grid spacing in units of the particle spacing l0")
    radius: float = Field(1.7, ge=1.2, le=4.0, description="kernel support of each particle's density, in l0 (at "
                          "least 1.2: below it lattice neighbours' kernels barely overlap, and a dam break's surface "
                          "held 0.88 of the water at 1.05 l0, 0.51 at 1.0, in fragments; 0.97 at 1.2)")
    iso: float = Field(0.63, gt=0.0, lt=1.0, description="iso level of Phi (1 inside the fluid, 0 outside); with "
                       "radius 1.7 a lone particle keeps about l0^3 and a flat surface lies l0/2 above the top layer")
    smoothing_iterations: int = Field(0, ge=0, le=200, description="Taubin (windowed sinc) smoothing passes "
                                      "(0 = off, else at least 2); each piece of water keeps its volume")
    anisotropic: bool = Field(False, description="anisotropic kernels (Yu and Turk 2013) stretched along the "
                                                "neighbours' spread: smoother sheets and flat surfaces")
    anisotropic_smoothing: float = Field(0.0, ge=0.0, le=1.0, description="with anisotropic: Yu and Turk's lambda "
                                         "(0.9 in their paper) smoothing the kernels' centres; it sinks flat "
                                         "surfaces (a still block loses 5 % at 0.9)")
    wall_term: bool = Field(True, description="with an SDF upstream: add the walls' density near them and cut "
                                              "the fluid at d = 0, so the surface meets the walls")


# Y-up -> Z-up: (x, y, z) -> (x, -z, y), a swap and a sign: exact in floating point both ways
_Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def z_up_field(sdf: SDFGrid) -> SDFGrid:
    """A Y-up scene's SDF seen from the Z-up frame: node (i, j, k) at (x, y, z) becomes node (i, nz-1-k, j)
    at (x, -z, y); the same values, moved, not resampled. The last one is kept: a shot's static field is
    turned once per process, not every frame."""
    kept = _turned.get(id(sdf))
    if kept is not None and kept[0] is sdf:
        return kept[1]
    dist = np.ascontiguousarray(np.flip(np.transpose(sdf.dist, (0, 2, 1)), axis=1))
    origin = np.array([sdf.origin[0], -sdf.upper[2], sdf.origin[1]])
    turned = dataclasses.replace(sdf, origin=origin, dist=dist)
    turned._slopes = sdf.axis_slopes()[[0, 2, 1]]
    _turned.clear()
    _turned[id(sdf)] = (sdf, turned)
    return turned


_turned: dict = {}  # id -> (field, its Z-up copy)


def extract_in_z_up(x: np.ndarray, vol: np.ndarray, l0: float, params: MarchingCubesParams, up_axis: str,
                    sdf: SDFGrid | None = None, timings: dict | None = None, check_memory=None) -> SurfaceMesh:
    """``extract`` of a scene with ``up_axis``, done in the Z-up frame and turned back: the surface of a
    Y-up scene is then the Z-up scene's surface turned, vertex for vertex."""
    if up_axis != "Y":
        return extract(x, vol, l0, params, sdf=sdf, timings=timings, check_memory=check_memory)
    mesh = extract(np.asarray(x, np.float64) @ _Y_TO_Z.T, vol, l0, params,
                   sdf=None if sdf is None else z_up_field(sdf), timings=timings, check_memory=check_memory)
    if len(mesh.vertices) == 0:
        return mesh
    back = lambda a: np.ascontiguousarray(a @ _Y_TO_Z.astype(a.dtype))  # noqa: E731 - the inverse turn, row form
    return SurfaceMesh(back(mesh.vertices), mesh.faces, back(mesh.normals))


SPLIT_NODES = 1 << 22  # a grid over all the water above this many nodes: extracted piece by piece if that is smaller
BYTES_PER_NODE = 8  # the float32 field and flying edges' work arrays (measured 6-7 on a splash frame)


def grid_nodes(lo: np.ndarray, hi: np.ndarray, pad: float, h: float) -> int:
    """Nodes of the grid over the box lo..hi padded by ``pad``, spacing ``h`` (as extract lays it out)."""
    return int(np.prod(np.ceil((hi - lo + 2.0 * pad + 0.25 * h) / h) + 1))


def apart(x: np.ndarray, gap: float) -> list[np.ndarray]:
    """The particles in groups more than ``gap`` from each other (indices per group): cells of size ``gap``, a
    group the cells joined through their 26 neighbours."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    c = np.floor((x - x.min(axis=0)) / gap).astype(np.int64)
    dims = c.max(axis=0) + 3
    key = ((c[:, 0] + 1) * dims[1] + c[:, 1] + 1) * dims[2] + c[:, 2] + 1
    cells, inverse = np.unique(key, return_inverse=True)
    rows, cols = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                nb_key = cells + (dx * dims[1] + dy) * dims[2] + dz
                at = np.minimum(np.searchsorted(cells, nb_key), len(cells) - 1)
                hit = cells[at] == nb_key
                rows.append(np.flatnonzero(hit))
                cols.append(at[hit])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    n, label = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(cells),) * 2),
                                    directed=False)
    of_particle = label[inverse.ravel()]
    order = np.argsort(of_particle, kind="stable")
    return np.split(order, np.cumsum(np.bincount(of_particle, minlength=n))[:-1])


def joined(pieces: list[SurfaceMesh]) -> SurfaceMesh:
    pieces = [m for m in pieces if len(m.faces)]
    if not pieces:
        return SurfaceMesh.empty()
    dtype = np.float64 if any(m.vertices.dtype == np.float64 for m in pieces) else np.float32
    offsets = np.cumsum([0] + [len(m.vertices) for m in pieces[:-1]])
    return SurfaceMesh(np.concatenate([m.vertices.astype(dtype, copy=False) for m in pieces]),
                       np.concatenate([m.faces + np.int32(o) for m, o in zip(pieces, offsets)]).astype(np.int32),
                       np.concatenate([m.normals for m in pieces]))


def extract(x: np.ndarray, vol: np.ndarray, l0: float, params: MarchingCubesParams,
            sdf: SDFGrid | None = None, timings: dict | None = None, check_memory=None,
            split: bool = True) -> SurfaceMesh:
    """The iso-surface Phi = iso of the particles ``x`` (N, 3) with rest volumes ``vol`` (N,) = m / rho0 (any
    quantity proportional to the masses: the volumes V_j = m_j / rho_j come from SPH summation), all in
    one length unit (the scene's: ``ParticleMeta.volume``), as ``l0``.

    ``sdf`` (optional) brings in the wall term; ``timings`` (optional) receives seconds per step;
    ``check_memory(bytes, details)`` (optional) refuses a grid the machine cannot hold.

    The grid is dense over the water's box: spray across a large domain made it huge (two drops in the corners
    of a 3 m tank asked for 49 GB after the simulation had run). Where a grid over all the water would be large
    and groups of particles lie more than 2 R apart (their fields do not meet), each group is extracted on its
    own grid (``split``) and the pieces joined: the same surface, on grids laid out from each group's corner."""
    import pyvista as pv
    from vtkmodules.util.numpy_support import vtk_to_numpy

    t = {"volumes": 0.0, "phi": 0.0, "contour": 0.0, "finish": 0.0}
    if timings is not None:
        timings.update(t)
    if len(x) == 0:
        return SurfaceMesh.empty()
    t0 = time.perf_counter()
    R = params.radius * l0
    h = params.cell * l0
    x = np.asarray(x, np.float64)
    vol = np.asarray(vol, np.float64)
    pad = R + 2.0 * h  # the surface is within R of a particle; two more cells keep it off the grid's edge
    # (anisotropic kernels reach past R: not split)
    whole = grid_nodes(x.min(axis=0), x.max(axis=0), pad, h) if split and not params.anisotropic else 0
    if whole > SPLIT_NODES:
        groups = apart(x, 2.0 * R * (1.0 + 1e-6))
        apart_nodes = sum(grid_nodes(x[g].min(axis=0), x[g].max(axis=0), pad, h) for g in groups)
        if len(groups) > 1 and apart_nodes < 0.5 * whole:
            pieces = []
            for g in groups:
                part: dict = {}
                pieces.append(extract(x[g], vol[g], l0, params, sdf, part, check_memory, split=False))
                if timings is not None:
                    for k, v in part.items():
                        timings[k] += v
            return joined(pieces)
    # a quarter cell off the particle lattice: an emitter box filling a tank's corner puts its first
    # particles l0/2 from the walls, which would put grid nodes exactly on the walls, where Phi' = iso
    # up to rounding and the topology of the contact depended on the last bit (so on the scene's units)
    grid_lo = x.min(axis=0) - pad - 0.25 * h
    shape = np.ceil((x.max(axis=0) + pad - grid_lo) / h).astype(np.int64) + 1  # (nx, ny, nz)
    n_real = len(x)
    n_thin = 0  # images beside thin walls, kept apart (thin_*): they count on their particle's side only
    if sdf is not None and params.wall_term:
        gx = np.empty_like(x)
        gv = np.empty_like(vol)
        keep = np.empty(len(x), np.bool_)
        behind = np.empty(len(x), np.bool_)
        depth = np.empty(len(x))
        ghost_particles(x, vol, sdf.dist, sdf.origin, 1.0 / sdf.spacing, R, gx, gv, keep, behind, depth)
        thin = keep & behind
        solid = keep & ~thin
        n_thin = int(thin.sum())
        thin_src, thin_x, thin_in, thin_depth = x[thin], gx[thin], gv[thin], depth[thin]
        x = np.concatenate([x, gx[solid]])
        vol = np.concatenate([vol, gv[solid]])
    vol_in = vol
    vol = particle_volumes(x, vol, R)  # the mirror images count: the wall carries its share of rho
    if n_thin:  # and beside thin walls, on their own side only
        from scipy.spatial import cKDTree

        near = cKDTree(x[:n_real]).query_ball_point(thin_x, R)
        pairs_g = np.repeat(np.arange(n_thin), [len(n) for n in near])
        pairs_i = np.fromiter((i for n in near for i in n), np.int64, len(pairs_g))
        summed = vol_in[:n_real] / vol[:n_real]
        add_seen_images(x, summed, pairs_g, pairs_i, thin_x, thin_in, thin_src, thin_depth, R, sdf.dist, sdf.origin,
                        1.0 / sdf.spacing)
        vol[:n_real] = vol_in[:n_real] / summed
        thin_vol = vol[:n_real][thin]  # an image occupies its particle's volume
    reach = R
    x_real = x[:n_real]  # the particles where they are (anisotropic kernels move their centres)
    if params.anisotropic:
        x, metric, extent = anisotropic_kernels(x, R, params.anisotropic_smoothing)  # centres, ellipsoids
        real = slice(0, n_real)
        grid_lo = (x[real] - extent[real]).min(axis=0) - 2.25 * h
        shape = np.ceil(((x[real] + extent[real]).max(axis=0) + 2.0 * h - grid_lo) / h).astype(np.int64) + 1
        reach = float(extent[:, 2].max())
    if check_memory is not None:
        span = "x".join(f"{e / l0:.0f}" for e in x_real.max(axis=0) - x_real.min(axis=0))
        check_memory(float(np.prod(shape)) * BYTES_PER_NODE,
                     f"a surface grid of {shape[0]}x{shape[1]}x{shape[2]} nodes over water {span} l0 across at "
                     f"surface_extract.cell {params.cell} l0: raise the cell")
    t_vol = time.perf_counter()
    order, first, last, bounds = order_and_chunks(x, grid_lo, h, reach, shape, SLABS_PER_CHUNK)
    xs = np.ascontiguousarray(x[order])
    vs = np.ascontiguousarray(vol[order])
    phi = grid_buffer((shape[2], shape[1], shape[0]))  # scatter_implicit zeroes it
    if params.anisotropic:
        phi[:] = 0.0
        scatter_anisotropic(xs, vs, np.ascontiguousarray(metric[order]), np.ascontiguousarray(extent[order]),
                            first, last, bounds, grid_lo, 1.0 / h, R, phi)
    else:
        scatter_implicit(xs, vs, first, last, bounds, grid_lo, 1.0 / h, R, phi)
    if n_thin:
        scatter_clipped(thin_x, thin_vol, thin_src, thin_depth, grid_lo, 1.0 / h, R, phi, sdf.dist, sdf.origin,
                        1.0 / sdf.spacing)
    if sdf is not None and params.wall_term:
        pts = np.ascontiguousarray(x_real, np.float64)
        grid = cell_grid(pts, R)
        ordered = pts[grid.sort(pts)]
        cut_by_walls(phi, grid_lo, h, params.iso, R, ordered, grid.starts, grid.lo, 1.0 / grid.cell, grid.dims,
                     sdf.dist, sdf.origin, 1.0 / sdf.spacing, sdf.axis_slopes())
    t1 = time.perf_counter()

    vtk_threads(nb.get_num_threads())
    # VTK places the vertices in float32: far from the origin it contours about the grid's corner and the
    # corner is added back in float64 (in place, 1e5 m out, the surface bent by a quarter spacing, -12 % volume)
    far = position_dtype(np.stack([grid_lo, grid_lo + h * (np.asarray(shape) - 1)]), h) is np.float64
    img = pv.ImageData(dimensions=tuple(int(s) for s in shape), spacing=(h, h, h),
                       origin=(0.0, 0.0, 0.0) if far else tuple(grid_lo))
    img.point_data["phi"] = phi.reshape(-1)  # (z, y, x) C order = VTK's x-fastest point order, no copy
    surf = img.contour([params.iso], scalars="phi", method="flying_edges", compute_normals=False,
                       compute_scalars=False)
    t2 = time.perf_counter()
    if surf.n_points == 0:
        return SurfaceMesh.empty()
    # flying edges makes triangles only: the cells' connectivity, without pyvista's legacy (n, i, j, k)
    # array (building it took a third of a second at 4M triangles)
    faces = vtk_to_numpy(surf.GetPolys().GetConnectivityArray()).astype(np.int32).reshape(-1, 3)
    if params.smoothing_iterations:
        raw = np.asarray(surf.points).copy()
        surf = surf.smooth_taubin(n_iter=params.smoothing_iterations, pass_band=0.1, normalize_coordinates=True)
        surf.points = keep_piece_volumes(raw, np.asarray(surf.points), faces)
    verts = np.asarray(surf.points)  # float32 from VTK, kept: no float64 copy of millions of vertices
    if far:
        verts = verts.astype(np.float64) + grid_lo
    if signed_volume(verts, faces) < 0:  # orient outwards (Phi falls off outside the fluid)
        faces = np.ascontiguousarray(faces[:, ::-1])
    normals = vertex_normals(verts, faces)
    t3 = time.perf_counter()
    if timings is not None:
        timings.update({"volumes": t_vol - t0, "phi": t1 - t_vol, "contour": t2 - t1, "finish": t3 - t2})
    return SurfaceMesh(verts.astype(position_dtype(verts, l0), copy=False), faces, normals.astype(np.float32, copy=False))


def diagnostics_file(frame: int) -> str:
    """What ``run_frame`` found in a frame (particles, empty, volume_ratio), beside its surface: the frames may run
    in several worker processes, and only ``summarise`` sees them all. A dotfile: the cache entry's bookkeeping, not
    published with the surfaces."""
    return f".surface_{frame:05d}.json"


def frame_list(frames, most: int = 6) -> str:
    """``[3, 7, 8, 9, 31]`` -> ``"3, 7-9, 31"``; past ``most`` ranges the first ones and "..."."""
    runs: list[list[int]] = []
    for f in sorted(frames):
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    text = [str(a) if a == b else f"{a}-{b}" for a, b in runs]
    return ", ".join(text[:most]) + (", ..." if len(text) > most else "")


def _span(values, fmt: str) -> str:
    lo, hi = fmt % min(values), fmt % max(values)
    return lo if lo == hi else f"{lo}-{hi}"


def said_volume(log, ratios: dict[int, float], total: int, params: MarchingCubesParams) -> None:
    """One line for the run: the frames whose surface is far from the water's volume (``ratios``: frame -> enclosed
    / N l0^3, of ``total`` frames) under settings changed from the defaults (at cell 1.5 l0 lone drops and jets
    vanished, at radius 4 a drop became 13 l0^3, without a word). The defaults keep 0.96-1.01 on a splash (a few
    lone drops 0.7-0.9: not said)."""
    changed = {k: getattr(params, k) for k in ("cell", "radius", "iso", "anisotropic_smoothing")
               if getattr(params, k) != MarchingCubesParams.model_fields[k].default}
    off = {f: r for f, r in ratios.items() if not 0.8 <= r <= 1.25}
    if not changed or not off:
        return
    log.warning("surface_extract: %d of %d frames (%s) enclose%s %s of the water's volume with %s (the defaults keep "
                "0.96-1.01 on a splash): a large cell or iso loses drops, jets and thin sheets, a large radius swells "
                "them", len(off), total, frame_list(off), "s" if len(off) == 1 else "", _span(off.values(), "%.2f"),
                ", ".join(f"{k} {v}" for k, v in changed.items()))


def said_empty(log, particles: dict[int, int], total: int, params: MarchingCubesParams) -> None:
    """One line for the run: the frames with particles whose surface is empty (``particles``: frame -> its
    particles, of ``total`` frames), with the settings changed from the defaults that likely emptied them
    (anisotropic or isotropic kernels at iso 0.999 left spray no node above the iso level, cell 1.5 l0 lone drops
    and a jet). Said at the default settings too."""
    if not particles:
        return
    fields = MarchingCubesParams.model_fields
    changed = [k for k in ("iso", "radius", "cell", "anisotropic", "anisotropic_smoothing", "wall_term")
               if getattr(params, k) != fields[k].default]
    settings = (f"with {', '.join(f'{k} {getattr(params, k)}' for k in changed)} (defaults: "
                f"{', '.join(f'{k} {fields[k].default}' for k in changed)})" if changed else
                "at the default settings (the walls' cut, wall_term, may have taken it)")
    one = len(particles) == 1
    log.warning("surface_extract: %d of %d frames (%s) %s an empty surface, enclosing 0.00 of the water's volume, "
                "though %s %s particles %s: a high iso, a small radius or a large cell leaves no grid node at the "
                "iso level (a lone particle's Phi peaks at 1 at its centre)", len(particles), total,
                frame_list(particles), "has" if one else "have", "it holds" if one else "they hold",
                _span(particles.values(), "%d"), settings)


class MarchingCubes(Stage):
    kind = "surface_extract"
    name = "marching_cubes"
    version = "5"
    Params = MarchingCubesParams
    inputs = ("particles",)
    optional_inputs = ("sdf",)
    outputs = ("raw_surface",)
    per_frame = True
    default = True
    description = ("Phi = sum (m/rho) W (rho by SPH summation) scattered onto a grid around the particles, "
                   "iso-surface by flying edges")

    def run_frame(self, ctx: Context, inputs: Mapping[str, Artifact], params: MarchingCubesParams, frame: int) -> None:
        folder = inputs["particles"].frame(frame)
        meta = ParticleMeta.load(folder)
        pf = load_particle_frame(folder, frame)
        vol = np.full(len(pf.x), meta.volume(meta.density))  # m / rho0 in scene units^3 (m / rho alone is m^3)
        sdf = None
        if inputs.get("sdf") is not None:  # moving walls folded in at the frame's time
            folder = inputs["sdf"].frame(frame)
            sdf = posed_field(*field(folder, file_stamps(folder)), frame / meta.fps)
        timings: dict = {}
        mesh = extract_in_z_up(pf.x, vol, meta.spacing, params, meta.up_axis, sdf=sdf, timings=timings,
                               check_memory=ctx.check_memory)
        ctx.log.debug("frame %d: %d particles -> %d triangles (volumes %.3f s, phi %.3f s, contour %.3f s, "
                      "finish %.3f s)", frame, len(pf.x), len(mesh.faces), timings["volumes"], timings["phi"],
                      timings["contour"], timings["finish"])
        ratio = signed_volume(mesh.vertices, mesh.faces) / (len(pf.x) * vol[0]) if len(mesh.faces) else 0.0
        (ctx.out_dir / diagnostics_file(frame)).write_text(json.dumps(
            {"particles": len(pf.x), "empty": not len(mesh.faces), "volume_ratio": ratio if len(pf.x) else None}))
        save_surface(ctx.out_dir, frame, mesh, meta.spacing)

    def summarise(self, ctx: Context, params: MarchingCubesParams, frames: Mapping[int, Path]) -> None:
        """The frames far off in volume, and those with particles and no surface, each in one line for the run."""
        seen = {}
        for f, folder in frames.items():
            path = Path(folder) / diagnostics_file(f)
            if path.is_file():  # (the code is keyed: only a damaged entry lacks it; not worth failing the run)
                seen[f] = json.loads(path.read_text())
        said_volume(ctx.log, {f: d["volume_ratio"] for f, d in seen.items() if d["particles"] and not d["empty"]},
                    len(seen), params)
        # (a frame without particles has no surface to have)
        said_empty(ctx.log, {f: d["particles"] for f, d in seen.items() if d["particles"] and d["empty"]},
                   len(seen), params)
