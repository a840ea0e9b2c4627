"""The particles' implicit function on a grid (PHYSICS.md eq. 17-18), numba.

Phi(x) = sum_j V_j W(|x - x_j|) with the Poly6 kernel W (eq. 10) of support R,
and V_j = m_j / rho_j with rho_j the SPH summation sum_k m_k W(|x_j - x_k|) over the same kernel
(``particle_volumes``), so Phi is 1 wherever the particles are evenly spread, whatever their
spacing, and 0 outside. Scattered per particle over the grid nodes inside its kernel sphere only (about
4.2 R^3 / h^3 nodes, against 27 R^3 / h^3 for a gather over neighbour cells).
The grid's z slabs are split into chunks, one chunk per parallel task, and every particle adds only
into the slabs of the chunk at hand, so each node is written by one thread, in particle order:
deterministic, no atomics.

Grid layout: ``phi[k, j, i]`` (z, y, x) in C order, i.e. x fastest, which is VTK's point order.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from stages.common.sdf import sdf_sample
from stages.simulate.neighbours import CellGrid, cell_coords

MAX_CELLS_PER_PARTICLE = 8  # the volumes' cell grid grows its cells rather than exceed this (far spray)


@nb.njit(cache=True, parallel=True)
def _summed_volumes(x, vol, starts, lo, inv_cell, dims, radius, out):
    """out_i = vol_i / sum_j vol_j W(|x_i - x_j|) (Poly6, eq. 10) over the 27 cells around i (self included)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    r2max = radius * radius
    coef = 315.0 / (64.0 * math.pi * radius ** 9)
    for i in nb.prange(x.shape[0]):
        xi, yi, zi = x[i, 0], x[i, 1], x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        s = 0.0
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + max(cx - 1, 0)], starts[base + min(cx + 1, nx - 1) + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    r2 = dx * dx + dy * dy + dz * dz
                    w = r2max - r2
                    if w > 0.0:
                        s += vol[j] * w * w * w
        out[i] = vol[i] / (coef * s)


def cell_grid(x: np.ndarray, radius: float) -> CellGrid:
    """A cell grid over the particles ``x`` for pair searches within ``radius``: cells of at least
    ``radius``, grown so that far-flung spray does not make more than MAX_CELLS_PER_PARTICLE cells each."""
    lo = x.min(axis=0)
    extent = np.maximum(x.max(axis=0) - lo, radius)
    cell = max(radius, float(np.prod(extent) / (MAX_CELLS_PER_PARTICLE * len(x))) ** (1.0 / 3.0))
    return CellGrid(lo, lo + extent * (1 + 1e-9), cell)


def particle_volumes(x: np.ndarray, vol: np.ndarray, radius: float) -> np.ndarray:
    """The volume m_i / rho_i each particle occupies, rho_i by SPH summation over the kernel of support
    ``radius`` (self included). ``vol`` is any quantity proportional to the masses (m / rho0): only
    ratios of masses enter, so the result is in the unit of ``x`` cubed. A lone particle gets
    1 / W(0), which makes its own Phi 1 at its centre."""
    grid = cell_grid(x, radius)
    order = grid.sort(x)
    out = np.empty(len(x))
    _summed_volumes(x[order], vol[order], grid.starts, grid.lo, 1.0 / grid.cell, grid.dims, radius, out)
    result = np.empty(len(x))
    result[order] = out
    return result


@nb.njit(cache=True, parallel=True, fastmath=True)
def scatter_implicit(x, vol, chunk_first, chunk_last, chunk_k0, grid_lo, inv_h, radius, phi):
    """phi = sum_j vol_j W(|node - x_j|) (eq. 17-18, Poly6 eq. 10 of support ``radius``); ``phi`` may come
    uninitialised (each chunk zeroes its own slabs first: in parallel, and warm in the cache it scatters into).

    ``x`` (N, 3) in ``order_and_chunks`` order, ``vol`` (N,) = m / rho_j in the same order. Chunk c owns the z slabs
    ``chunk_k0[c] <= k < chunk_k0[c + 1]`` and visits particles ``chunk_first[c] <= q < chunk_last[c]``
    (those whose kernel sphere reaches its slabs). ``grid_lo`` is node (0, 0, 0); spacing 1/inv_h."""
    nz, ny, nx = phi.shape
    r2max = radius * radius
    coef = 315.0 / (64.0 * math.pi * radius ** 9)
    h = 1.0 / inv_h
    h32 = np.float32(h)
    for c in nb.prange(len(chunk_first)):
        kc0 = chunk_k0[c]
        kc1 = chunk_k0[c + 1]
        phi[kc0:kc1] = 0.0
        for q in range(chunk_first[c], chunk_last[c]):
            px = x[q, 0]
            py = x[q, 1]
            pz = x[q, 2]
            cw = np.float32(coef * vol[q])
            fz = (pz - grid_lo[2]) * inv_h
            fy = (py - grid_lo[1]) * inv_h
            fx = (px - grid_lo[0]) * inv_h
            rn = radius * inv_h
            gx0 = np.float32(grid_lo[0] - px)
            k0 = max(int(math.ceil(fz - rn)), kc0)
            k1 = min(int(math.floor(fz + rn)) + 1, kc1, nz)
            j0 = max(int(math.ceil(fy - rn)), 0)
            j1 = min(int(math.floor(fy + rn)) + 1, ny)
            i0 = max(int(math.ceil(fx - rn)), 0)
            i1 = min(int(math.floor(fx + rn)) + 1, nx)
            for k in range(k0, k1):
                dz = grid_lo[2] + k * h - pz
                rz2 = r2max - dz * dz
                if rz2 <= 0.0:
                    continue
                for j in range(j0, j1):
                    dy = grid_lo[1] + j * h - py
                    ryz2 = rz2 - dy * dy
                    if ryz2 <= 0.0:
                        continue
                    row = phi[k, j]
                    # float32 and branch-free so the row vectorises (w < 0 only by rounding)
                    r32 = np.float32(ryz2)
                    for i in range(i0, i1):
                        dx = gx0 + np.float32(i) * h32
                        w = max(r32 - dx * dx, np.float32(0.0))
                        row[i] += cw * w * w * w


def order_and_chunks(x: np.ndarray, grid_lo: np.ndarray, h: float, radius: float, shape: np.ndarray, slabs: int):
    """Particle order and chunk plan for ``scatter_implicit``.

    Chunks are ``slabs`` z slabs thick. Particles are sorted by the chunk their z falls in, then by
    grid row (y) and column (x), so the writes of consecutive particles stay close in memory. Chunk c
    visits the particles of the chunks whose z lies within ``radius`` of its slabs.
    Returns (order, first, last, bounds)."""
    nx, ny, nz = (int(s) for s in shape)
    g = (x - grid_lo) / h
    zc = np.clip((g[:, 2] // slabs).astype(np.int64), 0, None)
    jy = np.clip(g[:, 1].astype(np.int64), 0, ny - 1)
    ix = np.clip(g[:, 0].astype(np.int64), 0, nx - 1)
    order = np.argsort((zc * ny + jy) * nx + ix, kind="stable")
    zc_sorted = zc[order]
    bounds = np.append(np.arange(0, nz, slabs, dtype=np.int64), nz)
    reach = int(np.ceil(radius / (slabs * h)))
    c = np.arange(len(bounds) - 1, dtype=np.int64)
    first = np.searchsorted(zc_sorted, c - reach, side="left").astype(np.int64)
    last = np.searchsorted(zc_sorted, c + reach, side="right").astype(np.int64)
    return order, first, last, bounds


@nb.njit(cache=True, parallel=True)
def ghost_particles(x, vol, dist, origin, inv_h_sdf, radius, out_x, out_vol, keep, thin, depth):
    """Mirror images x_j - 2 d_j n_j of the particles within ``radius`` of a wall (d, n from the SDF
    sampler): the wall's share of the density (PHYSICS.md (11)-(12), (17)-(18)) carried by the fluid
    that is actually there, so Phi stays about 1 up to the wall instead of falling to 0.5 on it.

    n is the mean of the sampler's normals a thousandth of an SDF cell either side of the particle: the
    trilinear gradient is one-sided at a node, and on a ridge of d (a tank's edge seen from inside) one
    side gives zero, so a particle exactly on a node (an emitter lattice next to a wall) got an image
    or none by the last bit of its position, i.e. by the scene's units. Both sides agree off ridges.

    Behind a wall thinner than the image's reach (d + radius from the wall point; probed every half SDF
    cell, the probe enters the wall and leaves it), the image would count past the wall too: beside a
    shell (0.6 l0) or an open box's 1 l0 sides it drew water under a bowl that had none (a user's
    sweep). Such an image is marked ``thin``: it counts only where its particle sees through no wall
    (scatter_clipped, add_seen_images). Dropping it instead left the surface up to 0.55 l0 off a thin
    paddle with water on both sides. An image in open space beside no thin wall is dropped: between a tank's
    side and the edge of a plate above its floor the normals of the ridge pointed down past the plate's
    edge, and those images drew water under the plate where there was none. ``depth``: how deep that wall
    reads in the sampled field (the least d the probe met, < 0): a 0.6 l0 wall whose medial plane falls
    between SDF nodes reads 0.1 l0 deep at most, shallower than any fixed threshold (the glass of the pour
    leaked 0.83 l0 of water past it)."""
    e = 1e-3 / inv_h_sdf
    step = 0.5 / inv_h_sdf
    for q in nb.prange(x.shape[0]):
        px, py, pz = x[q, 0], x[q, 1], x[q, 2]
        d, _, _, _ = sdf_sample(dist, origin[0], origin[1], origin[2], inv_h_sdf, px, py, pz)
        nx = ny = nz = norm = 0.0
        if 0.0 < d < radius:  # most particles are farther from a wall: one sample
            _, ax, ay, az = sdf_sample(dist, origin[0], origin[1], origin[2], inv_h_sdf, px + e, py + e, pz + e)
            _, bx, by, bz = sdf_sample(dist, origin[0], origin[1], origin[2], inv_h_sdf, px - e, py - e, pz - e)
            nx, ny, nz = ax + bx, ay + by, az + bz
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)  # 2 off ridges, 0 between two opposite walls
            if norm > 0.0:
                nx, ny, nz = nx / norm, ny / norm, nz / norm
        ok = norm > 0.5
        behind = False
        if ok:
            wx, wy, wz = px - d * nx, py - d * ny, pz - d * nz  # the wall point
            s = 0.5 * step
            inside = False  # (a convex edge's trilinear rounding reads > 0 just inside it: not open space yet)
            least = 0.0
            while s <= d + radius:
                dw = _sdf_distance(dist, origin, inv_h_sdf, wx - s * nx, wy - s * ny, wz - s * nz)
                if dw < 0.0:
                    inside = True
                    least = min(least, dw)
                elif inside:  # out of the wall again: open space within the image's reach
                    behind = True
                    break
                s += 0.5 * step
        ix, iy, iz = px - 2.0 * d * nx, py - 2.0 * d * ny, pz - 2.0 * d * nz
        if ok and not behind:  # an image in open space that no thin wall explains: the normal of a ridge
            ok = _sdf_distance(dist, origin, inv_h_sdf, ix, iy, iz) < 0.0
        keep[q] = ok
        thin[q] = behind
        depth[q] = least if behind else 0.0
        out_x[q, 0] = ix
        out_x[q, 1] = iy
        out_x[q, 2] = iz
        out_vol[q] = vol[q]


@nb.njit(cache=True)
def _enters(sx, sy, sz, x, y, z, depth, dist, origin, inv_h_sdf) -> bool:
    """Whether the segment from (sx, sy, sz) to (x, y, z) reads d < ``depth`` anywhere (probed every quarter
    SDF cell): it enters a wall."""
    length = math.sqrt((x - sx) ** 2 + (y - sy) ** 2 + (z - sz) ** 2)
    n = int(length * 4.0 * inv_h_sdf) + 1
    for m in range(1, n):
        f = m / n
        if _sdf_distance(dist, origin, inv_h_sdf, sx + f * (x - sx), sy + f * (y - sy), sz + f * (z - sz)) < depth:
            return True
    return False


@nb.njit(cache=True)
def _seen(sx, sy, sz, x, y, z, wall_depth, dist, origin, inv_h_sdf) -> bool:
    """Whether the segment from (sx, sy, sz) to (x, y, z) stays out of the walls: a wall is where d < -1/4 cell,
    or half the depth ``wall_depth`` (< 0) the wall beside the source reads where that is shallower (the
    trilinear field of a thin wall reads < 0 just off its faces, and a thin wall cut between its nodes reads
    only a fraction of its half-thickness deep)."""
    return not _enters(sx, sy, sz, x, y, z, max(-0.25 / inv_h_sdf, 0.5 * wall_depth), dist, origin, inv_h_sdf)


@nb.njit(cache=True)
def add_seen_images(x, summed, pairs_g, pairs_i, img, img_vol, src, src_depth, radius, dist, origin, inv_h_sdf):
    """summed_i += img_vol_g W(|x_i - img_g|) for the pairs (g, i) whose image source sees particle i: the
    images beside thin walls count in the density of the fluid on their own side only."""
    r2max = radius * radius
    coef = 315.0 / (64.0 * math.pi * radius ** 9)
    for p in range(len(pairs_g)):
        g, i = pairs_g[p], pairs_i[p]
        w = r2max - ((x[i, 0] - img[g, 0]) ** 2 + (x[i, 1] - img[g, 1]) ** 2 + (x[i, 2] - img[g, 2]) ** 2)
        if w > 0.0 and _seen(src[g, 0], src[g, 1], src[g, 2], x[i, 0], x[i, 1], x[i, 2], src_depth[g], dist, origin,
                             inv_h_sdf):
            summed[i] += coef * img_vol[g] * w * w * w


@nb.njit(cache=True)
def scatter_clipped(x, vol, src, src_depth, grid_lo, inv_h, radius, phi, dist, origin, inv_h_sdf):
    """Add sum_j vol_j W(|node - x_j|) (as scatter_implicit) for the images beside thin walls
    (ghost_particles), except at nodes in open space that their particle ``src_j`` sees only through a
    wall: the image stands for the wall's share of the density on the particle's side, not beyond the
    wall (a plane at the wall's far face cut open water past the wall's edges: 0.5 l0 steps in the
    surface). Few particles: serial; the segment is probed every half SDF cell."""
    nz, ny, nx = phi.shape
    r2max = radius * radius
    coef = 315.0 / (64.0 * math.pi * radius ** 9)
    h = 1.0 / inv_h
    rn = radius * inv_h
    for q in range(x.shape[0]):
        px, py, pz = x[q, 0], x[q, 1], x[q, 2]
        sx, sy, sz = src[q, 0], src[q, 1], src[q, 2]
        cw = coef * vol[q]
        k0 = max(int(math.ceil((pz - grid_lo[2]) * inv_h - rn)), 0)
        k1 = min(int(math.floor((pz - grid_lo[2]) * inv_h + rn)) + 1, nz)
        j0 = max(int(math.ceil((py - grid_lo[1]) * inv_h - rn)), 0)
        j1 = min(int(math.floor((py - grid_lo[1]) * inv_h + rn)) + 1, ny)
        i0 = max(int(math.ceil((px - grid_lo[0]) * inv_h - rn)), 0)
        i1 = min(int(math.floor((px - grid_lo[0]) * inv_h + rn)) + 1, nx)
        for k in range(k0, k1):
            z = grid_lo[2] + k * h
            for j in range(j0, j1):
                y = grid_lo[1] + j * h
                for i in range(i0, i1):
                    xx = grid_lo[0] + i * h
                    w = r2max - ((xx - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2)
                    if w <= 0.0:
                        continue
                    if (_sdf_distance(dist, origin, inv_h_sdf, xx, y, z) > 0.0  # open space, seen through a wall
                            and not _seen(sx, sy, sz, xx, y, z, src_depth[q], dist, origin, inv_h_sdf)):
                        continue
                    phi[k, j, i] += np.float32(cw * w * w * w)


@nb.njit(cache=True)
def _seen_by_any(px, py, pz, d_node, radius, x, starts, lo, inv_cell, dims, dist, origin, inv_h_sdf, slopes) -> bool:
    """Whether a particle within ``radius`` of (px, py, pz) sees it through open space. Strict (d < 0 anywhere
    on the segment is a wall, where _seen has a threshold): a thin wall cut between its nodes reads a few
    hundredths of a spacing deep, and one particle seen clearly is enough (most nodes see their nearest).
    ``d_node`` the field at the node, ``slopes`` the field's largest slope along each axis: the field changes
    along a segment by at most sum_k slope_k |step_k|, so a segment whose two ends' distances add up to more
    is seen without probing it (the same answer, most of the pairs beside a thick wall)."""
    gx, gy, gz = dims[0], dims[1], dims[2]
    cx, cy, cz = cell_coords(px, py, pz, lo[0], lo[1], lo[2], inv_cell, gx, gy, gz)
    r2max = radius * radius
    margin = 1e-6 / inv_h_sdf
    for kz in range(max(cz - 1, 0), min(cz + 2, gz)):
        for ky in range(max(cy - 1, 0), min(cy + 2, gy)):
            base = (kz * gy + ky) * gx
            for p in range(starts[base + max(cx - 1, 0)], starts[base + min(cx + 1, gx - 1) + 1]):
                ex, ey, ez = x[p, 0] - px, x[p, 1] - py, x[p, 2] - pz
                if ex * ex + ey * ey + ez * ez >= r2max:
                    continue
                change = slopes[0] * abs(ex) + slopes[1] * abs(ey) + slopes[2] * abs(ez)
                if d_node + _sdf_distance(dist, origin, inv_h_sdf, x[p, 0], x[p, 1], x[p, 2]) > change + margin:
                    return True
                if not _enters(x[p, 0], x[p, 1], x[p, 2], px, py, pz, 0.0, dist, origin, inv_h_sdf):
                    return True
    return False


@nb.njit(cache=True, parallel=True)
def cut_by_walls(phi, grid_lo, h, iso, radius, x, starts, lo, inv_cell, dims, dist, origin, inv_h_sdf, slopes):
    """Intersect the fluid with the wall-free region: Phi' = iso + min(Phi - iso, d / R).

    The iso-surface of Phi' is the boundary of {Phi >= iso} and {d >= 0} (a CSG intersection of two
    fields with the same slope scale, 1/R), so where the fluid (with its mirror images) touches a wall
    the surface lies on d = 0 of the SDF. Nodes without fluid (Phi = 0) are outside anyway: skipped.

    Before that, a node in open space near a wall (0 < d < R, Phi >= iso / 2) that no particle sees through
    open space is dry (Phi = 0): water there is what kernels (the particles' own, or a floor's mirror images
    beside a thin divider) reached through a wall thinner than their support; the pour's glass at 1.25 cm and
    a 0.6 l0 divider standing on a floor drew water on their dry sides. ``x`` the particles sorted by the cell
    grid (``starts``, ``lo``, ``inv_cell``, ``dims``) of cells >= R; ``slopes``: SDFGrid.axis_slopes of the field."""
    nz, ny, nx = phi.shape
    for k in nb.prange(nz):
        z = grid_lo[2] + k * h
        for j in range(ny):
            y = grid_lo[1] + j * h
            for i in range(nx):
                p = phi[k, j, i]
                if p == 0.0:
                    continue
                xx = grid_lo[0] + i * h
                d = _sdf_distance(dist, origin, inv_h_sdf, xx, y, z)
                if (0.0 < d < radius and p >= 0.5 * iso
                        and not _seen_by_any(xx, y, z, d, radius, x, starts, lo, inv_cell, dims, dist, origin, inv_h_sdf,
                                             slopes)):
                    phi[k, j, i] = 0.0
                    continue
                wall = d / radius
                if wall < p - iso:
                    phi[k, j, i] = iso + wall


@nb.njit(cache=True, inline="always")
def _sdf_distance(dist, origin, inv_h, x, y, z):
    d, _, _, _ = sdf_sample(dist, origin[0], origin[1], origin[2], inv_h, x, y, z)
    return d
