"""3D wall maps: the wall density, wall pressure-gradient and wall viscosity terms of eq. 11-15
precomputed on a grid from the SDF (the "density map" improvement PHYSICS.md names), so edges and
corners, where two or three walls are within h, count every wall and not only the nearest plane.

Each node integrates the kernels over the wall region {d < 0} inside its support with a quadrature
lattice of spacing l0/2 (the wall particles of eq. 12 and 15 smeared into a continuum), then a 1D
factor per wall distance makes the flat-wall value equal the lattice-sum table of walls/tables.py
exactly (so a particle l0/2 above a flat floor gets rho0, as with the 1D tables).

Channels: 0 Z_rho (kg/m^3), 1-3 wall pressure direction G = (m/rho0) sum -grad W (1/m, eq. 6, 8),
4 Z_vis (1/m^2, eq. 15)."""
from __future__ import annotations

import math
from collections import namedtuple

import numba as nb
import numpy as np

from stages.common.sdf import SDFGrid, sdf_sample

from numba.core import types
from numba.extending import overload

from ..kernels import poly6_coef, spiky_grad_coef, visc_lap_coef
from .tables import build_tables, table_lookup


@nb.njit(cache=True, inline="always")
def wall_weight(d, half_width):
    """Smooth occupancy of the wall region (1 deep inside, 0 in the fluid)."""
    t = 0.5 - d / (2.0 * half_width)
    return min(max(t, 0.0), 1.0)


def quadrature_stencil(h: float, dq: float, scale: float, mass: float, rho0: float, kernel=None):
    """The quadrature of the wall region as a stencil on the staggered lattice of spacing ``dq``
    (points half a cell off the nodes): (idx, w), a node's map = sum_s occ(node + idx_s + 1/2) w_s with
    occ the wall occupancy (wall_weight) there. ``kernel(r) -> (W, f)``, -grad W = -f o pointing from the
    wall sample at offset o to the node, gives channels 0-3 (default Poly6 and Spiky); channel 4 is the
    viscosity Laplacian. ``scale``: the quadrature volume in units of one wall particle's."""
    k = int(math.ceil(h / dq)) + 1
    m = np.arange(-k, k)
    idx = np.stack([g.ravel() for g in np.meshgrid(m, m, m, indexing="ij")], 1)
    o = (idx + 0.5) * dq  # cell-centred, symmetric about 0
    r = np.linalg.norm(o, axis=1)
    keep = r < h
    idx, o, r = idx[keep], o[keep], r[keep]
    if kernel is None:
        W = mass * poly6_coef(h) * (h * h - r * r) ** 3
        f = (mass / rho0) * spiky_grad_coef(h) * (h - r) ** 2 / r
    else:
        W, f = kernel(r)
    w = np.empty((len(r), 5))
    w[:, 0] = scale * W
    w[:, 1:4] = -scale * f[:, None] * o
    w[:, 4] = scale * (mass / rho0) * visc_lap_coef(h) * (h - r)
    return np.ascontiguousarray(idx.astype(np.int64)), np.ascontiguousarray(w)


def flat_wall_sums(idx: np.ndarray, w: np.ndarray, dq: float, r: np.ndarray) -> np.ndarray:
    """The stencil's sums (len(r), 5) at a node a height r above the flat floor z = 0 (the wall below it)."""
    out = np.zeros((len(r), w.shape[1]))
    for s, ri in enumerate(r):
        out[s] = np.clip(0.5 - (ri + (idx[:, 2] + 0.5) * dq) / dq, 0.0, 1.0) @ w  # wall_weight(d, dq / 2)
    return out


def flat_wall_factors(l0: float, h: float, mass: float, rho0: float, samples: int):
    """(fix_rho, fix_press, fix_vis, inv_dr): per wall distance over [0, h], the lattice-sum table of
    walls/tables.py over the map's quadrature of a half space (they do not depend on the SDF)."""
    dq = 0.5 * l0
    idx, w = quadrature_stencil(h, dq, dq ** 3 / l0 ** 3, mass, rho0)
    _, z_rho, z_vis, z_press = build_tables(l0, h, mass, rho0, samples)
    flat = flat_wall_sums(idx, w, dq, np.linspace(0.0, h, samples))
    fix_rho = np.where(flat[:, 0] > 1e-12, z_rho / np.maximum(flat[:, 0], 1e-300), 1.0)
    fix_press = np.where(flat[:, 3] > 1e-12, z_press / np.maximum(flat[:, 3], 1e-300), 1.0)
    fix_vis = np.where(flat[:, 4] > 1e-12, z_vis / np.maximum(flat[:, 4], 1e-300), 1.0)
    return fix_rho, fix_press, fix_vis, (samples - 1) / h


@nb.njit(cache=True, inline="always")
def map_sample(maps, ox, oy, oz, inv_h, x, y, z, c):
    """Trilinear value of channel ``c`` of a node-centred (nx, ny, nz, C) map (clamped to the grid)."""
    nx, ny, nz = maps.shape[0], maps.shape[1], maps.shape[2]
    fx = min(max((x - ox) * inv_h, 0.0), nx - 1.000001)
    fy = min(max((y - oy) * inv_h, 0.0), ny - 1.000001)
    fz = min(max((z - oz) * inv_h, 0.0), nz - 1.000001)
    i = int(fx)
    j = int(fy)
    k = int(fz)
    tx = fx - i
    ty = fy - j
    tz = fz - k
    c00 = maps[i, j, k, c] + (maps[i + 1, j, k, c] - maps[i, j, k, c]) * tx
    c10 = maps[i, j + 1, k, c] + (maps[i + 1, j + 1, k, c] - maps[i, j + 1, k, c]) * tx
    c01 = maps[i, j, k + 1, c] + (maps[i + 1, j, k + 1, c] - maps[i, j, k + 1, c]) * tx
    c11 = maps[i, j + 1, k + 1, c] + (maps[i + 1, j + 1, k + 1, c] - maps[i, j + 1, k + 1, c]) * tx
    c0 = c00 + (c10 - c00) * ty
    c1 = c01 + (c11 - c01) * ty
    return c0 + (c1 - c0) * tz



BRICK = 4  # wall-map brick edge, in nodes


# -- wall maps stored as bricks (memory) ------------------------------------------------------------
# A dense wall map (WallMaps) covers the whole SDF box at l0/2 with 5 float32 channels, 1.3 KB per
# particle in the PEERS dam break, yet it is non-zero only within h + l0/2 of a wall. The bricked form
# keeps only the BRICK^3-node blocks that hold a node of that band: the same node values (the same
# quadrature_stencil) and the same trilinear arithmetic, so every lookup returns the same bits as the
# dense map. ``wmap`` arguments below take either form.

@nb.njit(cache=True, parallel=True)
def bricks_needed(sdf, so, sinv, mo, mh, shape, reach, need):
    """need[bx, by, bz] = 1 if any node of the brick has SDF distance < reach (a non-zero map value)."""
    nbx, nby, nbz = need.shape
    for b in nb.prange(nbx * nby * nbz):
        bx = b // (nby * nbz)
        by = (b // nbz) % nby
        bz = b % nbz
        hit = 0
        for i in range(bx * BRICK, min(bx * BRICK + BRICK, shape[0])):
            for j in range(by * BRICK, min(by * BRICK + BRICK, shape[1])):
                for k in range(bz * BRICK, min(bz * BRICK + BRICK, shape[2])):
                    d, _, _, _ = sdf_sample(sdf, so[0], so[1], so[2], sinv, mo[0] + i * mh, mo[1] + j * mh,
                                            mo[2] + k * mh)
                    if d < reach:
                        hit = 1
        need[bx, by, bz] = hit


@nb.njit(cache=True, parallel=True)
def build_bricks(sdf, so, sinv, mo, mh, shape, index, slots, reach, idx, w, bricks):
    """Fill every allocated brick (slots[s] = its flat brick index): a node closer to a wall than ``reach``
    gets the stencil's sum (quadrature_stencil) over the wall occupancy on the staggered lattice, sampled
    once per brick with its halo (not once per node and offset: the halo is 5x the brick, the stencil
    ~500 offsets); the others are zero."""
    nby, nbz = index.shape[1], index.shape[2]
    lo = 0
    hi = 0
    for s in range(idx.shape[0]):
        lo = min(lo, idx[s, 0], idx[s, 1], idx[s, 2])
        hi = max(hi, idx[s, 0], idx[s, 1], idx[s, 2])
    n = BRICK + hi - lo
    for s in nb.prange(slots.shape[0]):
        b = slots[s]
        i0 = (b // (nby * nbz)) * BRICK
        j0 = ((b // nbz) % nby) * BRICK
        k0 = (b % nbz) * BRICK
        occ = np.empty((n, n, n))
        for a in range(n):
            x = mo[0] + (i0 + lo + a + 0.5) * mh
            for c in range(n):
                y = mo[1] + (j0 + lo + c + 0.5) * mh
                for e in range(n):
                    d, _, _, _ = sdf_sample(sdf, so[0], so[1], so[2], sinv, x, y, mo[2] + (k0 + lo + e + 0.5) * mh)
                    occ[a, c, e] = wall_weight(d, 0.5 * mh)
        for a in range(BRICK):
            for c in range(BRICK):
                for e in range(BRICK):
                    for ch in range(5):
                        bricks[s, a, c, e, ch] = 0.0
                    i = i0 + a
                    j = j0 + c
                    k = k0 + e
                    if i >= shape[0] or j >= shape[1] or k >= shape[2]:
                        continue
                    d, _, _, _ = sdf_sample(sdf, so[0], so[1], so[2], sinv, mo[0] + i * mh, mo[1] + j * mh, mo[2] + k * mh)
                    if d >= reach:
                        continue
                    o0 = o1 = o2 = o3 = o4 = 0.0
                    for t in range(idx.shape[0]):
                        o = occ[a - lo + idx[t, 0], c - lo + idx[t, 1], e - lo + idx[t, 2]]
                        if o > 0.0:
                            o0 += o * w[t, 0]
                            o1 += o * w[t, 1]
                            o2 += o * w[t, 2]
                            o3 += o * w[t, 3]
                            o4 += o * w[t, 4]
                    bricks[s, a, c, e, 0] = o0
                    bricks[s, a, c, e, 1] = o1
                    bricks[s, a, c, e, 2] = o2
                    bricks[s, a, c, e, 3] = o3
                    bricks[s, a, c, e, 4] = o4


@nb.njit(cache=True, inline="always")
def _node(index, bricks, i, j, k, c):
    s = index[i // BRICK, j // BRICK, k // BRICK]
    if s < 0:
        return np.float32(0.0)
    return bricks[s, i % BRICK, j % BRICK, k % BRICK, c]


@nb.njit(cache=True, inline="always")
def _trilinear(m000, m100, m010, m110, m001, m101, m011, m111, tx, ty, tz):
    """maps.map_sample's arithmetic, operation for operation (so the same bits)."""
    c00 = m000 + (m100 - m000) * tx
    c10 = m010 + (m110 - m010) * tx
    c01 = m001 + (m101 - m001) * tx
    c11 = m011 + (m111 - m011) * tx
    c0 = c00 + (c10 - c00) * ty
    c1 = c01 + (c11 - c01) * ty
    return c0 + (c1 - c0) * tz


@nb.njit(cache=True, inline="always")
def _cell(shape, ox, oy, oz, inv_h, x, y, z):
    fx = min(max((x - ox) * inv_h, 0.0), shape[0] - 1.000001)
    fy = min(max((y - oy) * inv_h, 0.0), shape[1] - 1.000001)
    fz = min(max((z - oz) * inv_h, 0.0), shape[2] - 1.000001)
    i = int(fx)
    j = int(fy)
    k = int(fz)
    return i, j, k, fx - i, fy - j, fz - k


@nb.njit(cache=True, inline="always")
def _slot(index, i, j, k):
    return index[i // BRICK, j // BRICK, k // BRICK]


@nb.njit(cache=True, inline="always")
def _at(bricks, s, i, j, k, c):
    if s < 0:
        return np.float32(0.0)  # a brick that is not stored: all its nodes are 0 in the dense map
    return bricks[s, i % BRICK, j % BRICK, k % BRICK, c]


@nb.njit(cache=True, inline="always")
def brick_sample(index, bricks, shape, ox, oy, oz, inv_h, x, y, z, c):
    """maps.map_sample of the dense map, read from its bricks (bitwise the same value)."""
    i, j, k, tx, ty, tz = _cell(shape, ox, oy, oz, inv_h, x, y, z)
    s000 = _slot(index, i, j, k)
    s100 = _slot(index, i + 1, j, k)
    s010 = _slot(index, i, j + 1, k)
    s110 = _slot(index, i + 1, j + 1, k)
    s001 = _slot(index, i, j, k + 1)
    s101 = _slot(index, i + 1, j, k + 1)
    s011 = _slot(index, i, j + 1, k + 1)
    s111 = _slot(index, i + 1, j + 1, k + 1)
    return _trilinear(_at(bricks, s000, i, j, k, c), _at(bricks, s100, i + 1, j, k, c),
                      _at(bricks, s010, i, j + 1, k, c), _at(bricks, s110, i + 1, j + 1, k, c),
                      _at(bricks, s001, i, j, k + 1, c), _at(bricks, s101, i + 1, j, k + 1, c),
                      _at(bricks, s011, i, j + 1, k + 1, c), _at(bricks, s111, i + 1, j + 1, k + 1, c), tx, ty, tz)


@nb.njit(cache=True, inline="always")
def brick_sample_1234(index, bricks, shape, ox, oy, oz, inv_h, x, y, z):
    """Channels 1-4 (wall pressure direction, Z_vis) at once: the brick slots are looked up once."""
    i, j, k, tx, ty, tz = _cell(shape, ox, oy, oz, inv_h, x, y, z)
    s000 = _slot(index, i, j, k)
    s100 = _slot(index, i + 1, j, k)
    s010 = _slot(index, i, j + 1, k)
    s110 = _slot(index, i + 1, j + 1, k)
    s001 = _slot(index, i, j, k + 1)
    s101 = _slot(index, i + 1, j, k + 1)
    s011 = _slot(index, i, j + 1, k + 1)
    s111 = _slot(index, i + 1, j + 1, k + 1)
    out1 = 0.0
    out2 = 0.0
    out3 = 0.0
    out4 = 0.0
    for c in range(1, 5):
        v = _trilinear(_at(bricks, s000, i, j, k, c), _at(bricks, s100, i + 1, j, k, c),
                       _at(bricks, s010, i, j + 1, k, c), _at(bricks, s110, i + 1, j + 1, k, c),
                       _at(bricks, s001, i, j, k + 1, c), _at(bricks, s101, i + 1, j, k + 1, c),
                       _at(bricks, s011, i, j + 1, k + 1, c), _at(bricks, s111, i + 1, j + 1, k + 1, c), tx, ty, tz)
        if c == 1:
            out1 = v
        elif c == 2:
            out2 = v
        elif c == 3:
            out3 = v
        else:
            out4 = v
    return out1, out2, out3, out4


def wall_sample_1234(wmap, ox, oy, oz, inv_h, x, y, z):
    """Channels 1-4 of the wall map at (x, y, z), either form of ``wmap``."""


@overload(wall_sample_1234)
def _wall_sample_1234(wmap, ox, oy, oz, inv_h, x, y, z):
    if isinstance(wmap, types.Array):
        def dense(wmap, ox, oy, oz, inv_h, x, y, z):
            return (map_sample(wmap, ox, oy, oz, inv_h, x, y, z, 1), map_sample(wmap, ox, oy, oz, inv_h, x, y, z, 2),
                    map_sample(wmap, ox, oy, oz, inv_h, x, y, z, 3), map_sample(wmap, ox, oy, oz, inv_h, x, y, z, 4))
        return dense
    return lambda wmap, ox, oy, oz, inv_h, x, y, z: brick_sample_1234(wmap[0], wmap[1], wmap[2], ox, oy, oz, inv_h,
                                                                      x, y, z)


def wall_sample(wmap, ox, oy, oz, inv_h, x, y, z, c):
    """Channel c of the wall map at (x, y, z): ``wmap`` the dense (nx, ny, nz, 5) array or the bricked
    form (index, bricks, shape); chosen at compile time."""


@overload(wall_sample)
def _wall_sample(wmap, ox, oy, oz, inv_h, x, y, z, c):
    if isinstance(wmap, types.Array):
        return lambda wmap, ox, oy, oz, inv_h, x, y, z, c: map_sample(wmap, ox, oy, oz, inv_h, x, y, z, c)
    return lambda wmap, ox, oy, oz, inv_h, x, y, z, c: brick_sample(wmap[0], wmap[1], wmap[2], ox, oy, oz, inv_h,
                                                                    x, y, z, c)


@nb.njit(cache=True)  # called, not inlined: the DFSPH density pass calls it 7 times (compile time)
def map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, x, y, z):
    """Z_rho of one wall field at a point (eq. 12): its 3D map times the flat-wall factor at its SDF distance
    (DFSPH's density and wall gradient differentiate it)."""
    dw, _, _, _ = sdf_sample(sdf, sdf_o[0], sdf_o[1], sdf_o[2], sdf_inv, x, y, z)
    if dw >= h:
        return 0.0
    return wall_sample(wmap, wo[0], wo[1], wo[2], winv, x, y, z, 0) * table_lookup(fix_rho, dw, inv_dr)


# -- the walls as the WCSPH kernels take them -------------------------------------------------------------
# ``Walls``: the static walls (their SDF and bricked map) and the moving rigid walls, each baked once in its
# own rest frame and sampled at the particle's position carried into that frame by the body's current pose.
# Numba's parallel loops take a named tuple of arrays but not nested tuples, so the bodies are an atlas:
# their SDF grids and brick indices concatenated flat (``b_grid`` / ``b_igrid`` rows: offset, nx, ny, nz),
# their bricks in one array; no body = empty arrays (the loops over them do nothing). The flat-wall tables
# depend only on l0 and h, so every field shares them.
# ``pose`` (bodies, POSE_SIZE) float64, rewritten in place each step (set_pose): R row-major (0:9), the
# pivot's current world position c (9:12), its rest position p0 (12:15), the pivot's velocity (15:18), the
# angular velocity (18:21): x_local = R^T (x - c) + p0 and the wall's velocity at x is v + omega x (x - c).
# The functions below that take the whole bundle are called, not inlined: the force kernel calls
# wall_density six times, and inlining each with its loop over the bodies made its build minutes long.
Walls = namedtuple("Walls", "sdf sdf_o sdf_inv index bricks shape wo winv fix_rho inv_dr "
                            "b_sdf b_grid b_sdf_o b_sdf_inv b_index b_igrid b_bricks b_shape b_wo b_winv pose")
POSE_SIZE = 21


def body_fields(grids) -> tuple:
    """(b_sdf, b_grid, b_sdf_o, b_sdf_inv, pose) of a walls bundle: the moving walls' SDFGrids (each in its rest
    frame) as one atlas, posed at rest until set_pose. Every solver's bundle has these fields, so to_body,
    body_sample and bodies_push_out serve them all."""
    n = len(grids)
    grid, offs = [], [0]
    for sb in grids:
        grid.append([offs[-1], *sb.dist.shape])
        offs.append(offs[-1] + sb.dist.size)
    pose = np.zeros((n, POSE_SIZE))
    pose[:, [0, 4, 8]] = 1.0
    for k, sb in enumerate(grids):  # at rest: c = p0 = the box's lower corner (any point will do)
        pose[k, 9:12] = pose[k, 12:15] = sb.origin
    dist = np.concatenate([sb.dist.ravel() for sb in grids]).astype(np.float32) if grids else np.zeros(0, np.float32)
    return (dist, np.array(grid, np.int64).reshape(n, 4), np.array([sb.origin for sb in grids], np.float64).reshape(n, 3),
            np.array([1.0 / sb.spacing for sb in grids], np.float64), pose)


def make_walls(sdf, maps, bodies=()) -> Walls:
    """The Walls of the static SDFGrid (SI) and its BrickWallMaps; ``bodies``: (SDFGrid in its rest frame,
    its BrickWallMaps) per moving wall, posed at rest until set_pose. Without moving walls ``pose`` is None:
    the kernels' moving-wall terms are then pruned by numba, not compiled (~10 s of a cold run)."""
    igrids, ioffs, nbricks = [], [0], 0
    index = []
    for sb, mb in bodies:
        igrids.append([ioffs[-1], *mb.index.shape])
        ioffs.append(ioffs[-1] + mb.index.size)
        index.append(np.where(mb.index >= 0, mb.index + nbricks, -1).astype(np.int32).ravel())
        nbricks += len(mb.bricks)
    n = len(bodies)
    b_sdf, b_grid, b_sdf_o, b_sdf_inv, pose = body_fields([sb for sb, _ in bodies])
    cat = (lambda xs, dt, shape: np.concatenate(xs).astype(dt) if xs else np.zeros(shape, dt))
    return Walls(sdf.dist, np.asarray(sdf.origin, np.float64), 1.0 / sdf.spacing, maps.index, maps.bricks,
                 np.asarray(maps.shape, np.int64), np.asarray(maps.origin, np.float64), 1.0 / maps.spacing, maps.fix_rho,
                 maps.inv_dr, b_sdf, b_grid, b_sdf_o, b_sdf_inv,
                 cat(index, np.int32, (0,)), np.array(igrids, np.int64).reshape(n, 4),
                 cat([mb.bricks for _, mb in bodies], np.float32, (0, BRICK, BRICK, BRICK, 5)),
                 np.array([mb.shape for _, mb in bodies], np.int64).reshape(n, 3),
                 np.array([mb.origin for _, mb in bodies], np.float64).reshape(n, 3),
                 np.array([1.0 / mb.spacing for _, mb in bodies], np.float64), pose if n else None)


def set_pose(walls: Walls, k: int, R, T, pivot, v, omega) -> None:
    """Body k at world = R (x_rest - pivot) + pivot + T, moving with the pivot's velocity v and angular
    velocity omega (stages.common.motion.RigidMotion.pose / velocity, in SI)."""
    p = walls.pose[k]
    p[0:9] = np.asarray(R, np.float64).ravel()
    p[9:12] = np.asarray(pivot, np.float64) + np.asarray(T, np.float64)
    p[12:15] = pivot
    p[15:18] = v
    p[18:21] = omega


@nb.njit(cache=True, inline="always")
def to_body(pose, x, y, z):
    """A world point in the body's rest frame: R^T (x - c) + p0."""
    dx = x - pose[9]
    dy = y - pose[10]
    dz = z - pose[11]
    return (pose[0] * dx + pose[3] * dy + pose[6] * dz + pose[12], pose[1] * dx + pose[4] * dy + pose[7] * dz + pose[13],
            pose[2] * dx + pose[5] * dy + pose[8] * dz + pose[14])


@nb.njit(cache=True, inline="always")
def body_direction(pose, gx, gy, gz):
    """A direction of the body's rest frame in the world: R g."""
    return (pose[0] * gx + pose[1] * gy + pose[2] * gz, pose[3] * gx + pose[4] * gy + pose[5] * gz,
            pose[6] * gx + pose[7] * gy + pose[8] * gz)


@nb.njit(cache=True, inline="always")
def body_velocity(pose, x, y, z):
    """The wall's velocity at world point x: v + omega x (x - c)."""
    rx = x - pose[9]
    ry = y - pose[10]
    rz = z - pose[11]
    return (pose[15] + pose[19] * rz - pose[20] * ry, pose[16] + pose[20] * rx - pose[18] * rz,
            pose[17] + pose[18] * ry - pose[19] * rx)


@nb.njit(cache=True, inline="always")
def _body_sdf(w, k):
    o, nx, ny, nz = w.b_grid[k, 0], w.b_grid[k, 1], w.b_grid[k, 2], w.b_grid[k, 3]
    return w.b_sdf[o:o + nx * ny * nz].reshape((nx, ny, nz))


@nb.njit(cache=True, inline="always")
def _body_index(w, k):
    o, nx, ny, nz = w.b_igrid[k, 0], w.b_igrid[k, 1], w.b_igrid[k, 2], w.b_igrid[k, 3]
    return w.b_index[o:o + nx * ny * nz].reshape((nx, ny, nz))


@nb.njit(cache=True, inline="always")
def body_distance(w, k, lx, ly, lz):
    """(d, gx, gy, gz) of body k at a point of its rest frame (gradient in that frame)."""
    so = w.b_sdf_o[k]
    return sdf_sample(_body_sdf(w, k), so[0], so[1], so[2], w.b_sdf_inv[k], lx, ly, lz)


@nb.njit(cache=True, inline="always")
def body_sample(w, k, x, y, z):
    """(d, nx, ny, nz) of body k at world point x: its SDF in its rest frame, the normal in the world."""
    pose = w.pose[k]
    lx, ly, lz = to_body(pose, x, y, z)
    d, gx, gy, gz = body_distance(w, k, lx, ly, lz)
    nx, ny, nz = body_direction(pose, gx, gy, gz)
    return d, nx, ny, nz


@nb.njit(cache=True, inline="always")
def body_map(w, k, lx, ly, lz, c):
    """Channel c of body k's wall map at a point of its rest frame."""
    wo = w.b_wo[k]
    return brick_sample(_body_index(w, k), w.b_bricks, w.b_shape[k], wo[0], wo[1], wo[2], w.b_winv[k], lx, ly, lz, c)


@nb.njit(cache=True)
def wall_density(w, h, x, y, z):
    """Z_rho of every wall at a point (eq. 12): the static walls' map and each moving wall's, each times
    the flat-wall factor at its own SDF distance (the WCSPH density adds it, its wall force differentiates it)."""
    dw, _, _, _ = sdf_sample(w.sdf, w.sdf_o[0], w.sdf_o[1], w.sdf_o[2], w.sdf_inv, x, y, z)
    s = 0.0
    if dw < h:
        s = brick_sample(w.index, w.bricks, w.shape, w.wo[0], w.wo[1], w.wo[2], w.winv, x, y, z, 0) * table_lookup(
            w.fix_rho, dw, w.inv_dr)
    return s + bodies_density(w, w.pose, h, x, y, z)


@nb.njit(cache=True)
def bodies_density(w, pose, h, x, y, z):
    """The moving walls' share of wall_density."""
    if pose is None:  # no moving walls: numba prunes the rest (not compiled)
        return 0.0
    s = 0.0
    for k in range(pose.shape[0]):
        lx, ly, lz = to_body(pose[k], x, y, z)
        db, _, _, _ = body_distance(w, k, lx, ly, lz)
        if db < h:
            s += body_map(w, k, lx, ly, lz, 0) * table_lookup(w.fix_rho, db, w.inv_dr)
    return s


@nb.njit(cache=True)
def bodies_nearest(w, pose, x, y, z, d, nx, ny, nz):
    """(d, nx, ny, nz) of the nearest wall: the given static wall's, or a moving wall's if nearer."""
    if pose is None:  # no moving walls: numba prunes the rest (not compiled)
        return d, nx, ny, nz
    for k in range(pose.shape[0]):
        db, bx, by, bz = body_sample(w, k, x, y, z)
        if db < d:
            d, nx, ny, nz = db, bx, by, bz
    return d, nx, ny, nz


@nb.njit(cache=True)
def nearest_wall_velocity(w, pose, d, x, y, z):
    """The velocity at x of the nearest wall, given ``d`` its distance (bodies_nearest's): the nearest moving
    wall's if it is at that distance (to rounding: another kernel's arithmetic), else a static wall's (zero).
    The wall friction damps the velocity relative to it."""
    if pose is None:  # no moving walls: numba prunes the rest (not compiled)
        return 0.0, 0.0, 0.0
    near = -1
    best = np.inf
    for k in range(pose.shape[0]):
        lx, ly, lz = to_body(pose[k], x, y, z)
        db, _, _, _ = body_distance(w, k, lx, ly, lz)
        if db < best:
            best = db
            near = k
    if near < 0 or best > d + 1e-9 * (abs(d) + w.b_sdf_inv[near] ** -1):
        return 0.0, 0.0, 0.0
    return body_velocity(pose[near], x, y, z)


@nb.njit(cache=True)
def static_distance(w, pose, d, x, y, z):
    """The static walls' SDF distance at x, given ``d`` the nearest wall's (the same without moving walls)."""
    if pose is None:  # no moving walls: numba prunes the rest (not compiled)
        return d
    if pose.shape[0] == 0:
        return d
    ds, _, _, _ = sdf_sample(w.sdf, w.sdf_o[0], w.sdf_o[1], w.sdf_o[2], w.sdf_inv, x, y, z)
    return ds


@nb.njit(cache=True)
def bodies_viscous(w, pose, fix_vis, h, x, y, z, vx, vy, vz):
    """sum over the moving walls within h of fix_vis(d_b) Z_vis,b (v_b(x) - v): the no-slip term of eq. 13-15
    against each wall's own velocity."""
    if pose is None:  # no moving walls: numba prunes the rest (not compiled)
        return 0.0, 0.0, 0.0
    ax = 0.0
    ay = 0.0
    az = 0.0
    for k in range(pose.shape[0]):
        lx, ly, lz = to_body(pose[k], x, y, z)
        db, _, _, _ = body_distance(w, k, lx, ly, lz)
        if db < h:
            c = table_lookup(fix_vis, db, w.inv_dr) * body_map(w, k, lx, ly, lz, 4)
            ux, uy, uz = body_velocity(pose[k], x, y, z)
            ax += c * (ux - vx)
            ay += c * (uy - vy)
            az += c * (uz - vz)
    return ax, ay, az


@nb.njit(cache=True, inline="always")
def facing(nx, ny, nz, mx, my, mz):
    """n . m where the wall of normal n faces the last one pushed out (normal m): an acute V, normals more
    than 90 degrees apart; else 0 (orthogonal or no last wall; antiparallel, a slot thinner than 2 r_rep,
    has no room for both)."""
    c = nx * mx + ny * my + nz * mz
    return c if -0.999 < c < -1e-3 else 0.0


@nb.njit(cache=True, inline="always")
def push_move(nx, ny, nz, mx, my, mz, need, max_corr):
    """One eq. 16 projection's move (corr, ex, ey, ez) for a wall of normal n that is ``need`` short of
    r_rep, m the last projection's normal (0 for the first): along n by need, or, where the wall faces
    the last one (an acute V: normals more than 90 degrees apart), along n's part orthogonal to m by as
    much as the distance needs, so the last wall stays satisfied: the projection onto both (a particle
    in a 20 degree V's apex, pushed back and forth between its sides, stayed inside them). Orthogonal
    normals (right-angled edges, corners) move along n, bitwise as before; at most max_corr."""
    c = facing(nx, ny, nz, mx, my, mz)
    if c != 0.0:
        ex = nx - c * mx
        ey = ny - c * my
        ez = nz - c * mz
        gain = math.sqrt(ex * ex + ey * ey + ez * ez)  # sqrt(1 - c^2) = n . e / |e|: distance per move
        return min(need / gain, max_corr), ex / gain, ey / gain, ez / gain
    return min(need, max_corr), nx, ny, nz


@nb.njit(cache=True, inline="always")
def push_velocity(vx, vy, vz, ux, uy, uz, nx, ny, nz, mx, my, mz):
    """The eq. 16 velocity: the part into the wall of normal n (relative to the wall's velocity u) goes;
    where the wall faces the last one (normal m, an acute V as in ``push_move``) and the velocity still
    runs into that one, its part into m orthogonal to n goes too, so the particle keeps no velocity into
    the V. Orthogonal normals: bitwise the plain removal."""
    vn = (vx - ux) * nx + (vy - uy) * ny + (vz - uz) * nz
    if vn < 0.0:
        vx -= vn * nx
        vy -= vn * ny
        vz -= vn * nz
    c = facing(nx, ny, nz, mx, my, mz)
    if c != 0.0:
        vm = (vx - ux) * mx + (vy - uy) * my + (vz - uz) * mz
        if vm < 0.0:
            ex = mx - c * nx
            ey = my - c * ny
            ez = mz - c * nz
            s = vm / (ex * ex + ey * ey + ez * ez)  # along e = m - c n (e . n = 0, e . m = |e|^2): v . m -> 0
            vx -= s * ex
            vy -= s * ey
            vz -= s * ez
    return vx, vy, vz


CONTACT = 1e-3  # a particle within this share of r_rep of its push-out surface is on it (the push-out's own tolerance)


@nb.njit(cache=True)
def sdf_sample_of(w, pose, k, x, y, z):
    """(d, nx, ny, nz) at world point x of the static walls (pose None: numba prunes the other branch) or of
    moving wall k."""
    if pose is None:
        return sdf_sample(w.sdf, w.sdf_o[0], w.sdf_o[1], w.sdf_o[2], w.sdf_inv, x, y, z)
    return body_sample(w, k, x, y, z)


@nb.njit(cache=True)
def wall_velocity(pose, k, x, y, z):
    """The wall's velocity at world point x: zero for the static walls (pose None), else moving wall k's."""
    if pose is None:
        return 0.0, 0.0, 0.0
    return body_velocity(pose[k], x, y, z)


@nb.njit(cache=True, inline="always")
def contact_velocity(w, pose, k, px, py, pz, vx, vy, vz, ux, uy, uz, dw, nx, ny, nz, mx, my, mz, r_rep):
    """The velocity of a particle on its push-out surface (within CONTACT r_rep of r_rep, so not pushed) of
    wall k (``sdf_sample_of``; u its velocity there, n its normal, m the last push's): no part into the wall,
    as after a push, nor into a second wall of an edge or corner, which n does not see, found by sampling
    again CONTACT r_rep along the velocity left. Without it a particle that gravity or pressure held on a wall
    kept a dt into it until it crossed the push-out's tolerance, steps later: at rest every clamped row carried
    up to 0.03 m/s into the walls (bench_rest's tank: 0.0061 m/s at 1.5 s without it, 0.0033 with it)."""
    vx, vy, vz = push_velocity(vx, vy, vz, ux, uy, uz, nx, ny, nz, mx, my, mz)
    for _ in range(2):
        rx = vx - ux
        ry = vy - uy
        rz = vz - uz
        sp = math.sqrt(rx * rx + ry * ry + rz * rz)
        if sp == 0.0:
            break
        e = CONTACT * r_rep / sp
        dq, qx, qy, qz = sdf_sample_of(w, pose, k, px + e * rx, py + e * ry, pz + e * rz)
        if dq >= dw - 1e-6 * r_rep:  # along the walls or away from them
            break
        vx, vy, vz = push_velocity(vx, vy, vz, ux, uy, uz, qx, qy, qz, nx, ny, nz)
        nx = qx
        ny = qy
        nz = qz
    return vx, vy, vz


@nb.njit(cache=True)
def push_out(w, pose, k, px, py, pz, vx, vy, vz, r_rep, max_corr, contact):
    """Eq. 16 against the static walls (pose None) or moving wall k: a particle closer than r_rep moves out along
    the normal (at most max_corr per projection, ``push_move``; up to three projections, since in an edge or
    corner each one finds the next closest wall) and loses its velocity into the wall, relative to the wall's
    own (a moving wall pushes the fluid); with ``contact``, one left on the surface keeps none into it
    (``contact_velocity``; the SPH solvers. MPS's pressure solve takes the velocity into the walls into its
    source, and there the rule threw impact particles at 4.8 x the ballistic bound in the stability suite's
    jet). Returns the new (x, v)."""
    mx = 0.0
    my = 0.0
    mz = 0.0
    for _ in range(3):
        dw, nx, ny, nz = sdf_sample_of(w, pose, k, px, py, pz)
        if dw >= r_rep * (1.0 - CONTACT):
            if contact and dw < r_rep * (1.0 + CONTACT):
                ux, uy, uz = wall_velocity(pose, k, px, py, pz)
                vx, vy, vz = contact_velocity(w, pose, k, px, py, pz, vx, vy, vz, ux, uy, uz, dw, nx, ny, nz, mx, my, mz,
                                              r_rep)
            break
        corr, ex, ey, ez = push_move(nx, ny, nz, mx, my, mz, r_rep - dw, max_corr)
        px += corr * ex
        py += corr * ey
        pz += corr * ez
        ux, uy, uz = wall_velocity(pose, k, px, py, pz)
        vx, vy, vz = push_velocity(vx, vy, vz, ux, uy, uz, nx, ny, nz, mx, my, mz)
        mx = nx
        my = ny
        mz = nz
    return px, py, pz, vx, vy, vz


@nb.njit(cache=True)
def bodies_push_out(w, pose, px, py, pz, vx, vy, vz, r_rep, max_corr, contact):
    """Eq. 16 against every moving wall (``push_out``)."""
    if pose is None:  # no moving walls: numba prunes the rest (not compiled)
        return px, py, pz, vx, vy, vz
    for k in range(pose.shape[0]):
        px, py, pz, vx, vy, vz = push_out(w, pose, k, px, py, pz, vx, vy, vz, r_rep, max_corr, contact)
    return px, py, pz, vx, vy, vz


class BrickWallMaps:
    """WallMaps stored as bricks (BRICK^3 nodes) holding a node of the band
    d < h + l0/2 where the map is non-zero: the same node values and lookups (bitwise), without the dense array
    over the whole SDF box (1.3 KB per particle in the PEERS dam break, and built at that size).
    ``wmap`` is what the kernels take: (index, bricks, shape)."""

    every_brick = False

    def __init__(self, sdf: SDFGrid, l0: float, h: float, mass: float, rho0: float, samples: int = 256):
        # the flat-wall factors do not depend on the SDF (no dense map built, nor its kernel compiled)
        self.fix_rho, self.fix_press, self.fix_vis, self.inv_dr = flat_wall_factors(l0, h, mass, rho0, samples)
        self.h = h
        slots = self._allocate(sdf, l0, h)
        dq = self.spacing
        idx, w = quadrature_stencil(h, dq, dq ** 3 / l0 ** 3, mass, rho0)
        build_bricks(sdf.dist, sdf.origin, 1.0 / sdf.spacing, self.origin, dq, self.shape, self.index, slots, h + dq,
                     idx, w, self.bricks)

    def _allocate(self, sdf: SDFGrid, l0: float, h: float) -> np.ndarray:
        """Nodes every l0/2 over the SDF box (as WallMaps); zeroed bricks for those holding a node within
        h + l0/2 of a wall. Returns each brick's flat brick index (the fill kernel's ``slots``)."""
        self.spacing = 0.5 * l0
        self.origin = np.asarray(sdf.origin, np.float64)
        self.shape = np.floor((sdf.upper - sdf.origin) / self.spacing).astype(np.int64) + 1
        need = np.zeros(tuple(-(-self.shape // BRICK)), np.uint8)
        bricks_needed(sdf.dist, sdf.origin, 1.0 / sdf.spacing, self.origin, self.spacing, self.shape,
                      np.inf if self.every_brick else h + self.spacing, need)
        slots = np.flatnonzero(need.ravel()).astype(np.int64)
        self.index = np.full(need.shape, -1, np.int32)
        self.index.ravel()[slots] = np.arange(len(slots), dtype=np.int32)
        self.bricks = np.zeros((len(slots), BRICK, BRICK, BRICK, 5), np.float32)
        self._dense = None
        return slots

    @property
    def wmap(self) -> tuple:
        return self.index, self.bricks, self.shape

    @property
    def maps(self) -> np.ndarray:
        """The dense (nx, ny, nz, 5) map, built on first use (for code written against WallMaps)."""
        if self._dense is None:
            dense = np.zeros((*self.shape, 5), np.float32)
            B = BRICK
            for (bx, by, bz) in np.argwhere(self.index >= 0):
                b = self.bricks[self.index[bx, by, bz]]
                sx, sy, sz = (min(B, n - o) for n, o in zip(self.shape, (bx * B, by * B, bz * B)))
                dense[bx * B:bx * B + sx, by * B:by * B + sy, bz * B:bz * B + sz] = b[:sx, :sy, :sz]
            self._dense = dense
        return self._dense

    @property
    def nbytes(self) -> int:
        return self.index.nbytes + self.bricks.nbytes


class WallMaps(BrickWallMaps):
    """The dense form: every brick of the SDF box built, zeros included (``maps``; tests check that the
    bricks BrickWallMaps leaves out are zero)."""
    every_brick = True
