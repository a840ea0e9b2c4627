"""The numba kernels of one weakly compressible SPH step with distance-function walls.

Every particle loop is a prange over i that writes only particle i (no scatter, no atomics), so the
result is bitwise deterministic whatever the thread count. Arrays are in cell order (see
neighbours.py). Effects are compile-time: ``forces_pressure`` and ``forces_pressure_viscosity`` are
two kernels built from one inlined body with a literal flag, so the pressure-only build contains no
viscosity code at all (issue 8 adds more flags the same way)."""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from stages.common.sdf import sdf_sample

from .wall_maps import map_sample
from .wall_tables import table_lookup

EOS_LINEAR = 0
EOS_TAIT = 1


@nb.njit(cache=True, parallel=True)
def density_pressure(x, starts, lo, inv_cell, dims, h, poly6_coef, mass, rho0, wmap, wo, winv, fix_rho, inv_dr,
                     sdf, sdf_o, sdf_inv, eos, stiffness, clamp, rho, p, d, nrm):
    """Eq. 11: rho_i = sum_j m W(r_ij) (eq. 4, 10, self included) + Z_rho (eq. 12) from the 3D wall
    map (wall_maps.py) times the flat-wall factor at the SDF distance r_iw; eq. 5 pressure p = k (rho - rho0) (or Tait, B = stiffness), optionally
    clamped at 0. Also stores the SDF distance ``d`` and wall normal ``nrm`` of each particle."""
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        cx = min(max(int(math.floor((xi - lo[0]) * inv_cell)), 0), nx - 1)
        cy = min(max(int(math.floor((yi - lo[1]) * inv_cell)), 0), ny - 1)
        cz = min(max(int(math.floor((zi - lo[2]) * inv_cell)), 0), nz - 1)
        x0 = max(cx - 1, 0)
        x1 = min(cx + 1, nx - 1)
        s = 0.0
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + x0], starts[base + x1 + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 < h2:
                        q = h2 - r2
                        s += q * q * q
        dw, gx, gy, gz = sdf_sample(sdf, sdf_o[0], sdf_o[1], sdf_o[2], sdf_inv, xi, yi, zi)
        d[i] = dw
        nrm[i, 0] = gx
        nrm[i, 1] = gy
        nrm[i, 2] = gz
        zw = 0.0
        if dw < h:  # only particles within h of a wall have wall terms
            zw = map_sample(wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi, 0) * table_lookup(fix_rho, dw, inv_dr)
        r = mass * poly6_coef * s + zw
        rho[i] = r
        if eos == EOS_TAIT:
            ratio = r / rho0
            r7 = ratio * ratio * ratio
            r7 = r7 * r7 * ratio
            pi = stiffness * (r7 - 1.0)
        else:
            pi = stiffness * (r - rho0)
        if clamp and pi < 0.0:
            pi = 0.0
        p[i] = pi


@nb.njit(cache=True, inline="always")
def _forces_body(x, v, rho, p, d, starts, lo, inv_cell, dims, h, spiky_coef, lap_coef, mass, mu,
                 wmap, wo, winv, fix_vis, fix_press, inv_dr, gravity, av, acc, with_viscosity):
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    gx0 = gravity[0]
    gy0 = gravity[1]
    gz0 = gravity[2]
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        vxi = v[i, 0]
        vyi = v[i, 1]
        vzi = v[i, 2]
        pi = p[i]
        rhoi = rho[i]
        cx = min(max(int(math.floor((xi - lo[0]) * inv_cell)), 0), nx - 1)
        cy = min(max(int(math.floor((yi - lo[1]) * inv_cell)), 0), ny - 1)
        cz = min(max(int(math.floor((zi - lo[2]) * inv_cell)), 0), nz - 1)
        x0 = max(cx - 1, 0)
        x1 = min(cx + 1, nx - 1)
        eps = 0.01 * h2
        ax = 0.0
        ay = 0.0
        az = 0.0
        bx = 0.0
        by = 0.0
        bz = 0.0
        sp = 0.0
        sw = 1e-300
        near_wall = d[i] < h  # loop-invariant: LLVM unswitches the Shepard sum out of other particles' loops
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + x0], starts[base + x1 + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    r2 = dx * dx + dy * dy + dz * dz
                    if near_wall and r2 < h2:
                        q = h2 - r2
                        q = q * q * q
                        sp += p[j] * q
                        sw += q
                    if r2 < h2 and r2 > 1e-24:
                        r = math.sqrt(r2)
                        hr = h - r
                        inv_rhoj = 1.0 / rho[j]
                        # eq. 6 with the Spiky gradient (eq. 8): -grad W = c (h - r)^2 (x_i - x_j) / r.
                        # Without eq. 6's factor 1/2 (Monaghan's symmetric form at rho ~ rho0): with
                        # it, sum V (p_i + p_j) / 2 grad W gives only half of grad p on a lattice,
                        # and the hydrostatic pressure came out twice rho g h
                        f = (pi + p[j]) * inv_rhoj
                        # Monaghan's artificial viscosity on approaching pairs (av = alpha c h): it
                        # dissipates the acoustic noise of the weakly compressible EOS; without it a
                        # dam break never settles and sprays into a gas. Symmetric in i, j.
                        vdx = (vxi - v[j, 0]) * dx + (vyi - v[j, 1]) * dy + (vzi - v[j, 2]) * dz
                        if vdx < 0.0:
                            f += av * (-vdx) / (r2 + eps) * 2.0 * rhoi / (rhoi + rho[j])
                        f *= hr * hr / r
                        ax += f * dx
                        ay += f * dy
                        az += f * dz
                        if with_viscosity:
                            # eq. 7 with the viscosity Laplacian (eq. 9)
                            w = hr * inv_rhoj
                            bx += (v[j, 0] - vxi) * w
                            by += (v[j, 1] - vyi) * w
                            bz += (v[j, 2] - vzi) * w
        inv_rhoi = 1.0 / rho[i]
        c = mass * spiky_coef * inv_rhoi
        ax = ax * c + gx0
        ay = ay * c + gy0
        az = az * c + gz0
        if near_wall:  # only particles within h of a wall have wall terms
            # the wall's share of eq. 6 along the wall map's gradient direction, rho_wall = rho0 and
            # p_wall the Shepard (Poly6-weighted) average of the neighbours' pressure, at least p_i
            pw = max(pi, sp / sw)
            cw = (pi + pw) * inv_rhoi * table_lookup(fix_press, d[i], inv_dr)
            ax += cw * map_sample(wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi, 1)
            ay += cw * map_sample(wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi, 2)
            az += cw * map_sample(wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi, 3)
            if with_viscosity:
                # eq. 13-14: the resting wall's viscous term -mu v_i Z_vis(r_iw)
                zw = mu * inv_rhoi * table_lookup(fix_vis, d[i], inv_dr) * map_sample(
                    wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi, 4)
                ax -= zw * vxi
                ay -= zw * vyi
                az -= zw * vzi
        if with_viscosity:
            cv = mu * mass * lap_coef * inv_rhoi
            ax += bx * cv
            ay += by * cv
            az += bz * cv
        acc[i, 0] = ax
        acc[i, 1] = ay
        acc[i, 2] = az


@nb.njit(cache=True, parallel=True)
def forces_pressure(x, v, rho, p, d, starts, lo, inv_cell, dims, h, spiky_coef, lap_coef, mass, mu,
                    wmap, wo, winv, fix_vis, fix_press, inv_dr, gravity, av, acc):
    """Acceleration from pressure (eq. 6, 8, with artificial viscosity ``av``) plus ``gravity``."""
    _forces_body(x, v, rho, p, d, starts, lo, inv_cell, dims, h, spiky_coef, lap_coef, mass, mu,
                 wmap, wo, winv, fix_vis, fix_press, inv_dr, gravity, av, acc, False)


@nb.njit(cache=True, parallel=True)
def forces_pressure_viscosity(x, v, rho, p, d, starts, lo, inv_cell, dims, h, spiky_coef, lap_coef,
                              mass, mu, wmap, wo, winv, fix_vis, fix_press, inv_dr, gravity, av, acc):
    """As ``forces_pressure`` plus fluid viscosity (eq. 7, 9) and wall viscosity (eq. 13-15)."""
    _forces_body(x, v, rho, p, d, starts, lo, inv_cell, dims, h, spiky_coef, lap_coef, mass, mu,
                 wmap, wo, winv, fix_vis, fix_press, inv_dr, gravity, av, acc, True)


@nb.njit(cache=True, parallel=True)
def integrate(x, v, acc, dt, sdf, sdf_o, sdf_inv, r_rep, max_corr):
    """Symplectic Euler (v += dt a; x += dt v), then the wall pressure of eq. 16 as a position
    correction along the SDF normal for r_iw < r_rep, capped at ``max_corr`` per step, and removal of
    the velocity component into the wall."""
    for i in nb.prange(x.shape[0]):
        vx = v[i, 0] + dt * acc[i, 0]
        vy = v[i, 1] + dt * acc[i, 1]
        vz = v[i, 2] + dt * acc[i, 2]
        px = x[i, 0] + dt * vx
        py = x[i, 1] + dt * vy
        pz = x[i, 2] + dt * vz
        # up to three projections: in an edge or corner each one finds the next closest wall
        for _ in range(3):
            dw, nx, ny, nz = sdf_sample(sdf, sdf_o[0], sdf_o[1], sdf_o[2], sdf_inv, px, py, pz)
            if dw >= r_rep * 0.999:
                break
            corr = min(r_rep - dw, max_corr)
            px += corr * nx
            py += corr * ny
            pz += corr * nz
            vn = vx * nx + vy * ny + vz * nz
            if vn < 0.0:
                vx -= vn * nx
                vy -= vn * ny
                vz -= vn * nz
        v[i, 0] = vx
        v[i, 1] = vy
        v[i, 2] = vz
        x[i, 0] = px
        x[i, 1] = py
        x[i, 2] = pz


@nb.njit(cache=True, parallel=True)
def max_speed2_accel2(v, acc):
    """(max |v|^2, max |a|^2) for the time-step limits; an exact max, so deterministic."""
    mv = 0.0
    ma = 0.0
    for i in nb.prange(v.shape[0]):
        s = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]
        a = acc[i, 0] * acc[i, 0] + acc[i, 1] * acc[i, 1] + acc[i, 2] * acc[i, 2]
        mv = max(mv, s)
        ma = max(ma, a)
    return mv, ma
