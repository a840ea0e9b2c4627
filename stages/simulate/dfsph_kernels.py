"""The numba kernels of Divergence-Free SPH (Bender and Koschier 2015, 2017) with distance-function
walls (PHYSICS.md eq. 11-16) treated like a boundary density map (Koschier and Bender 2017).

Notation (SI, arrays in cell order, see neighbours.py):
- density rho_i = sum_j m W_ij (eq. 4, 10, Poly6, self included) + Z_rho(x_i) (eq. 11-12, wall map);
- gradient grad_i W_ij = -f_ij (x_i - x_j) with f_ij = c (h - r)^2 / r (Spiky, eq. 8; c divided by the
  lattice factor of kernels.spiky_lattice_factor, as in the SPH solver), stored per pair as f_ij (float32);
  the option f_ij = 6 c6 (h^2 - r^2)^2 is the exact Poly6 derivative of the density, but it let a resting
  tank blow up (the Poly6 gradient vanishes for close pairs), so Spiky is the default;
- wall gradient Psi_i = sum_wall m grad_i W_iw, pointing into the wall: with the Spiky gradient (the
  default) -rho0 G(x_i) fix_press(d_i), G the wall map's wall-direction channels (the Spiky sums of the
  wall quadrature) and fix_press the flat-wall factor over the lattice factor, so it is the fluid's own
  gradient of the missing neighbours, edges and corners included; with the Poly6 gradient, grad Z_rho
  by central differences (step ``fd``) of the wall density itself;
- pressure acceleration (eq. 6 in kappa form, kappa = p / rho):
      a_i = -sum_j m (kappa_i / rho_i + kappa_j / rho_j) grad_i W_ij - WALL_MIRROR kappa_i / rho_i Psi_i
  (WALL_MIRROR = 1: the wall's share counts the particle's kappa once, as the boundary terms of
  Akinci et al. 2012 and SPlisHSPlasH's DFSPH do; 2 = a mirrored wall pressure p_wall = p_i, which
  made a resting tank unstable);
- rate of density change D rho_i / Dt = sum_j m (v_i - v_j) . grad_i W_ij + v_i . Psi_i (walls at rest);
- DFSPH factor alpha_i = rho_i / ((S_i + WALL_MIRROR Psi_i) . (S_i + Psi_i) + sum_j |m grad_i W_ij|^2),
  S_i the fluid part of sum_j m grad_i W_ij: the exact diagonal of the linearised solve;
- each solve is a projected, relaxed Jacobi iteration on the total kappa (>= 0), warm started, and stops on
  a weighted complementarity residual (session 39): the compression max(e, 0), plus EXPANSION_WEIGHT x the
  expansion max(-e, 0) where kappa_i > 0 (a pressure may not push the fluid apart). Counting the compression
  alone, a warm-started pressure that now expanded the fluid passed as converged: each step pushed a narrow
  column apart and kept the work, +184 % energy for one column in a pipe 2.5 spacings wide, +17 % for a jet into
  a pipe 3.5 wide, +5 % by the end of water poured into a closed cone at 1 cm.

Neighbour lists are built once per step in the density pass (fixed stride ``cap`` per particle; a
pass that finds more neighbours than ``cap`` reports it and the caller grows ``cap`` and runs the pass
again, so no neighbour is ever dropped); the solver iterations then loop over the lists only.
Every loop is a prange over i writing only row i: deterministic for any thread count. Sums over all
particles are left to the caller (serial numpy sums, fixed order)."""
from __future__ import annotations

import math

import numba as nb

from stages.common.sdf import sdf_sample

from .walls.spline import spline_f, spline_w
from .neighbours import cell_coords
from .walls.maps import map_density, wall_sample_1234
from .walls.tables import table_lookup

SPIKY, POLY6, SPLINE = 0, 1, 2  # the ``gradient`` modes of density_alpha_neighbours
# the share of the expansion under a positive pressure in each solve's error (the complementarity residual's
# weight): the expansion is allowed 5 x the tolerance the compression is. Measured (20k dam break, 0.3 s; density
# + divergence iterations a step; the cone at 1.4 / 1 cm, energy at the end / start): compression only 4.6 + 3.8,
# 1.045 / 1.057; weight 0.1: 5.0 + 3.7, 0.77 / 0.84; 0.2: 6.0 + 4.1, 0.71 / 0.78; 1 (the full residual): 11.2
# + 6.0, 0.68 / 0.72. Each stops the pipe's and the jet's energy. The density error is the same (0.14-0.15 %).
EXPANSION_WEIGHT = 0.2
WALL_MIRROR = 1.0  # the wall's share of the pressure acceleration counts kappa_i once (see above)


@nb.njit(cache=True, parallel=True)
def density_alpha_neighbours(x, starts, lo, inv_cell, dims, h, poly6_coef, grad_coef, mass, rho0, wmap, wo, winv,
                             fix_rho, fix_press, fd, inv_dr, sdf, sdf_o, sdf_inv, wall_mirror, mode, cap, nbr, fac, count,
                             rho, alpha, d, nrm, psi, warm, kappa, kappa_v, kr, kr_v):
    """One pass over the cell grid: density (eq. 11), SDF distance ``d`` and normal ``nrm``, wall
    gradient ``psi``, the DFSPH factor ``alpha`` and the neighbour list (``nbr``/``fac`` rows of stride
    ``cap``, ``count`` entries, j != i). Returns the largest neighbour count (exact max): if it exceeds
    ``cap`` the lists are incomplete and the caller must grow ``cap`` and call again.
    Also the warm starts of both solves (their rho is this pass's): kr = warm kappa / rho and
    kr_v = warm kappa_v / rho (one parallel region less each, which counts on a busy 2-core machine).
    ``mode`` SPIKY / POLY6: Poly6 density with that gradient (``poly6_coef``, ``grad_coef`` its
    coefficients); SPLINE: the cubic spline for both (walls/spline.py; ``poly6_coef`` and ``grad_coef``
    then carry its k and l, and the wall map must be spline.SplineWallMaps)."""
    spiky = mode != POLY6  # the wall terms of SPIKY and SPLINE are read the same way from their maps
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    most = 0
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        x0 = max(cx - 1, 0)
        x1 = min(cx + 1, nx - 1)
        s = 0.0
        sx = 0.0
        sy = 0.0
        sz = 0.0
        sq = 0.0
        n = 0
        row = i * cap
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + x0], starts[base + x1 + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 < h2:
                        if mode == SPLINE:
                            r = math.sqrt(r2)
                            s += spline_w(r, h, poly6_coef)
                            if j != i:
                                f = spline_f(r, h, grad_coef)  # -grad_i W_ij = f (x_i - x_j), the density's own
                                sx -= f * dx
                                sy -= f * dy
                                sz -= f * dz
                                sq += f * f * r2
                                if n < cap:
                                    nbr[row + n] = j
                                    fac[row + n] = f
                                n += 1
                            continue
                        q = h2 - r2
                        s += q * q * q
                        if j != i:
                            if spiky:  # eq. 8: -grad_i W_ij = c (h - r)^2 / r (x_i - x_j)
                                f = 0.0
                                if r2 > 1e-24:
                                    r = math.sqrt(r2)
                                    f = grad_coef * (h - r) * (h - r) / r
                            else:  # Poly6 (eq. 10) gradient: -grad_i W_ij = 6 c (h^2 - r^2)^2 (x_i - x_j)
                                f = grad_coef * q * q
                            # m grad_i W_ij = -m f (x_i - x_j)
                            sx -= f * dx
                            sy -= f * dy
                            sz -= f * dz
                            sq += f * f * r2
                            if n < cap:
                                nbr[row + n] = j
                                fac[row + n] = f
                            n += 1
        count[i] = n
        most = max(most, n)
        dw, gx, gy, gz = sdf_sample(sdf, sdf_o[0], sdf_o[1], sdf_o[2], sdf_inv, xi, yi, zi)
        d[i] = dw
        nrm[i, 0] = gx
        nrm[i, 1] = gy
        nrm[i, 2] = gz
        zw = 0.0
        px = 0.0
        py = 0.0
        pz = 0.0
        if spiky:
            if dw < h:  # only particles within h of a wall have wall terms
                zw = map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi, zi)
                # Psi = sum_wall m grad_i W_iw with the fluid's (normalised) Spiky gradient: the map's
                # wall direction G = (m / rho0) sum -grad W times the flat-wall factor, so Psi cancels the
                # fluid's S_i on the rest lattice at a floor, in edges and in corners alike (grad Z_rho
                # is the Poly6 slope: 11-13 % short of S in edges and corners, and S + Psi then pushed
                # compressed corner particles into the walls)
                g1, g2, g3, _ = wall_sample_1234(wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi)
                c = -rho0 * table_lookup(fix_press, dw, inv_dr)
                px = c * g1
                py = c * g2
                pz = c * g3
        elif dw < h + fd:
            zw = map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi, zi)
            # Poly6: Psi = grad Z_rho by central differences of the same function the density uses, so
            # the solver's predicted density change matches the real one, edges and corners included
            c = 0.5 / fd
            px = c * (map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi + fd, yi, zi)
                      - map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi - fd, yi, zi))
            py = c * (map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi + fd, zi)
                      - map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi - fd, zi))
            pz = c * (map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi, zi + fd)
                      - map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi, zi - fd))
        psi[i, 0] = px
        psi[i, 1] = py
        psi[i, 2] = pz
        r_i = mass * (s if mode == SPLINE else poly6_coef * s) + zw
        rho[i] = r_i
        sx *= mass
        sy *= mass
        sz *= mass
        sq *= mass * mass
        den = ((sx + wall_mirror * px) * (sx + px) + (sy + wall_mirror * py) * (sy + py)
               + (sz + wall_mirror * pz) * (sz + pz) + sq)
        den = max(den, sq)
        alpha[i] = r_i / den if den > 1e-9 * r_i * r_i / h2 else 0.0  # no neighbours: no pressure
        kr[i] = warm * kappa[i] / r_i
        kr_v[i] = warm * kappa_v[i] / r_i
    return most


@nb.njit(cache=True, parallel=True)
def predict_velocity(x, v, acc, dt, nbr, fac, count, cap, mass, psi, kr, wall_mirror, u):
    """u_i = v_i + dt (a_i + acc_i), a_i the pressure acceleration of the module docstring for the
    field kr = kappa / rho (eq. 6 in kappa form, the wall's share along Psi); ``acc`` the non-pressure
    accelerations (the density solve: v is the velocity before them) or None. Reads v and writes u at
    row i only, so ``u`` may be ``v`` (the last pass of a solve updates v in place)."""
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        ki = kr[i]
        ax = 0.0
        ay = 0.0
        az = 0.0
        row = i * cap
        for k in range(count[i]):
            j = nbr[row + k]
            f = (ki + kr[j]) * fac[row + k]
            ax += f * (xi - x[j, 0])
            ay += f * (yi - x[j, 1])
            az += f * (zi - x[j, 2])
        # -sum m kk grad_i W_ij = +sum m kk f (x_i - x_j); the wall: -mirror k_i Psi_i
        cw = wall_mirror * ki
        ax = mass * ax - cw * psi[i, 0]
        ay = mass * ay - cw * psi[i, 1]
        az = mass * az - cw * psi[i, 2]
        if acc is not None:
            ax += acc[i, 0]
            ay += acc[i, 1]
            az += acc[i, 2]
        u[i, 0] = v[i, 0] + dt * ax
        u[i, 1] = v[i, 1] + dt * ay
        u[i, 2] = v[i, 2] + dt * az


@nb.njit(cache=True, inline="always")
def _density_rate(i, x, u, nbr, fac, count, cap, mass, psi):
    """D rho_i / Dt = sum_j m (u_i - u_j) . grad_i W_ij + u_i . Psi_i at the velocities u (the wall is
    at rest)."""
    xi = x[i, 0]
    yi = x[i, 1]
    zi = x[i, 2]
    uxi = u[i, 0]
    uyi = u[i, 1]
    uzi = u[i, 2]
    s = 0.0
    row = i * cap
    for k in range(count[i]):
        j = nbr[row + k]
        s += fac[row + k] * ((uxi - u[j, 0]) * (xi - x[j, 0]) + (uyi - u[j, 1]) * (yi - x[j, 1])
                             + (uzi - u[j, 2]) * (zi - x[j, 2]))
    return -mass * s + uxi * psi[i, 0] + uyi * psi[i, 1] + uzi * psi[i, 2]


@nb.njit(cache=True, inline="always")
def _residual(e, k0):
    """One particle's share of a solve's error: the compression, plus EXPANSION_WEIGHT x the expansion under a
    positive pressure k0 (the weighted complementarity residual)."""
    return max(e, 0.0) + (EXPANSION_WEIGHT * max(-e, 0.0) if k0 > 0.0 else 0.0)


@nb.njit(cache=True, parallel=True)
def jacobi_density(x, u, nbr, fac, count, cap, mass, psi, rho, alpha, rho0, dt, beta, omega, kappa, kr, kr_out, err):
    """One projected, relaxed Jacobi sweep of the constant-density solve (Bender and Koschier 2017,
    Alg. 3, on the total kappa as in SPlisHSPlasH 2.x, so a warm start can be undone): predicted density
    rho*_i = rho_i + dt D rho_i / Dt at u = v + dt a(kappa); kappa_i += omega alpha_i (rho*_i - rho0) / dt^2,
    clamped at 0 (no tension: a free surface is not pulled together); kr_out_i = kappa_i / rho_i (kr, the
    field u came from, is left as it is: a solve that has converged keeps it and u). err_i, the weighted
    complementarity residual: the compression max(rho*_i - rho0, 0), plus EXPANSION_WEIGHT x the expansion where
    kappa_i > 0. The current kappa_i is kr_i rho_i (kr holds the warm start before the
    first sweep). ``beta`` (<= 1) is the share of the existing error rho_i - rho0 this
    step removes: rho*_i = rho0 + beta (rho_i - rho0) + dt D rho_i / Dt (Baumgarte: see DFSPHSolver.step)."""
    inv_dt2 = 1.0 / (dt * dt)
    for i in nb.prange(x.shape[0]):
        e = beta * (rho[i] - rho0) + dt * _density_rate(i, x, u, nbr, fac, count, cap, mass, psi)
        k0 = kr[i] * rho[i]
        err[i] = _residual(e, k0)
        k = max(k0 + omega * e * alpha[i] * inv_dt2, 0.0)
        kappa[i] = k
        kr_out[i] = k / rho[i]


@nb.njit(cache=True, parallel=True)
def jacobi_divergence(x, u, nbr, fac, count, cap, mass, psi, rho, alpha, dt, omega, min_rho, kappa, kr, kr_out, err):
    """One projected, relaxed Jacobi sweep of the divergence-free solve (Alg. 2): D rho_i / Dt at u,
    kappa_i += omega alpha_i (D rho_i / Dt) / dt, clamped at 0 (only compressing flow is corrected); err_i,
    the weighted complementarity residual as in jacobi_density.
    Particles with rho_i < min_rho (a sparse free-surface neighbourhood, SPlisHSPlasH's
    fewer-than-20-neighbours rule) are left alone. The current kappa_i is kr_i rho_i; the new one / rho_i
    goes to kr_out, as in jacobi_density."""
    inv_dt = 1.0 / dt
    for i in nb.prange(x.shape[0]):
        e = 0.0
        if rho[i] >= min_rho:
            e = _density_rate(i, x, u, nbr, fac, count, cap, mass, psi)
        k0 = kr[i] * rho[i]
        err[i] = _residual(e, k0)
        k = max(k0 + omega * e * alpha[i] * inv_dt, 0.0)
        kappa[i] = k
        kr_out[i] = k / rho[i]


@nb.njit(cache=True, parallel=True)
def gather_state(order, x, v, ids, kappa, kappa_v, x2, v2, ids2, kappa2, kappa_v2):
    """The solver state in cell order in ONE parallel region: row k of the outputs is row order[k] of
    the inputs (neighbours.reorder does one region per array)."""
    for k in nb.prange(order.shape[0]):
        j = order[k]
        x2[k, 0] = x[j, 0]
        x2[k, 1] = x[j, 1]
        x2[k, 2] = x[j, 2]
        v2[k, 0] = v[j, 0]
        v2[k, 1] = v[j, 1]
        v2[k, 2] = v[j, 2]
        ids2[k] = ids[j]
        kappa2[k] = kappa[j]
        kappa_v2[k] = kappa_v[j]


@nb.njit(cache=True, parallel=True)
def pressure_of(kappa, rho, p):
    """p_i = kappa_i rho_i (kappa = p / rho)."""
    for i in nb.prange(rho.shape[0]):
        p[i] = kappa[i] * rho[i]
