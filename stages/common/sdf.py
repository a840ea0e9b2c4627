"""The baked signed distance field: artifact format and the numba sampler used by simulate and wall_snap.

Convention (PHYSICS.md): d(x) > 0 in the fluid region, < 0 inside a wall, and n = grad d / |grad d|
points from the wall into the fluid. Values are exact within ``band`` of a wall and clamped to
+-band beyond it (the sign stays right). The grid is node-centred: node (i, j, k) sits at
origin + spacing * (i, j, k).
"""
from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

from stages.common.motion import RigidMotion

SDF_FILE = "sdf.npz"
# moving walls: bodies.json = [{"wall": index into walls.json, "name", "motion": RigidMotion.to_json(),
# "file": "bodies/<k>.npz"}], each file an SDFGrid of that wall alone in its rest pose
BODIES_FILE = "bodies.json"
BODIES_DIR = "bodies"

# Shells and thin walls against the trilinear grid (tests/test_shells.py proves the bound):
# the field |d| - t/2 of a wall thinner than a cell is V-shaped, and trilinear sampling flattens the V
# in the cells the wall cuts: there the gradient can point across the wall, and the eq. 16 push-out
# then carries a particle through it. A particle left at d >= r_rep by the push-out never starts in
# such a cell when the cell is no wider than r_rep; one step of length delta brings it into one only if
# t < cell + 2 (delta - r_rep) (exact for a wall along the grid axes; random orientations in the test
# need no more). WCSPH moves a particle at most delta = cfl l0 + dt^2 a_max <= 0.4 l0 + 0.125 l0 (the
# CFL and force limits), so at cell 0.5 l0 and r_rep 0.5 l0 the least safe thickness is 0.55 l0.
SHELL_STEP = 0.525  # largest particle step per time step the bound is made for, in l0
SHELL_R_REP = 0.5  # the eq. 16 repulsion distance of the solvers, in l0
DEFAULT_SHELL_THICKNESS = 0.6  # in l0: above min_shell_thickness at the default cell 0.5


def wall_move_limit(r_rep: float) -> float:
    """The longest move (in l0) between two eq. 16 push-outs to ``r_rep`` l0 that the walls sdf_bake
    thickens to by default (min_shell_thickness) hold against: the bound above solved for the step.
    A solver with a small r_rep (DFSPH's 0.2 l0) or long steps (CFL near 1) sub-steps its moves near
    walls to it; for WCSPH (r_rep 0.5 l0) it is SHELL_STEP, never less than its own steps."""
    return r_rep + SHELL_STEP - SHELL_R_REP


def min_shell_thickness(cell: float, step: float = SHELL_STEP, r_rep: float = SHELL_R_REP) -> float:
    """The thinnest wall (in l0) that a particle cannot cross on a grid of ``cell`` l0, moving at most
    ``step`` l0 per time step and pushed out to ``r_rep`` l0 (see above); 0 if any wall is safe."""
    return max(cell + 2.0 * (step - r_rep), 0.0)


@dataclass
class SDFGrid:
    origin: np.ndarray  # (3,) float64, position of node (0, 0, 0)
    spacing: float  # node spacing, scene units
    dist: np.ndarray  # (nx, ny, nz) float32, C order
    band: float  # |d| is exact below this, clamped above
    shell_thickness: np.ndarray | None = None  # (walls,) float64: thickness as baked, 0 for a solid wall

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.dist.shape)  # type: ignore[return-value]

    @property
    def upper(self) -> np.ndarray:
        return self.origin + self.spacing * (np.array(self.dist.shape) - 1)

    def save(self, folder: Path) -> Path:
        return self.save_file(Path(folder) / SDF_FILE)

    def save_file(self, path: Path) -> Path:
        extra = {} if self.shell_thickness is None else {"shell_thickness": np.asarray(self.shell_thickness, np.float64)}
        np.savez(path, origin=self.origin, spacing=np.float64(self.spacing),
                 dist=np.ascontiguousarray(self.dist, dtype=np.float32), band=np.float64(self.band), **extra)
        return path

    @classmethod
    def load(cls, folder: Path) -> "SDFGrid":
        return cls.load_file(Path(folder) / SDF_FILE)

    @classmethod
    def load_file(cls, path: Path) -> "SDFGrid":
        with np.load(path) as z:
            return cls(origin=np.asarray(z["origin"], np.float64), spacing=float(z["spacing"]),
                       dist=np.ascontiguousarray(z["dist"], np.float32), band=float(z["band"]),
                       shell_thickness=np.asarray(z["shell_thickness"], np.float64) if "shell_thickness" in z else None)

    def axis_slopes(self) -> np.ndarray:
        """The field's largest |change| between neighbouring nodes along each axis, per unit length (kept): its
        trilinear interpolant changes by at most sum_k slopes_k |step_k| along any step (1 for a distance
        field; more where a sign flips across a wall that is not closed)."""
        if getattr(self, "_slopes", None) is None:
            self._slopes = np.array([float(np.abs(np.diff(self.dist, axis=k)).max(initial=0.0)) / self.spacing
                                     for k in range(3)])
        return self._slopes

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (N,) and unit normal (N, 3) at ``points`` (N, 3); convenience wrapper."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        d = np.empty(len(pts), np.float64)
        n = np.empty((len(pts), 3), np.float64)
        sdf_sample_many(self.dist, self.origin, 1.0 / self.spacing, pts, d, n)
        return d, n


# Per process (a worker runs many frames of one shot): the field every frame shares, loaded once. Cache
# entries are written once and moved in whole, so a folder with the same files' times and sizes holds
# the same data.
def file_stamps(folder: Path) -> tuple:
    """(name, mtime_ns, size) of each file in ``folder``: the key of what was loaded from it."""
    return tuple(sorted((e.name, e.stat().st_mtime_ns, e.stat().st_size) for e in os.scandir(folder) if e.is_file()))


@functools.lru_cache(maxsize=2)
def field(folder: Path, stamps: tuple) -> tuple["SDFGrid", list[tuple["SDFGrid", RigidMotion]]]:
    """The static SDF and the moving walls' fields of an sdf artifact (``stamps``: file_stamps of ``folder``)."""
    return SDFGrid.load(folder), load_bodies(folder)


def load_bodies(folder: Path) -> list[tuple[SDFGrid, RigidMotion]]:
    """The moving walls sdf_bake baked apart from ``sdf.npz``: per moving wall (in walls.json order) its
    field in its rest pose and its motion. A point x at time t is sampled at the body's rest position
    ``motion.to_rest(x, t)`` (R^T (x - pivot - T) + pivot), and the normal found there turns back with R.
    Empty when no wall moves."""
    info = Path(folder) / BODIES_FILE
    if not info.is_file():
        return []
    return [(SDFGrid.load_file(Path(folder) / b["file"]), RigidMotion.from_json(b["motion"]))
            for b in json.loads(info.read_text())]


def body_walls(folder: Path) -> list[int]:
    """Each moving wall's index in walls.json (and the config's walls), in load_bodies' order."""
    info = Path(folder) / BODIES_FILE
    return [int(b["wall"]) for b in json.loads(info.read_text())] if info.is_file() else []


def posed_field(static: SDFGrid, bodies: list[tuple[SDFGrid, RigidMotion]], t: float) -> SDFGrid:
    """One grid for a consumer that takes one field (surface_extract): ``static`` with every moving wall
    at time ``t`` (s) folded in by the minimum, each body sampled at the nodes' rest positions in its
    frame (trilinear on trilinear: exact on flat faces, corners rounded within a cell). ``static``
    itself when no wall moves."""
    if not bodies:
        return static
    dist = static.dist.copy()
    changed = []  # the node blocks the bodies changed, a node wider: where the slopes can differ from static's
    for grid, motion in bodies:
        # only the static nodes within the body's grid box where it stands at t (its field beyond that box
        # is the clamped border value, at least the band: the minimum leaves those nodes as they are)
        lo, hi = grid.origin, grid.upper
        corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
        world = motion.to_world(corners, t)
        i0 = np.clip(np.floor((world.min(axis=0) - static.origin) / static.spacing).astype(int), 0, np.array(dist.shape) - 1)
        i1 = np.clip(np.ceil((world.max(axis=0) - static.origin) / static.spacing).astype(int) + 1, 0, np.array(dist.shape))
        ny, nz = i1[1] - i0[1], i1[2] - i0[2]
        if np.any(i1 <= i0):
            continue
        j, k = np.meshgrid(np.arange(i0[1], i1[1]), np.arange(i0[2], i1[2]), indexing="ij")
        plane = np.stack([np.zeros(j.size), j.ravel(), k.ravel()], axis=1) * static.spacing + static.origin
        d = np.empty(len(plane), np.float64)
        n = np.empty((len(plane), 3), np.float64)
        for i in range(i0[0], i1[0]):  # one x-slab at a time: a few MB whatever the grid
            plane[:, 0] = static.origin[0] + i * static.spacing
            sdf_sample_many(grid.dist, grid.origin, 1.0 / grid.spacing, np.ascontiguousarray(motion.to_rest(plane, t)), d, n)
            block = dist[i, i0[1]:i1[1], i0[2]:i1[2]]
            np.minimum(block, np.clip(d, -static.band, static.band).reshape(ny, nz).astype(np.float32), out=block)
        changed.append(tuple(slice(max(a - 1, 0), b + 1) for a, b in zip(i0, i1)))
    posed = SDFGrid(static.origin, static.spacing, dist, static.band, static.shell_thickness)
    slopes = static.axis_slopes()  # and the changed blocks' own, not a pass over the whole grid every frame
    for block in changed:
        slopes = np.maximum(slopes, SDFGrid(static.origin, static.spacing, dist[block], static.band).axis_slopes())
    posed._slopes = slopes
    return posed


@nb.njit(cache=True, inline="always")
def sdf_sample(dist, ox, oy, oz, inv_h, x, y, z):
    """Trilinear distance and the normalised gradient of the trilinear interpolant at (x, y, z).

    Points outside the grid are clamped onto it (the grid covers the domain plus a margin, so only
    escaping particles get there). Returns (d, nx, ny, nz). Allocation-free; safe in prange loops.
    """
    nx, ny, nz = dist.shape
    fx = (x - ox) * inv_h
    fy = (y - oy) * inv_h
    fz = (z - oz) * inv_h
    fx = min(max(fx, 0.0), nx - 1.000001)
    fy = min(max(fy, 0.0), ny - 1.000001)
    fz = min(max(fz, 0.0), nz - 1.000001)
    i = int(fx)
    j = int(fy)
    k = int(fz)
    tx = fx - i
    ty = fy - j
    tz = fz - k
    c000 = dist[i, j, k]
    c100 = dist[i + 1, j, k]
    c010 = dist[i, j + 1, k]
    c110 = dist[i + 1, j + 1, k]
    c001 = dist[i, j, k + 1]
    c101 = dist[i + 1, j, k + 1]
    c011 = dist[i, j + 1, k + 1]
    c111 = dist[i + 1, j + 1, k + 1]
    # interpolate along x, then y, then z; derivatives by the product rule
    c00 = c000 + (c100 - c000) * tx
    c10 = c010 + (c110 - c010) * tx
    c01 = c001 + (c101 - c001) * tx
    c11 = c011 + (c111 - c011) * tx
    c0 = c00 + (c10 - c00) * ty
    c1 = c01 + (c11 - c01) * ty
    d = c0 + (c1 - c0) * tz
    dx00 = c100 - c000
    dx10 = c110 - c010
    dx01 = c101 - c001
    dx11 = c111 - c011
    dx0 = dx00 + (dx10 - dx00) * ty
    dx1 = dx01 + (dx11 - dx01) * ty
    gx = dx0 + (dx1 - dx0) * tz
    gy0 = c10 - c00
    gy1 = c11 - c01
    gy = gy0 + (gy1 - gy0) * tz
    gz = c1 - c0
    norm = np.sqrt(gx * gx + gy * gy + gz * gz)
    if norm > 1e-12:
        gx /= norm
        gy /= norm
        gz /= norm
    else:
        gx = 0.0
        gy = 0.0
        gz = 0.0
    return d, gx, gy, gz


@nb.njit(cache=True, parallel=True)
def sdf_sample_many(dist, origin, inv_h, points, out_d, out_n):
    """Sample ``points`` (N, 3) into ``out_d`` (N,) and ``out_n`` (N, 3); no allocation."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    for p in nb.prange(points.shape[0]):
        d, gx, gy, gz = sdf_sample(dist, ox, oy, oz, inv_h, points[p, 0], points[p, 1], points[p, 2])
        out_d[p] = d
        out_n[p, 0] = gx
        out_n[p, 1] = gy
        out_n[p, 2] = gz


def grid_from_function(fn, lo, hi, spacing: float, band: float | None = None) -> SDFGrid:
    """Bake an SDFGrid from an analytic vectorised signed distance ``fn(points) -> d`` (tests, builtin
    shapes). ``lo``/``hi`` are the corners to cover; the grid is padded by one cell."""
    lo = np.asarray(lo, np.float64) - spacing
    hi = np.asarray(hi, np.float64) + spacing
    n = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = [lo[a] + spacing * np.arange(n[a]) for a in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    d = fn(np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)).reshape(X.shape)
    band = float(band) if band is not None else float(np.abs(d).max())
    d = np.clip(d, -band, band)
    return SDFGrid(origin=lo, spacing=float(spacing), dist=np.ascontiguousarray(d, np.float32), band=band)


def box_interior_sdf(lo, hi):
    """Signed distance, positive inside the box [lo, hi] (a closed tank), exact everywhere."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)

    def fn(p: np.ndarray) -> np.ndarray:
        c = 0.5 * (lo + hi)
        e = 0.5 * (hi - lo)
        q = np.abs(p - c) - e
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return -(outside + inside)

    return fn
