"""Anisotropic kernels (Yu and Turk 2013) for surface_extract.marching_cubes (``anisotropic: true``), numba.

Per particle i, over its neighbours j within r_n = 1.5 R (R the kernel support), weights
w_ij = 1 - (r_ij / r_n)^3 (self included):
- the weighted mean m_i = sum w_ij x_j / sum w_ij;
- the weighted covariance C_i = sum w_ij (x_j - m_i)(x_j - m_i)^T / sum w_ij, eigenvalues s1 >= s2 >= s3
  (Jacobi rotations; no LAPACK per particle) with axes e_k;
- with fewer than N_eps = 25 neighbours (a droplet, a thin jet) or a degenerate C the kernel stays
  isotropic; otherwise the eigenvalues are clamped to s_k >= s1 / k_r (k_r = 4) and the kernel's axes
  are a_k = s_k / (s1 s2 s3)^(1/3): det = 1, so every kernel keeps the isotropic kernel's integral and
  Phi stays 1 inside the fluid (this normalisation takes the place of Yu and Turk's k_s, and an
  isotropic neighbourhood gives exactly the isotropic kernel; their k_n is our isotropic kernel).
  A surface particle's kernel becomes a disc, about 1.5 R across and 0.45 R thick on a flat surface:
  that is what smooths sheets (the top of a still 16^3 block: its faces' normals 1.3 degrees off the
  vertical on average instead of 5.3, its volume within 1.5 %).
- the kernel's centre: Yu and Turk's Laplacian smoothing x_i + lambda (m_i - x_i) (they use lambda
  0.9), here followed by Taubin's inflating step mu = -(lambda + 0.01) on the smoothed positions
  with the same weights. It is the parameter ``anisotropic_smoothing``, 0 by default: every
  smoothing of positions pulls a free surface's layer towards the fluid (its neighbours lie on one
  side), and measured on a still 16^3 block (cell 0.5 l0), lambda = 0.9 sank the flat surface by
  0.10 l0 even with the inflating step (volume 0.935 against 0.987 without smoothing) and made its
  normals no smoother (1.8 degrees); lambda = 0.5 sank it by 0.01 l0 (volume 0.975).
The kernel is W(|G_i (x - c_i)|) with G_i = sum_k e_k e_k^T / a_k, scattered over the grid nodes inside
its ellipsoid (each row's chord from the quadratic form).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from stages.simulate.neighbours import cell_coords

from .implicit import cell_grid

NEIGHBOURHOOD = 1.5  # r_n / R: 2.55 l0 at R = 1.7 l0, about 70 neighbours inside the fluid, 35 on a surface
N_EPS = 25  # fewer neighbours: isotropic kernel
K_R = 4.0  # largest / smallest axis


@nb.njit(cache=True, inline="always")
def _weight(r2, inv_rn3):
    """Yu and Turk's neighbour weight 1 - (r / r_n)^3 (for r < r_n)."""
    r = math.sqrt(r2)
    return 1.0 - r * r2 * inv_rn3


@nb.njit(cache=True, parallel=True)
def _means_and_covariance(x, starts, lo, inv_cell, dims, rn, mean, cov, count):
    """Weighted mean (N, 3), covariance (N, 6: xx yy zz xy xz yz) and neighbour count, all in cell order."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    rn2 = rn * rn
    inv_rn3 = 1.0 / (rn * rn * rn)
    for i in nb.prange(x.shape[0]):
        xi, yi, zi = x[i, 0], x[i, 1], x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        sw = sx = sy = sz = sxx = syy = szz = sxy = sxz = syz = 0.0
        n = 0
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + max(cx - 1, 0)], starts[base + min(cx + 1, nx - 1) + 1]):
                    dx = x[j, 0] - xi  # relative to x_i: the one-pass covariance stays accurate
                    dy = x[j, 1] - yi
                    dz = x[j, 2] - zi
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 >= rn2:
                        continue
                    w = _weight(r2, inv_rn3)
                    n += 1
                    sw += w
                    sx += w * dx
                    sy += w * dy
                    sz += w * dz
                    sxx += w * dx * dx
                    syy += w * dy * dy
                    szz += w * dz * dz
                    sxy += w * dx * dy
                    sxz += w * dx * dz
                    syz += w * dy * dz
        mx, my, mz = sx / sw, sy / sw, sz / sw
        mean[i, 0] = xi + mx
        mean[i, 1] = yi + my
        mean[i, 2] = zi + mz
        cov[i, 0] = sxx / sw - mx * mx
        cov[i, 1] = syy / sw - my * my
        cov[i, 2] = szz / sw - mz * mz
        cov[i, 3] = sxy / sw - mx * my
        cov[i, 4] = sxz / sw - mx * mz
        cov[i, 5] = syz / sw - my * mz
        count[i] = n


@nb.njit(cache=True, parallel=True)
def _weighted_mean_of(x, y, starts, lo, inv_cell, dims, rn, out):
    """out_i = sum w_ij y_j / sum w_ij with the weights of the positions ``x`` (cell order)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    rn2 = rn * rn
    inv_rn3 = 1.0 / (rn * rn * rn)
    for i in nb.prange(x.shape[0]):
        xi, yi, zi = x[i, 0], x[i, 1], x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        sw = sx = sy = sz = 0.0
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + max(cx - 1, 0)], starts[base + min(cx + 1, nx - 1) + 1]):
                    dx = x[j, 0] - xi
                    dy = x[j, 1] - yi
                    dz = x[j, 2] - zi
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 >= rn2:
                        continue
                    w = _weight(r2, inv_rn3)
                    sw += w
                    sx += w * (y[j, 0] - y[i, 0])
                    sy += w * (y[j, 1] - y[i, 1])
                    sz += w * (y[j, 2] - y[i, 2])
        out[i, 0] = y[i, 0] + sx / sw
        out[i, 1] = y[i, 1] + sy / sw
        out[i, 2] = y[i, 2] + sz / sw


@nb.njit(cache=True, inline="always")
def _jacobi_eigen(a, v):
    """Eigen-decomposition of the symmetric 3x3 ``a`` in place (cyclic Jacobi): the diagonal of ``a``
    ends as the eigenvalues, the columns of ``v`` as the eigenvectors."""
    for p in range(3):
        for q in range(3):
            v[p, q] = 1.0 if p == q else 0.0
    for _ in range(12):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        scale = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-24 * scale or off == 0.0:
            return
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):  # A <- A J
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(3):  # A <- J^T A
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(3):
                    vkp = v[k, p]
                    vkq = v[k, q]
                    v[k, p] = c * vkp - s * vkq
                    v[k, q] = s * vkp + c * vkq


@nb.njit(cache=True, parallel=True)
def _kernel_shapes(cov, count, n_eps, k_r, radius, metric, extent):
    """Per particle the metric M = G^T G (N, 6: xx yy zz xy xz yz) of its kernel, |G d|^2 = d^T M d, and the
    half extents (N, 3) of its support ellipsoid along x, y, z (R sqrt((G^-2)_kk))."""
    for i in nb.prange(cov.shape[0]):
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        a[0, 0], a[1, 1], a[2, 2] = cov[i, 0], cov[i, 1], cov[i, 2]
        a[0, 1] = a[1, 0] = cov[i, 3]
        a[0, 2] = a[2, 0] = cov[i, 4]
        a[1, 2] = a[2, 1] = cov[i, 5]
        iso = count[i] < n_eps
        s1 = 0.0
        if not iso:
            _jacobi_eigen(a, v)
            s1 = max(a[0, 0], a[1, 1], a[2, 2])
            iso = not s1 > 1e-12 * radius * radius  # all neighbours on one point (or NaN)
        if iso:
            metric[i, 0] = metric[i, 1] = metric[i, 2] = 1.0
            metric[i, 3] = metric[i, 4] = metric[i, 5] = 0.0
            extent[i, 0] = extent[i, 1] = extent[i, 2] = radius
            continue
        ax0 = max(a[0, 0], s1 / k_r)
        ax1 = max(a[1, 1], s1 / k_r)
        ax2 = max(a[2, 2], s1 / k_r)
        norm = (ax0 * ax1 * ax2) ** (1.0 / 3.0)
        ax0 /= norm
        ax1 /= norm
        ax2 /= norm
        m00 = m11 = m22 = m01 = m02 = m12 = 0.0
        e00 = e11 = e22 = 0.0
        for k in range(3):
            ak = ax0 if k == 0 else (ax1 if k == 1 else ax2)
            ex, ey, ez = v[0, k], v[1, k], v[2, k]
            g2 = 1.0 / (ak * ak)  # M = sum e e^T / a^2
            m00 += g2 * ex * ex
            m11 += g2 * ey * ey
            m22 += g2 * ez * ez
            m01 += g2 * ex * ey
            m02 += g2 * ex * ez
            m12 += g2 * ey * ez
            a2 = ak * ak  # G^-2 = sum e e^T a^2
            e00 += a2 * ex * ex
            e11 += a2 * ey * ey
            e22 += a2 * ez * ez
        metric[i, 0], metric[i, 1], metric[i, 2] = m00, m11, m22
        metric[i, 3], metric[i, 4], metric[i, 5] = m01, m02, m12
        extent[i, 0] = radius * math.sqrt(e00)
        extent[i, 1] = radius * math.sqrt(e11)
        extent[i, 2] = radius * math.sqrt(e22)


def anisotropic_kernels(x: np.ndarray, radius: float, smoothing: float = 0.0
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kernel centres (N, 3), kernel metrics (N, 6) and support half extents (N, 3) of particles ``x``
    for kernels of support ``radius``, centres smoothed with lambda = ``smoothing`` (module docstring).
    Finite for any input: a lone particle, collinear or coincident particles get the isotropic kernel
    or a clamped ellipsoid."""
    rn = NEIGHBOURHOOD * radius
    grid = cell_grid(x, rn)
    order = grid.sort(x)
    xs = np.ascontiguousarray(x[order])
    n = len(x)
    mean = np.empty((n, 3))
    cov = np.empty((n, 6))
    count = np.empty(n, np.int64)
    args = (grid.starts, grid.lo, 1.0 / grid.cell, grid.dims, rn)
    _means_and_covariance(xs, *args, mean, cov, count)
    centres_s = xs
    if smoothing > 0.0:
        smoothed = xs + smoothing * (mean - xs)
        mean2 = np.empty((n, 3))
        _weighted_mean_of(xs, smoothed, *args, mean2)
        centres_s = smoothed - (smoothing + 0.01) * (mean2 - smoothed)
    metric_s = np.empty((n, 6))
    extent_s = np.empty((n, 3))
    _kernel_shapes(cov, count, N_EPS, K_R, radius, metric_s, extent_s)
    centres = np.empty_like(centres_s)
    metric = np.empty_like(metric_s)
    extent = np.empty_like(extent_s)
    centres[order] = centres_s
    metric[order] = metric_s
    extent[order] = extent_s
    return centres, metric, extent


@nb.njit(cache=True, parallel=True, fastmath=True)
def scatter_anisotropic(x, vol, metric, extent, chunk_first, chunk_last, chunk_k0, grid_lo, inv_h, radius, phi):
    """``scatter_implicit`` with each particle's kernel W(|G_q d|) (Poly6 of support ``radius`` in the
    metric ``metric[q]`` = G^T G, det G = 1): nodes inside the ellipsoid of half extents ``extent[q]``,
    each row's chord from the quadratic d^T M d < R^2. Same chunking and order rules."""
    nz, ny, nx = phi.shape
    r2max = radius * radius
    coef = 315.0 / (64.0 * math.pi * radius ** 9)
    h = 1.0 / inv_h
    h32 = np.float32(h)
    zero = np.float32(0.0)
    r2max32 = np.float32(r2max)
    for c in nb.prange(len(chunk_first)):
        kc0 = chunk_k0[c]
        kc1 = chunk_k0[c + 1]
        for q in range(chunk_first[c], chunk_last[c]):
            px = x[q, 0]
            py = x[q, 1]
            pz = x[q, 2]
            m00, m11, m22 = metric[q, 0], metric[q, 1], metric[q, 2]
            m01, m02, m12 = metric[q, 3], metric[q, 4], metric[q, 5]
            cw = np.float32(coef * vol[q])
            fz = (pz - grid_lo[2]) * inv_h
            fy = (py - grid_lo[1]) * inv_h
            fx = (px - grid_lo[0]) * inv_h
            k0 = max(int(math.ceil(fz - extent[q, 2] * inv_h)), kc0)
            k1 = min(int(math.floor(fz + extent[q, 2] * inv_h)) + 1, kc1, nz)
            j0 = max(int(math.ceil(fy - extent[q, 1] * inv_h)), 0)
            j1 = min(int(math.floor(fy + extent[q, 1] * inv_h)) + 1, ny)
            for k in range(k0, k1):
                dz = grid_lo[2] + k * h - pz
                for j in range(j0, j1):
                    dy = grid_lo[1] + j * h - py
                    b = m01 * dy + m02 * dz  # d^T M d = m00 dx^2 + 2 b dx + c
                    cc = m11 * dy * dy + 2.0 * m12 * dy * dz + m22 * dz * dz
                    disc = b * b - m00 * (cc - r2max)
                    if disc <= 0.0:
                        continue
                    root = math.sqrt(disc)
                    xa = (-b - root) / m00
                    xb = (-b + root) / m00
                    i0 = max(int(math.ceil(fx + xa * inv_h)), 0)
                    i1 = min(int(math.floor(fx + xb * inv_h)) + 1, nx)
                    if i1 <= i0:
                        continue
                    row = phi[k, j]
                    gx0 = np.float32(grid_lo[0] - px)
                    a32 = np.float32(m00)
                    b32 = np.float32(2.0 * b)
                    c32 = np.float32(r2max32 - np.float32(cc))
                    for i in range(i0, i1):
                        dx = gx0 + np.float32(i) * h32
                        w = max(c32 - dx * (b32 + a32 * dx), zero)
                        row[i] += cw * w * w * w
