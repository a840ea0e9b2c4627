"""The numba kernels of one MPS step (Koshizuka and Oka 1996; PHYSICS.md "MPS") with distance-function
walls (walls/mps.py).

Neighbours: one list per step, built at the start-of-step positions with radius max(re) + skin, so
it still holds every pair after the prediction moved particles by at most cfl l0; each kernel
recomputes r from the current positions and keeps the pairs within its own radius.

Determinism: every particle loop is a prange over i writing only i; the conjugate gradient's dot
products are per-block partial sums over a fixed number of blocks, added in block order, so the
result does not depend on the thread count."""
from __future__ import annotations

import math

import numba as nb

from stages.common.sdf import sdf_sample

from .neighbours import cell_coords
from .walls.maps import bodies_push_out, push_out
from .walls.mps import (FIX_G, FIX_L, FIX_M, FIX_N, FIX_T, G, M, T, ZL, ZN, bodies_divergence, bodies_gradient,
                        bodies_hydrostatic, bodies_laplacian, bodies_number_density, wall_sum)

CG_BLOCKS = 128


# Pairs closer than R_MIN re count as R_MIN re apart (0.21 l0 for the number density's re = 2.1 l0; the
# lattice's nearest pair is l0 and the collision keeps pairs near 0.5 l0): w = re / r - 1 and the 1 / r^2 of the
# gradient, divergence and corrective matrix stay finite. Without it, the eq. 16 projection put particles of a
# 20 degree V's apex onto one line; a pair there met at 1e-7 m, n/n0 reached 31,000 and the run blew up.
R_MIN = 0.1


@nb.njit(cache=True, inline="always")
def weight(r, re):
    """MPS weight w(r) = re / r - 1 for 0 < r < re (the caller ensures r < re), r at least R_MIN re."""
    return re / max(r, R_MIN * re) - 1.0


@nb.njit(cache=True, inline="always")
def weight_over_r2(r2, re):
    """w(r) / r^2 with r at least R_MIN re in both (the gradient and divergence sums' pair factor)."""
    r2 = max(r2, R_MIN * R_MIN * re * re)
    return (re / math.sqrt(r2) - 1.0) / r2


# -- neighbour list ---------------------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def count_neighbours(x, starts, lo, inv_cell, dims, radius, counts):
    """counts[i] = number of j != i with |x_i - x_j| < radius (cell size >= radius)."""
    r2max = radius * radius
    nx, ny, nz = dims[0], dims[1], dims[2]
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        x0 = max(cx - 1, 0)
        x1 = min(cx + 1, nx - 1)
        c = 0
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + x0], starts[base + x1 + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    if dx * dx + dy * dy + dz * dz < r2max and j != i:
                        c += 1
        counts[i] = c


@nb.njit(cache=True, parallel=True)
def fill_neighbours(x, starts, lo, inv_cell, dims, radius, offsets, nbr):
    """nbr[offsets[i]:offsets[i + 1]] = the neighbours of i, in cell order (deterministic)."""
    r2max = radius * radius
    nx, ny, nz = dims[0], dims[1], dims[2]
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        x0 = max(cx - 1, 0)
        x1 = min(cx + 1, nx - 1)
        k = offsets[i]
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + x0], starts[base + x1 + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    if dx * dx + dy * dy + dz * dz < r2max and j != i:
                        nbr[k] = j
                        k += 1


@nb.njit(cache=True)
def prefix_sum(counts, offsets):
    """offsets[0] = 0, offsets[i + 1] = offsets[i] + counts[i]; returns the total."""
    offsets[0] = 0
    for i in range(counts.shape[0]):
        offsets[i + 1] = offsets[i] + counts[i]
    return offsets[counts.shape[0]]


# -- walls ------------------------------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def wall_distance(x, walls, d, nrm):
    """The static walls' SDF distance and normal (into the fluid) of every particle (the moving walls'
    terms find their own distance)."""
    for i in nb.prange(x.shape[0]):
        dw, gx, gy, gz = sdf_sample(walls.sdf, walls.sdf_o[0], walls.sdf_o[1], walls.sdf_o[2], walls.sdf_inv, x[i, 0],
                                    x[i, 1], x[i, 2])
        d[i] = dw
        nrm[i, 0] = gx
        nrm[i, 1] = gy
        nrm[i, 2] = gz


# -- prediction: u* = u + dt (nu lap u + g), x* = x + dt u* ---------------------------------------
@nb.njit(cache=True, parallel=True)
def predict(x, v, gravity, dt, xs, vs):
    """Explicit prediction with gravity only (no viscosity effect declared)."""
    for i in nb.prange(x.shape[0]):
        for a in range(3):
            u = v[i, a] + dt * gravity[a]
            vs[i, a] = u
            xs[i, a] = x[i, a] + dt * u


@nb.njit(cache=True, parallel=True)
def predict_viscosity(x, v, offsets, nbr, re_l, lap_coef, nu, d, walls, wall_visc, gravity, dt, xs, vs):
    """Explicit prediction with the MPS Laplacian of the velocity, <lap u>_i = (2 d / (lambda n0))
    [sum_j (u_j - u_i) w(r_ij) - u_i Zl(x_i)] (``lap_coef`` = 2 d / (lambda n0)); the wall term is the
    resting no-slip wall (eq. 13-15 in MPS form, Zl from the wall maps), only with ``wall_visc``; a moving
    wall's is sum_b (u_b - u_i) Zl_b, no-slip against the wall's velocity at the particle."""
    r2max = re_l * re_l
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        lx = 0.0
        ly = 0.0
        lz = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = x[j, 0] - xi
            dy = x[j, 1] - yi
            dz = x[j, 2] - zi
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < r2max and r2 > 1e-24:
                w = weight(math.sqrt(r2), re_l)
                lx += (v[j, 0] - v[i, 0]) * w
                ly += (v[j, 1] - v[i, 1]) * w
                lz += (v[j, 2] - v[i, 2]) * w
        if wall_visc:
            if d[i] < re_l:
                zw = wall_sum(walls, xi, yi, zi, d[i], ZL, FIX_L)
                lx -= v[i, 0] * zw
                ly -= v[i, 1] * zw
                lz -= v[i, 2] * zw
            if walls.pose.shape[0] > 0:  # moving walls (a call per particle costs even when it does nothing)
                bx, by, bz = bodies_laplacian(walls, re_l, xi, yi, zi, v[i, 0], v[i, 1], v[i, 2])
                lx += bx
                ly += by
                lz += bz
        c = nu * lap_coef
        ux = v[i, 0] + dt * (c * lx + gravity[0])
        uy = v[i, 1] + dt * (c * ly + gravity[1])
        uz = v[i, 2] + dt * (c * lz + gravity[2])
        vs[i, 0] = ux
        vs[i, 1] = uy
        vs[i, 2] = uz
        xs[i, 0] = xi + dt * ux
        xs[i, 1] = yi + dt * uy
        xs[i, 2] = zi + dt * uz


@nb.njit(cache=True, parallel=True)
def collide(xs, vs, offsets, nbr, r_col, restitution, dt, x_out, v_out):
    """Collision of close particles (Koshizuka's treatment): for every approaching pair closer than
    r_col, the relative normal velocity is reduced as in an inelastic collision of equal masses,
    du_i = (1 + e) / 2 ((u_j - u_i) . n) n, and x_i moves by dt du_i. Jacobi form (each i sums over
    its pairs from the same old velocities), so it is symmetric and deterministic."""
    r2max = r_col * r_col
    f = 0.5 * (1.0 + restitution)
    for i in nb.prange(xs.shape[0]):
        xi = xs[i, 0]
        yi = xs[i, 1]
        zi = xs[i, 2]
        dux = 0.0
        duy = 0.0
        duz = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = xs[j, 0] - xi
            dy = xs[j, 1] - yi
            dz = xs[j, 2] - zi
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < r2max and r2 > 1e-24:
                r = math.sqrt(r2)
                nx = dx / r
                ny = dy / r
                nz = dz / r
                vn = (vs[j, 0] - vs[i, 0]) * nx + (vs[j, 1] - vs[i, 1]) * ny + (vs[j, 2] - vs[i, 2]) * nz
                if vn < 0.0:  # approaching
                    dux += f * vn * nx
                    duy += f * vn * ny
                    duz += f * vn * nz
        v_out[i, 0] = vs[i, 0] + dux
        v_out[i, 1] = vs[i, 1] + duy
        v_out[i, 2] = vs[i, 2] + duz
        x_out[i, 0] = xi + dt * dux
        x_out[i, 1] = yi + dt * duy
        x_out[i, 2] = zi + dt * duz


@nb.njit(cache=True, parallel=True)
def number_density(x, offsets, nbr, re_n, d, walls, n):
    """n_i = sum_{j != i} w(r_ij) + Zn(x_i): the fluid neighbours plus the walls' share from the 3D maps
    (walls.mps.MPSWallMaps; each moving wall's at the particle in its rest frame)."""
    r2max = re_n * re_n
    for i in nb.prange(x.shape[0]):
        s = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < r2max and r2 > 1e-24:
                s += weight(math.sqrt(r2), re_n)
        if d[i] < re_n:
            s += wall_sum(walls, x[i, 0], x[i, 1], x[i, 2], d[i], ZN, FIX_N)
        if walls.pose.shape[0] > 0:
            s += bodies_number_density(walls, re_n, x[i, 0], x[i, 1], x[i, 2])
        n[i] = s


@nb.njit(cache=True, parallel=True)
def divergence(x, v, offsets, nbr, re_n, grad_coef, d, walls, g_dt, div, moment2):
    """MPS divergence <div u>_i = (d / n0) [sum_j (u_j - u_i) . (x_j - x_i) / r_ij^2 w(r_ij)
    - (u_i - g dt) . G(x_i)] (``grad_coef`` = d / n0), G the wall maps' sum (x_w - x_i) / r^2 w over the
    resting walls (u_w = 0). The g dt part of u* into the wall is left out because the hydrostatic wall
    pressure (p_w = p_i + rho g . (x_w - x_i)) already balances it: counted twice, a tank at rest would
    be driven towards twice rho g h at the floor. A moving wall's particles move with it: its term is
    (u_b - (u_i - g dt)) . G_b, u_b the wall's velocity at the particle.
    Over the same pairs and walls, ``moment2`` = (d / n0)^2 |m_i|^2, m_i = sum_j (x_j - x_i) / r_ij^2 w(r_ij) + G(x_i)
    (moving walls included) the first moment of i's neighbourhood: the Poisson rows' repulsion term (_fill_rows)."""
    r2max = re_n * re_n
    for i in nb.prange(x.shape[0]):
        s = 0.0
        mx = 0.0
        my = 0.0
        mz = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < r2max and r2 > 1e-24:
                wr = weight_over_r2(r2, re_n)
                du = (v[j, 0] - v[i, 0]) * dx + (v[j, 1] - v[i, 1]) * dy + (v[j, 2] - v[i, 2]) * dz
                s += du * wr
                mx += wr * dx
                my += wr * dy
                mz += wr * dz
        xi, yi, zi, di = x[i, 0], x[i, 1], x[i, 2], d[i]
        if di < re_n:
            gx = wall_sum(walls, xi, yi, zi, di, G, FIX_G)
            gy = wall_sum(walls, xi, yi, zi, di, G + 1, FIX_G)
            gz = wall_sum(walls, xi, yi, zi, di, G + 2, FIX_G)
            s -= (v[i, 0] - g_dt[0]) * gx
            s -= (v[i, 1] - g_dt[1]) * gy
            s -= (v[i, 2] - g_dt[2]) * gz
            mx += gx
            my += gy
            mz += gz
        if walls.pose.shape[0] > 0:
            sb, bx, by, bz = bodies_divergence(walls, re_n, xi, yi, zi, v[i, 0] - g_dt[0], v[i, 1] - g_dt[1],
                                               v[i, 2] - g_dt[2])
            s += sb
            mx += bx
            my += by
            mz += bz
        div[i] = grad_coef * s
        moment2[i] = grad_coef * grad_coef * (mx * mx + my * my + mz * mz)


# -- pressure Poisson equation ----------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def _count_rows(x, offsets, nbr, re_l, dirichlet, row_counts):
    r2max = re_l * re_l
    for i in nb.prange(x.shape[0]):
        c = 0
        if not dirichlet[i]:
            for k in range(offsets[i], offsets[i + 1]):
                j = nbr[k]
                if dirichlet[j]:
                    continue
                dx = x[j, 0] - x[i, 0]
                dy = x[j, 1] - x[i, 1]
                dz = x[j, 2] - x[i, 2]
                r2 = dx * dx + dy * dy + dz * dz
                if r2 < r2max and r2 > 1e-24:
                    c += 1
        row_counts[i] = c


@nb.njit(cache=True, parallel=True)
def _fill_rows(x, offsets, nbr, re_l, lap_coef, dirichlet, n, n0, src_coef, div, div_coef, diag_extra, moment2, p_last,
               d, walls, g_vec, rho, row_off, cols, vals, diag, b):
    r2max = re_l * re_l
    for i in nb.prange(x.shape[0]):
        if dirichlet[i]:
            diag[i] = 1.0
            b[i] = 0.0
            continue
        k_out = row_off[i]
        s = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < r2max and r2 > 1e-24:
                w = lap_coef * weight(math.sqrt(r2), re_l)
                s += w
                if not dirichlet[j]:
                    cols[k_out] = j
                    vals[k_out] = -w
                    k_out += 1
        diag[i] = s + diag_extra + moment2[i]
        bi = src_coef * (n[i] - n0) / n0 + div_coef * div[i]
        # the wall's resting pressure p_w = p_i + rho g . (x_w - x_i) (walls/mps.py): the p_i part
        # cancels, the hydrostatic part rho g . M is known and moves to the right-hand side
        xi, yi, zi, di = x[i, 0], x[i, 1], x[i, 2], d[i]
        if di < re_l:
            gm = (g_vec[0] * wall_sum(walls, xi, yi, zi, di, M, FIX_M)
                  + g_vec[1] * wall_sum(walls, xi, yi, zi, di, M + 1, FIX_M)
                  + g_vec[2] * wall_sum(walls, xi, yi, zi, di, M + 2, FIX_M))
            bi += lap_coef * rho * gm
        if walls.pose.shape[0] > 0:
            bi += lap_coef * rho * bodies_hydrostatic(walls, re_l, xi, yi, zi, g_vec)
        b[i] = bi + moment2[i] * p_last[i]


@nb.njit(cache=True)
def build_poisson(x, offsets, nbr, re_l, lap_coef, dirichlet, n, n0, src_coef, div, div_coef, diag_extra, moment2, p_last,
                  d, walls, g_vec, rho, row_counts, row_off, cols, vals, diag, b):
    """The PPE  -<lap p>_i + (alpha rho / dt^2) p_i = src_coef (n*_i - n0) / n0 + div_coef <div u*>_i  as a CSR
    matrix: off-diagonals -c w(r_ij) between non-Dirichlet particles, diagonal c sum_j w(r_ij) plus
    the compressibility term ``diag_extra``, c = 2 d / (lambda n0). Dirichlet rows (free surface,
    p = 0) are identity rows, so the matrix stays symmetric positive definite. Returns nnz, or -1 when
    ``cols`` is too small (the caller grows it and calls again).

    The repulsion rows (issue 17, session 34): each row also counts what correct()'s p_min gradient does to the
    particle's own divergence beyond the Laplacian, for the change of its pressure from the last step
    (``p_last``). That gradient is the difference form sum_j (p_j - p_i) e_j plus a repulsion (p_i - p_min) m_i,
    m_i the first moment of the neighbourhood (walls included; e_j = (x_j - x_i) w / r^2), and the Laplacian
    models the difference form only. A change dp_i of i's pressure changes its divergence through the repulsion
    by (dt / rho) (d / n0)^2 |m_i|^2 dp_i (the corrective matrix left out): ``moment2`` = (d / n0)^2 |m_i|^2
    (divergence()) goes on the diagonal and moment2 p_last_i on the right-hand side.
    - m_i is about 0 in a full neighbourhood (the lattice, walls included) and large where it is lopsided:
      next to the free surface, or in a thin front hitting a wall. There, the Laplacian alone solved for 3-4 x
      the pressure that stops a particle in one step. The repulsion (p_min = 0 beside a free-surface particle)
      then threw single particles out at 2.9 x the scene's ballistic speed, and blew up the thin plate.
    - Counted for the whole pressure (moment2 p_min on the right), the rows also lowered the steady pressure
      where m_i is the wall maps' error: in a 20 degree wedge's apex the density error reached 271 % (40 %
      before)."""
    _count_rows(x, offsets, nbr, re_l, dirichlet, row_counts)
    nnz = prefix_sum(row_counts, row_off)
    if nnz > cols.shape[0]:
        return -1
    _fill_rows(x, offsets, nbr, re_l, lap_coef, dirichlet, n, n0, src_coef, div, div_coef, diag_extra, moment2, p_last,
               d, walls, g_vec, rho, row_off, cols, vals, diag, b)
    return nnz


@nb.njit(cache=True, parallel=True)
def _direction_spmv(row_off, cols, vals, diag, z, p, q, beta, partial):
    """p = z + beta p and q = A p as q = A z + beta q (the previous A p), in one pass; returns p . q
    (fixed-order block sums). One parallel region instead of two: each costs a thread barrier."""
    n = p.shape[0]
    nbk = partial.shape[0]
    bs = (n + nbk - 1) // nbk
    for bk in nb.prange(nbk):
        s = 0.0
        for i in range(bk * bs, min((bk + 1) * bs, n)):
            acc = diag[i] * z[i]
            for k in range(row_off[i], row_off[i + 1]):
                acc += vals[k] * z[cols[k]]
            pi = z[i] + beta * p[i]
            qi = acc + beta * q[i]
            p[i] = pi
            q[i] = qi
            s += pi * qi
        partial[bk] = s
    tot = 0.0
    for bk in range(nbk):
        tot += partial[bk]
    return tot


@nb.njit(cache=True, parallel=True)
def _residual(row_off, cols, vals, diag, x, b, r, z, partial, partial2):
    """r = b - A x, z = r / diag; returns (r . z, r . r, b . b)."""
    n = x.shape[0]
    nbk = partial.shape[0]
    bs = (n + nbk - 1) // nbk
    for bk in nb.prange(nbk):
        s = 0.0
        s2 = 0.0
        s3 = 0.0
        for i in range(bk * bs, min((bk + 1) * bs, n)):
            acc = diag[i] * x[i]
            for k in range(row_off[i], row_off[i + 1]):
                acc += vals[k] * x[cols[k]]
            ri = b[i] - acc
            r[i] = ri
            z[i] = ri / diag[i]
            s += ri * z[i]
            s2 += ri * ri
            s3 += b[i] * b[i]
        partial[bk] = s
        partial2[bk, 0] = s2
        partial2[bk, 1] = s3
    rz = 0.0
    rr = 0.0
    bb = 0.0
    for bk in range(nbk):
        rz += partial[bk]
        rr += partial2[bk, 0]
        bb += partial2[bk, 1]
    return rz, rr, bb


@nb.njit(cache=True, parallel=True)
def _update(x, r, z, p, q, diag, alpha, partial2):
    """x += alpha p, r -= alpha q, z = r / diag; returns (r . z, r . r)."""
    n = x.shape[0]
    nbk = partial2.shape[0]
    bs = (n + nbk - 1) // nbk
    for bk in nb.prange(nbk):
        s = 0.0
        s2 = 0.0
        for i in range(bk * bs, min((bk + 1) * bs, n)):
            x[i] += alpha * p[i]
            ri = r[i] - alpha * q[i]
            r[i] = ri
            zi = ri / diag[i]
            z[i] = zi
            s += ri * zi
            s2 += ri * ri
        partial2[bk, 0] = s
        partial2[bk, 1] = s2
    rz = 0.0
    rr = 0.0
    for bk in range(nbk):
        rz += partial2[bk, 0]
        rr += partial2[bk, 1]
    return rz, rr


@nb.njit(cache=True)
def pcg(row_off, cols, vals, diag, b, x, r, z, p, q, partial, partial2, rtol, max_iter):
    """Jacobi-preconditioned conjugate gradient for the SPD system of ``build_poisson``, from the
    initial guess in ``x`` (the previous step's pressure). Stops at ||r|| <= rtol ||b||. Returns the
    number of iterations."""
    rz, rr, bb = _residual(row_off, cols, vals, diag, x, b, r, z, partial, partial2)
    tol2 = rtol * rtol * max(bb, 1e-300)
    if rr <= tol2:
        return 0
    p[:] = 0.0
    q[:] = 0.0
    beta = 0.0
    it = 0
    while it < max_iter:
        it += 1
        pq = _direction_spmv(row_off, cols, vals, diag, z, p, q, beta, partial)
        if pq <= 0.0:
            break
        alpha = rz / pq
        rz_new, rr = _update(x, r, z, p, q, diag, alpha, partial2)
        if rr <= tol2:
            break
        beta = rz_new / rz
        rz = rz_new
    return it


# -- correction ------------------------------------------------------------------------------------
@nb.njit(cache=True, parallel=True)
def correct(xs, vs, p, offsets, nbr, re_g, grad_coef, d, walls, g_vec, rho, dirichlet, det_min, dt, x_out, v_out):
    """Pressure gradient <grad p>_i = C_i (d / n0) [sum_j (p_j - p_min_i) / r_ij^2 (x_j - x_i) w(r_ij)
    + (p_i - p_min_i) G(x_i) + rho T(x_i) g], p_min_i the smallest pressure of i and its neighbours; the
    wall terms are the wall maps' sums with the resting wall pressure p_w = p_i + rho g . (x_w - x_i)
    (walls/mps.py; a moving wall's turned into the world by its pose); then u = u* - (dt / rho) <grad p>,
    x = x* + dt (u - u*).

    C_i is the corrective matrix (Khayyer and Gotoh 2011; not yet in PHYSICS.md), the inverse of
    (d / n0) [sum_j (x_j - x_i)(x_j - x_i)^T / r_ij^2 w(r_ij) + T(x_i)] (identity on the cubic lattice),
    so a linear pressure gives its exact gradient on any particle arrangement: without it the tank at
    rest settles into a packing with that tensor's zz part 1.09 and the pressure 6-9 % below rho g h.
    Only where the tensor is well conditioned: C_i = I for free-surface particles (``dirichlet``) and
    where det < ``det_min`` (det_min <= 0 turns the correction off)."""
    r2max = re_g * re_g
    for i in nb.prange(xs.shape[0]):
        xi = xs[i, 0]
        yi = xs[i, 1]
        zi = xs[i, 2]
        pmin = p[i]
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = xs[j, 0] - xi
            dy = xs[j, 1] - yi
            dz = xs[j, 2] - zi
            if dx * dx + dy * dy + dz * dz < r2max and p[j] < pmin:
                pmin = p[j]
        gx = 0.0
        gy = 0.0
        gz = 0.0
        axx = 0.0
        ayy = 0.0
        azz = 0.0
        axy = 0.0
        axz = 0.0
        ayz = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = xs[j, 0] - xi
            dy = xs[j, 1] - yi
            dz = xs[j, 2] - zi
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < r2max and r2 > 1e-24:
                wr = weight_over_r2(r2, re_g)
                f = (p[j] - pmin) * wr
                gx += f * dx
                gy += f * dy
                gz += f * dz
                axx += wr * dx * dx
                ayy += wr * dy * dy
                azz += wr * dz * dz
                axy += wr * dx * dy
                axz += wr * dx * dz
                ayz += wr * dy * dz
        dp = p[i] - pmin
        if d[i] < re_g:
            di = d[i]
            gx += dp * wall_sum(walls, xi, yi, zi, di, G, FIX_G)
            gy += dp * wall_sum(walls, xi, yi, zi, di, G + 1, FIX_G)
            gz += dp * wall_sum(walls, xi, yi, zi, di, G + 2, FIX_G)
            txx = wall_sum(walls, xi, yi, zi, di, T, FIX_T)
            tyy = wall_sum(walls, xi, yi, zi, di, T + 1, FIX_T)
            tzz = wall_sum(walls, xi, yi, zi, di, T + 2, FIX_T)
            txy = wall_sum(walls, xi, yi, zi, di, T + 3, FIX_T)
            txz = wall_sum(walls, xi, yi, zi, di, T + 4, FIX_T)
            tyz = wall_sum(walls, xi, yi, zi, di, T + 5, FIX_T)
            gx += rho * (txx * g_vec[0] + txy * g_vec[1] + txz * g_vec[2])
            gy += rho * (txy * g_vec[0] + tyy * g_vec[1] + tyz * g_vec[2])
            gz += rho * (txz * g_vec[0] + tyz * g_vec[1] + tzz * g_vec[2])
            axx += txx
            ayy += tyy
            azz += tzz
            axy += txy
            axz += txz
            ayz += tyz
        if walls.pose.shape[0] > 0:
            bx, by, bz, txx, tyy, tzz, txy, txz, tyz = bodies_gradient(walls, re_g, xi, yi, zi, dp, rho, g_vec)
            gx += bx
            gy += by
            gz += bz
            axx += txx
            ayy += tyy
            azz += tzz
            axy += txy
            axz += txz
            ayz += tyz
        if det_min > 0.0 and not dirichlet[i]:
            axx *= grad_coef
            ayy *= grad_coef
            azz *= grad_coef
            axy *= grad_coef
            axz *= grad_coef
            ayz *= grad_coef
            c00 = ayy * azz - ayz * ayz
            c01 = axz * ayz - axy * azz
            c02 = axy * ayz - ayy * axz
            det = axx * c00 + axy * c01 + axz * c02
            if det > det_min:
                inv = 1.0 / det
                hx = (c00 * gx + c01 * gy + c02 * gz) * inv
                hy = (c01 * gx + (axx * azz - axz * axz) * gy + (axy * axz - axx * ayz) * gz) * inv
                hz = (c02 * gx + (axy * axz - axx * ayz) * gy + (axx * ayy - axy * axy) * gz) * inv
                gx = hx
                gy = hy
                gz = hz
        c = dt * grad_coef / rho
        dux = -c * gx
        duy = -c * gy
        duz = -c * gz
        v_out[i, 0] = vs[i, 0] + dux
        v_out[i, 1] = vs[i, 1] + duy
        v_out[i, 2] = vs[i, 2] + duz
        x_out[i, 0] = xi + dt * dux
        x_out[i, 1] = yi + dt * duy
        x_out[i, 2] = zi + dt * duz


@nb.njit(cache=True, parallel=True)
def clamp_negative(p):
    for i in nb.prange(p.shape[0]):
        if p[i] < 0.0:
            p[i] = 0.0


@nb.njit(cache=True, parallel=True)
def mark_free_surface(n, threshold, dirichlet):
    """Dirichlet (p = 0) where n*_i < beta n0."""
    for i in nb.prange(n.shape[0]):
        dirichlet[i] = n[i] < threshold


@nb.njit(cache=True)
def project_one(i, px, py, pz, v, walls, r_rep, max_corr, x_out):
    """Particle i at (px, py, pz) out of the static and moving walls (eq. 16): its position into x_out[i], its
    velocity, less the part into the walls, into v[i]."""
    vx, vy, vz = v[i, 0], v[i, 1], v[i, 2]
    px, py, pz, vx, vy, vz = push_out(walls, None, -1, px, py, pz, vx, vy, vz, r_rep, max_corr, False)
    if walls.pose.shape[0] > 0:
        px, py, pz, vx, vy, vz = bodies_push_out(walls, walls.pose, px, py, pz, vx, vy, vz, r_rep, max_corr, False)
    x_out[i, 0] = px
    x_out[i, 1] = py
    x_out[i, 2] = pz
    v[i, 0] = vx
    v[i, 1] = vy
    v[i, 2] = vz


@nb.njit(cache=True, parallel=True)
def project_out_of_walls(x, v, walls, r_rep, max_corr):
    """The (16) wall pressure as a position correction: a particle closer than r_rep moves back along
    the SDF normal (capped at max_corr per step; up to three projections for edges and corners) and
    loses its velocity component into the wall (relative to a moving wall's own velocity: it pushes)."""
    for i in nb.prange(x.shape[0]):
        project_one(i, x[i, 0], x[i, 1], x[i, 2], v, walls, r_rep, max_corr, x)


# Pairs the eq. 16 projection stacks. Where two walls meet at an acute angle (a V's apex), the points r_rep from
# both form a line, and the projection moves every particle between them onto it: mirror-image particles land on
# the same point. Nothing else parts such a pair (no mutual pressure gradient), so it stayed: in the stability
# suite's 20 degree wedge, pairs 0-0.005 l0 apart on that line had n / n0 1.5-1.7 (the weight is flat below
# R_MIN re, not zero) and threw their neighbours at up to 9.5 x the ballistic bound within a step. Closer than R_MIN re
# is stacked; an exactly coincident pair parts along STACK_AXIS (no axis nor common wall normal), the lower id to
# the minus side. (WCSPH stacks such pairs too, but parted to 0.2 l0 its pressure then threw them at 2.9 x the
# bound, against 1.75 x left merged, so only MPS parts them.)
STACK_AXIS = (1.0 / math.sqrt(14.0), 2.0 / math.sqrt(14.0), 3.0 / math.sqrt(14.0))


@nb.njit(cache=True, parallel=True)
def part_stacked(x, v, ids, offsets, nbr, r_sep, walls, r_rep, max_corr, x_out):
    """After the projection: each pair closer than r_sep moves apart by the shortfall, half each, in Jacobi form
    (from the same old positions: symmetric, deterministic, momentum-free), and a moved particle is projected out
    of the walls again. Positions only: the next pressure solve takes it from there. A pair parted along its line
    into a V's walls is projected back onto one point: the next step parts it along the V (a second pass within
    the step did that too, but in the stability suite's wedges it threw particles faster: 2.9 x the ballistic
    bound in 1 run of 35, against 1.64 x at most in one pass)."""
    r2max = r_sep * r_sep
    tiny2 = (1e-6 * r_sep) ** 2
    ax, ay, az = STACK_AXIS
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        mx = 0.0
        my = 0.0
        mz = 0.0
        for k in range(offsets[i], offsets[i + 1]):
            j = nbr[k]
            dx = x[j, 0] - xi
            dy = x[j, 1] - yi
            dz = x[j, 2] - zi
            r2 = dx * dx + dy * dy + dz * dz
            if r2 >= r2max or j == i:
                continue
            if r2 > tiny2:
                f = 0.5 * (r_sep / math.sqrt(r2) - 1.0)
                mx -= f * dx
                my -= f * dy
                mz -= f * dz
            else:
                s = 0.5 * r_sep if ids[i] > ids[j] else -0.5 * r_sep
                mx += s * ax
                my += s * ay
                mz += s * az
        if mx == 0.0 and my == 0.0 and mz == 0.0:
            x_out[i, 0] = xi
            x_out[i, 1] = yi
            x_out[i, 2] = zi
        else:
            project_one(i, xi + mx, yi + my, zi + mz, v, walls, r_rep, max_corr, x_out)


@nb.njit(cache=True, parallel=True)
def max_speed2(v):
    """max |v|^2 (an exact max, so deterministic)."""
    m = 0.0
    for i in nb.prange(v.shape[0]):
        s = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]
        m = max(m, s)
    return m
