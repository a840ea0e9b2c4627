"""MPS walls from the distance function (PHYSICS.md "Walls for MPS": polygon wall boundary model,
Harada et al. 2008, Mitsume et al. 2015). No wall particles are stored.

The wall acts through sums over the wall particles a particle boundary would have had, with the MPS
weight w(r) = re / r - 1 (w_n with re for the number density and gradient, w_l for the Laplacian):

- Zn = sum w_n                           the wall's share of the number density n_i
- G  = sum (x_w - x_i) / r^2 w_n           gradient with a uniform wall pressure; divergence (u_w = 0)
- T  = sum (x_w - x_i)(x_w - x_i)^T / r^2 w_n   gradient with the hydrostatic part of the wall pressure
- Zl = sum w_l                           Laplacian: the no-slip viscous wall (eq. 13-15 in MPS form)
- M  = sum (x_w - x_i) w_l                 Laplacian with the hydrostatic part of the wall pressure

The wall particles carry the "resting" pressure p_w = p_i + rho g . (x_w - x_i): the particle's own
pressure extended hydrostatically into the wall (for a flat floor, rho g s deeper by s); without
gravity it is the Neumann condition p_w = p_i.

``build_tables``: the flat-wall values as 1D tables of the wall distance r, summed over virtual wall
particles on the cubic lattice of spacing l0 below the plane, first layer l0/2 behind the surface,
like the SPH tables (walls/tables.py): Zn, Zg = -G . n, Zgz = T_nn, Zl, Zlz = -M . n.

``MPSWallMaps``: every channel as a 3D map over the SDF grid (a convolution of the wall occupancy,
cheap: 0.35 s for a 0.1 x 0.1 x 0.3 m tank at l0 = 1 cm), scaled per wall distance so that on a flat
wall each equals its lattice table. A particle in a concave edge or corner then counts both or all
three walls: n/n0 on the initial lattice is 1.000 at a flat wall, 1.023 in an edge, 1.045 in a corner
(the nearest-wall table alone gives 0.79 and 0.63: those particles would be taken for free
surface, p = 0, and be pushed towards the missing wall). Convex edges and thin plates are
over-counted by a flat calibration too; the eq. 16 projection keeps every particle out of the wall."""
from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..kernels import rest_lattice
from .maps import body_direction, body_distance, body_fields, body_velocity, map_sample, to_body
from .tables import table_lookup, wall_lattice


def mps_weight_np(r: np.ndarray, re: float) -> np.ndarray:
    """w(r) = re / r - 1 for 0 < r < re, else 0 (Koshizuka and Oka 1996)."""
    r = np.asarray(r, float)
    out = np.zeros_like(r)
    m = (r > 1e-12) & (r < re)
    out[m] = re / r[m] - 1.0
    return out


def lattice_constants(l0: float, re: float) -> tuple[float, float]:
    """(n0, lambda) on the full cubic lattice around an interior particle (PHYSICS.md: re = 2.1 l0
    gives n0 = 14.42, lambda = 1.702 l0^2)."""
    _, r = rest_lattice(l0, re)
    w = mps_weight_np(r, re)
    n0 = float(w.sum())
    lam = float((w * r * r).sum() / n0)
    return n0, lam


@dataclass
class MPSWallTables:
    r_max: float
    inv_dr: float
    zn: np.ndarray
    zg: np.ndarray
    zgz: np.ndarray
    zl: np.ndarray
    zlz: np.ndarray


def build_tables(l0: float, re_n: float, re_l: float, samples: int = 256) -> MPSWallTables:
    """Tables on r = r_max i / (samples - 1), r_max = max(re_n, re_l)."""
    r_max = max(re_n, re_l)
    wall = wall_lattice(l0, r_max)
    r = np.linspace(0.0, r_max, samples)
    tabs = np.zeros((5, samples))
    for i, ri in enumerate(r):
        s = ri - wall[:, 2]
        dist = np.sqrt(wall[:, 0] ** 2 + wall[:, 1] ** 2 + s ** 2)
        wn = mps_weight_np(dist, re_n)
        wl = mps_weight_np(dist, re_l)
        tabs[0, i] = wn.sum()
        tabs[1, i] = (s / dist ** 2 * wn).sum()
        tabs[2, i] = (s * s / dist ** 2 * wn).sum()
        tabs[3, i] = wl.sum()
        tabs[4, i] = (s * wl).sum()
    return MPSWallTables(r_max, (samples - 1) / r_max, *tabs)


# -- 3D wall maps (edges and corners) ----------------------------------------------------------------
# channels of the map: the wall sums of every wall within re, for a particle at the node
ZN = 0  # sum w_n                                 number density
G = 1  # 1-3: sum (x_w - x) / r^2 w_n             gradient (uniform wall pressure) and divergence
T = 4  # 4-9: sum (x_w - x)(x_w - x)^T / r^2 w_n   gradient, hydrostatic wall pressure (xx yy zz xy xz yz)
ZL = 10  # sum w_l                                viscosity (no-slip wall)
M = 11  # 11-13: sum (x_w - x) w_l                Laplacian, hydrostatic wall pressure
CHANNELS = 14


def stencil(l0: float, re_n: float, re_l: float) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature stencil of cell-centred samples around a map node (spacing dq = l0 / 2): sample k
    sits at o_k = (idx_k + 1/2) dq, |o_k| < max(re), i.e. at index node + idx_k of the staggered lattice
    (node + dq / 2 on every axis); per sample the weights (K, CHANNELS) of every channel, each sample
    weighing (dq / l0)^3 wall particles. Cell-centred samples never sit on the node (r > 0), and
    measured in box edges and corners they over-count n by 2-5 % where node-centred ones under-count by
    as much (which would take corner particles for free surface)."""
    dq = 0.5 * l0
    r_max = max(re_n, re_l)
    k = int(math.ceil(r_max / dq)) + 1
    g = np.arange(-k, k)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    idx = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    o = (idx + 0.5) * dq
    r = np.linalg.norm(o, axis=1)
    keep = r < r_max
    idx, o, r = idx[keep], o[keep], r[keep]
    scale = (dq / l0) ** 3
    wn = scale * mps_weight_np(r, re_n)
    wl = scale * mps_weight_np(r, re_l)
    f = wn / (r * r)
    w = np.zeros((len(r), CHANNELS))
    w[:, ZN] = wn
    w[:, G:G + 3] = f[:, None] * o
    w[:, T:T + 3] = f[:, None] * o * o
    w[:, T + 3] = f * o[:, 0] * o[:, 1]
    w[:, T + 4] = f * o[:, 0] * o[:, 2]
    w[:, T + 5] = f * o[:, 1] * o[:, 2]
    w[:, ZL] = wl
    w[:, M:M + 3] = wl[:, None] * o
    return np.ascontiguousarray(idx.astype(np.int64)), np.ascontiguousarray(w)


def occupancy(d, dq):
    """Smooth occupancy of the wall region {d < 0}: 1 deeper than dq/2, 0 beyond dq/2 in the fluid."""
    return np.clip(0.5 - np.asarray(d) / dq, 0.0, 1.0)


@nb.njit(cache=True, parallel=True)
def _build(dist, occ, reach, idx, w, maps):
    """maps[node] = sum_k occ[node + idx_k] w_k for the nodes closer to a wall than ``reach``: a discrete
    convolution with the occupancy on the staggered lattice (indices beyond it clamped to its border,
    as the SDF sampler clamps).

    Summed in float64 and rounded to the float32 map once (as maps.build_bricks does for SPH): the stencil
    is summed in index order, so with the scene's axes swapped (Y up against Z up) the same wall sum runs in
    another order; accumulated in the float32 map that order changed 58 % of the values by up to 4e-7
    (float32 rounding), and the number density and pressure with them from the first step, where float64
    differs by 1e-16 and its rounding to float32 almost never."""
    nx, ny, nz = occ.shape[0], occ.shape[1], occ.shape[2]
    nc = w.shape[1]
    for i in nb.prange(nx):
        acc = np.empty(nc)
        for j in range(ny):
            for k in range(nz):
                if dist[i, j, k] >= reach:
                    continue  # maps start at zero
                acc[:] = 0.0
                for s in range(idx.shape[0]):
                    a = min(max(i + idx[s, 0], 0), nx - 1)
                    b = min(max(j + idx[s, 1], 0), ny - 1)
                    c = min(max(k + idx[s, 2], 0), nz - 1)
                    o = occ[a, b, c]
                    if o > 0.0:
                        for ch in range(nc):
                            acc[ch] += o * w[s, ch]
                for ch in range(nc):
                    maps[i, j, k, ch] = acc[ch]


class MPSWallMaps:
    """The wall sums of every wall within re on a node grid of spacing l0 / 2 over the SDF (like
    maps.WallMaps for SPH), so a particle in a concave edge or corner counts both walls and is
    neither under-counted (taken for free surface) nor pushed towards the missing wall.

    ``fix`` (5, samples), per wall distance r = r_max i / (samples - 1): the lattice table over the
    flat-wall quadrature for Zn, G, T, Zl and M in turn, so on a flat wall each map equals the lattice
    sum of ``build_tables`` exactly (a particle l0/2 above the floor sees n0)."""

    def __init__(self, sdf, l0: float, re_n: float, re_l: float, tables: MPSWallTables):
        dq = 0.5 * l0
        self.spacing = dq
        self.origin = np.asarray(sdf.origin, np.float64)
        shape = np.floor((sdf.upper - sdf.origin) / dq).astype(np.int64) + 1
        nodes = np.stack([g.ravel() for g in np.meshgrid(
            *[self.origin[a] + dq * np.arange(shape[a]) for a in range(3)], indexing="ij")], 1)
        dist = sdf.sample(nodes)[0].reshape(shape)
        occ = occupancy(sdf.sample(nodes + 0.5 * dq)[0], dq).reshape(shape)  # the staggered lattice
        idx, w = stencil(l0, re_n, re_l)
        self.maps = np.zeros((*shape, CHANNELS), np.float32)
        _build(dist, occ, max(re_n, re_l) + dq, idx, w, self.maps)
        # flat-wall correction: the same stencil over the floor z = 0 below a particle at height r
        r = np.linspace(0.0, tables.r_max, len(tables.zn))
        flat = np.zeros((len(r), 5))
        for i, ri in enumerate(r):
            out = occupancy(ri + (idx[:, 2] + 0.5) * dq, dq) @ w
            flat[i] = out[ZN], -out[G + 2], out[T + 2], out[ZL], -out[M + 2]
        lattice = np.stack([tables.zn, tables.zg, tables.zgz, tables.zl, tables.zlz], axis=1)
        self.fix = np.ascontiguousarray(np.where(flat > 1e-9, lattice / np.maximum(flat, 1e-300), 1.0).T)
        self.inv_dr = (len(r) - 1) / tables.r_max


# -- the walls as the MPS kernels take them ---------------------------------------------------------
# ``MPSWalls``: the static walls (SDF, dense MPSWallMaps and its flat-wall factors ``fix``) and the moving
# rigid walls, each baked once in its own rest frame (its SDF and its own dense map, in an atlas: ``b_maps``
# the maps concatenated flat, ``b_mgrid`` rows offset, nx, ny, nz) and sampled at the particle carried into
# that frame by its pose (walls.maps: the same b_sdf ... pose fields as the WCSPH bundle, so to_body,
# body_sample and bodies_push_out serve both). ``fix`` depends only on l0 and re: every field shares it.
# A moving wall's vector sums (G, M) turn into the world with its rotation R, its tensor T as R T R^T; its
# wall particles move with the wall's velocity at the particle (viscosity and divergence). No body = empty
# arrays (the loops over them do nothing).
MPSWalls = namedtuple("MPSWalls", "sdf sdf_o sdf_inv maps m_o m_inv fix inv_dr "
                                  "b_sdf b_grid b_sdf_o b_sdf_inv b_maps b_mgrid b_mo b_minv pose")
# rows of MPSWallMaps.fix
FIX_N, FIX_G, FIX_T, FIX_L, FIX_M = 0, 1, 2, 3, 4


def make_mps_walls(sdf, maps: MPSWallMaps, bodies=()) -> MPSWalls:
    """The MPSWalls of the static SDFGrid (SI) and its MPSWallMaps; ``bodies``: (SDFGrid in its rest frame,
    its MPSWallMaps) per moving wall, posed at rest until walls.maps.set_pose."""
    n = len(bodies)
    mgrid, offs = [], [0]
    for _, mb in bodies:
        mgrid.append([offs[-1], *mb.maps.shape[:3]])
        offs.append(offs[-1] + mb.maps.size)
    b_sdf, b_grid, b_sdf_o, b_sdf_inv, pose = body_fields([sb for sb, _ in bodies])
    b_maps = np.concatenate([mb.maps.ravel() for _, mb in bodies]) if bodies else np.zeros(0)
    return MPSWalls(sdf.dist, np.asarray(sdf.origin, np.float64), 1.0 / sdf.spacing, maps.maps, maps.origin,
                    1.0 / maps.spacing, maps.fix, maps.inv_dr, b_sdf, b_grid, b_sdf_o, b_sdf_inv,
                    b_maps.astype(np.float32), np.array(mgrid, np.int64).reshape(n, 4),
                    np.array([mb.origin for _, mb in bodies], np.float64).reshape(n, 3),
                    np.array([1.0 / mb.spacing for _, mb in bodies], np.float64), pose)


@nb.njit(cache=True, inline="always")
def wall_sum(w, x, y, z, d, c, row):
    """Channel ``c`` of the static walls' map at (x, y, z) times its flat-wall factor ``fix[row]`` at the wall
    distance d."""
    return map_sample(w.maps, w.m_o[0], w.m_o[1], w.m_o[2], w.m_inv, x, y, z, c) * table_lookup(w.fix[row], d,
                                                                                                 w.inv_dr)


@nb.njit(cache=True, inline="always")
def body_sum(w, k, lx, ly, lz, db, c, row):
    """wall_sum of moving wall k at a point of its rest frame (lx, ly, lz), db its distance there."""
    o, nx, ny, nz = w.b_mgrid[k, 0], w.b_mgrid[k, 1], w.b_mgrid[k, 2], w.b_mgrid[k, 3]
    maps = w.b_maps[o:o + nx * ny * nz * CHANNELS].reshape((nx, ny, nz, CHANNELS))
    mo = w.b_mo[k]
    return map_sample(maps, mo[0], mo[1], mo[2], w.b_minv[k], lx, ly, lz, c) * table_lookup(w.fix[row], db, w.inv_dr)


@nb.njit(cache=True, inline="always")
def _near(w, k, x, y, z):
    lx, ly, lz = to_body(w.pose[k], x, y, z)
    db, _, _, _ = body_distance(w, k, lx, ly, lz)
    return lx, ly, lz, db


@nb.njit(cache=True)
def bodies_number_density(w, re, x, y, z):
    """The moving walls' share of the number density: sum_b Zn_b."""
    s = 0.0
    for k in range(w.pose.shape[0]):
        lx, ly, lz, db = _near(w, k, x, y, z)
        if db < re:
            s += body_sum(w, k, lx, ly, lz, db, ZN, FIX_N)
    return s


@nb.njit(cache=True)
def bodies_laplacian(w, re, x, y, z, vx, vy, vz):
    """The moving walls' share of the velocity Laplacian sum: sum_b Zl_b (u_b(x) - v), no-slip against each
    wall's own velocity."""
    ax = 0.0
    ay = 0.0
    az = 0.0
    for k in range(w.pose.shape[0]):
        lx, ly, lz, db = _near(w, k, x, y, z)
        if db < re:
            zl = body_sum(w, k, lx, ly, lz, db, ZL, FIX_L)
            ux, uy, uz = body_velocity(w.pose[k], x, y, z)
            ax += zl * (ux - vx)
            ay += zl * (uy - vy)
            az += zl * (uz - vz)
    return ax, ay, az


@nb.njit(cache=True)
def _body_vector(w, k, lx, ly, lz, db, c, row):
    """A vector channel (G or M) of body k, turned into the world."""
    return body_direction(w.pose[k], body_sum(w, k, lx, ly, lz, db, c, row), body_sum(w, k, lx, ly, lz, db, c + 1, row),
                          body_sum(w, k, lx, ly, lz, db, c + 2, row))


@nb.njit(cache=True)
def bodies_divergence(w, re, x, y, z, ux, uy, uz):
    """The moving walls' share of the divergence sum, sum_b (u_b(x) - u) . G_b (``u`` = u* - g dt, as for the
    static walls), and their share of the first moment, sum_b G_b."""
    s = 0.0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for k in range(w.pose.shape[0]):
        lx, ly, lz, db = _near(w, k, x, y, z)
        if db < re:
            gx, gy, gz = _body_vector(w, k, lx, ly, lz, db, G, FIX_G)
            bx, by, bz = body_velocity(w.pose[k], x, y, z)
            s += (bx - ux) * gx + (by - uy) * gy + (bz - uz) * gz
            sx += gx
            sy += gy
            sz += gz
    return s, sx, sy, sz


@nb.njit(cache=True)
def bodies_hydrostatic(w, re, x, y, z, g):
    """The moving walls' share of g . M (the hydrostatic part of their resting pressure in the Laplacian)."""
    s = 0.0
    for k in range(w.pose.shape[0]):
        lx, ly, lz, db = _near(w, k, x, y, z)
        if db < re:
            mx, my, mz = _body_vector(w, k, lx, ly, lz, db, M, FIX_M)
            s += g[0] * mx + g[1] * my + g[2] * mz
    return s


@nb.njit(cache=True)
def bodies_gradient(w, re, x, y, z, dp, rho, g):
    """The moving walls' share of the pressure gradient sum, dp G + rho T g, and of the gradient tensor T
    (xx yy zz xy xz yz), each wall's G and T turned into the world (R G, R T R^T)."""
    gx = 0.0
    gy = 0.0
    gz = 0.0
    txx = 0.0
    tyy = 0.0
    tzz = 0.0
    txy = 0.0
    txz = 0.0
    tyz = 0.0
    for k in range(w.pose.shape[0]):
        lx, ly, lz, db = _near(w, k, x, y, z)
        if db >= re:
            continue
        ax, ay, az = _body_vector(w, k, lx, ly, lz, db, G, FIX_G)
        a = body_sum(w, k, lx, ly, lz, db, T, FIX_T)
        b = body_sum(w, k, lx, ly, lz, db, T + 1, FIX_T)
        c = body_sum(w, k, lx, ly, lz, db, T + 2, FIX_T)
        e = body_sum(w, k, lx, ly, lz, db, T + 3, FIX_T)
        f = body_sum(w, k, lx, ly, lz, db, T + 4, FIX_T)
        h = body_sum(w, k, lx, ly, lz, db, T + 5, FIX_T)
        # R T R^T column by column: R (T R^T e_j) = R (T row j of R)
        p = w.pose[k]
        c0x, c0y, c0z = body_direction(p, a * p[0] + e * p[1] + f * p[2], e * p[0] + b * p[1] + h * p[2],
                                       f * p[0] + h * p[1] + c * p[2])
        c1x, c1y, c1z = body_direction(p, a * p[3] + e * p[4] + f * p[5], e * p[3] + b * p[4] + h * p[5],
                                       f * p[3] + h * p[4] + c * p[5])
        c2x, c2y, c2z = body_direction(p, a * p[6] + e * p[7] + f * p[8], e * p[6] + b * p[7] + h * p[8],
                                       f * p[6] + h * p[7] + c * p[8])
        gx += dp * ax + rho * (c0x * g[0] + c1x * g[1] + c2x * g[2])
        gy += dp * ay + rho * (c0y * g[0] + c1y * g[1] + c2y * g[2])
        gz += dp * az + rho * (c0z * g[0] + c1z * g[1] + c2z * g[2])
        txx += c0x
        tyy += c1y
        tzz += c2z
        txy += c1x
        txz += c2x
        tyz += c2y
    return gx, gy, gz, txx, tyy, tzz, txy, txz, tyz
