"""Frozen copy of the WCSPH density and force kernels as they were before the speed work of issue 4
(session 3, commit ec404de: 27 cells of size h scanned in both passes, no neighbour list), so that
bench_sph.py can time the old and the new step side by side in one process. Not used by the pipeline."""
from __future__ import annotations

import math

import numba as nb

from stages.common.sdf import sdf_sample
from stages.simulate.walls.maps import map_sample
from stages.simulate.walls.tables import table_lookup

EOS_LINEAR = 0
EOS_TAIT = 1


@nb.njit(cache=True, parallel=True)
def density_pressure(x, starts, lo, inv_cell, dims, h, poly6_coef, mass, rho0, wmap, wo, winv, fix_rho, inv_dr,
                     sdf, sdf_o, sdf_inv, eos, stiffness, clamp, rho, p, d, nrm):
    """Eq. 11: rho_i = sum_j m W(r_ij) (eq. 4, 10, self included) + Z_rho (eq. 12) from the 3D wall
    map (walls/maps.py) times the flat-wall factor at the SDF distance r_iw; eq. 5 pressure p = k (rho - rho0) (or Tait, B = stiffness), optionally
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


@nb.njit(cache=True, parallel=True)
def forces(x, v, rho, d, nrm, starts, lo, inv_cell, dims, h, mass, rho0, wmap, wo, winv, inv_dr, gravity, acc,
           pressure, viscosity, tension, adhesion, friction, wind, attractor):
    """Acceleration of every particle: gravity plus the declared effects (module docstring). Pressure
    eq. 6, 8 (+ Monaghan av) and the wall pressure along the wall map; viscosity eq. 7, 9 and the wall
    term eq. 13-15; tension, adhesion, friction, wind, attractor as in PHYSICS.md "Effects"."""
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    gx0 = gravity[0]
    gy0 = gravity[1]
    gz0 = gravity[2]
    if pressure is not None:
        p, grad_coef, fix_press, av = pressure
    if viscosity is not None:
        mu, lap_coef, fix_vis = viscosity
    if tension is not None:
        k_ten, normals, coh_coef = tension
        h6_64 = h2 * h2 * h2 / 64.0
    if adhesion is not None:
        adh_table = adhesion[0]
    if friction is not None:
        fr_rate = friction[0]
    if wind is not None:
        u_air, drag = wind
    if attractor is not None:
        a_pt, a_k, a_soft = attractor
        soft2 = a_soft * a_soft
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        vxi = v[i, 0]
        vyi = v[i, 1]
        vzi = v[i, 2]
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
        tx = 0.0
        ty = 0.0
        tz = 0.0
        ux = 0.0
        uy = 0.0
        uz = 0.0
        sp = 0.0
        sw = 1e-300
        pi = 0.0
        if pressure is not None:
            pi = p[i]
        if tension is not None:
            nxi = normals[i, 0]
            nyi = normals[i, 1]
            nzi = normals[i, 2]
        near_wall = d[i] < h  # loop-invariant: LLVM unswitches the Shepard sum out of other particles' loops
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + x0], starts[base + x1 + 1]):
                    dx = xi - x[j, 0]
                    dy = yi - x[j, 1]
                    dz = zi - x[j, 2]
                    r2 = dx * dx + dy * dy + dz * dz
                    if pressure is not None:
                        if near_wall and r2 < h2:
                            q = h2 - r2
                            q = q * q * q
                            sp += p[j] * q
                            sw += q
                    if r2 < h2 and r2 > 1e-24:
                        r = math.sqrt(r2)
                        hr = h - r
                        inv_rhoj = 1.0 / rho[j]
                        if pressure is not None:
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
                        if viscosity is not None:
                            # eq. 7 with the viscosity Laplacian (eq. 9)
                            w = hr * inv_rhoj
                            bx += (v[j, 0] - vxi) * w
                            by += (v[j, 1] - vyi) * w
                            bz += (v[j, 2] - vzi) * w
                        if tension is not None:
                            # Akinci 2013: cohesion C(r) (eq. 2) and curvature, both times K_ij
                            kij = 2.0 * rho0 / (rhoi + rho[j])
                            c3 = hr * hr * hr * r2 * r
                            if r > 0.5 * h:
                                cr = c3
                            else:
                                cr = 2.0 * c3 - h6_64
                            cc = kij * cr / r
                            tx -= cc * dx
                            ty -= cc * dy
                            tz -= cc * dz
                            ux -= kij * (nxi - normals[j, 0])
                            uy -= kij * (nyi - normals[j, 1])
                            uz -= kij * (nzi - normals[j, 2])
        inv_rhoi = 1.0 / rho[i]
        if pressure is not None:
            c = mass * grad_coef * inv_rhoi
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
        else:
            ax = gx0
            ay = gy0
            az = gz0
        if viscosity is not None:
            if near_wall:
                # eq. 13-14: the resting wall's viscous term -mu v_i Z_vis(r_iw)
                zw = mu * inv_rhoi * table_lookup(fix_vis, d[i], inv_dr) * map_sample(
                    wmap, wo[0], wo[1], wo[2], winv, xi, yi, zi, 4)
                ax -= zw * vxi
                ay -= zw * vyi
                az -= zw * vzi
            cv = mu * mass * lap_coef * inv_rhoi
            ax += bx * cv
            ay += by * cv
            az += bz * cv
        if tension is not None:
            # cohesion k m C; curvature k m / (100 h^3) (n_i - n_j): Akinci's -k (n_i - n_j) made an
            # acceleration with the weight SPlisHSPlasH's implementation has at its default resolution
            # (h = 0.1 m, m ~ 0.1 kg, so m / h^3 = 100 there), i.e. scale-free
            ct = k_ten * mass * coh_coef
            cn = 0.01 * k_ten * mass / (h2 * h)
            ax += ct * tx + cn * ux
            ay += ct * ty + cn * uy
            az += ct * tz + cn * uz
        if adhesion is not None:
            if near_wall:  # Akinci adhesion integrated over the wall half-space, towards the wall
                aa = table_lookup(adh_table, d[i], inv_dr)
                ax -= aa * nrm[i, 0]
                ay -= aa * nrm[i, 1]
                az -= aa * nrm[i, 2]
        if friction is not None:
            if near_wall:  # contact weight 1 up to d = h/2 (first layer), 0 at h
                wc = min(2.0 - 2.0 * d[i] / h, 1.0) * fr_rate
                vn = vxi * nrm[i, 0] + vyi * nrm[i, 1] + vzi * nrm[i, 2]
                ax -= wc * (vxi - vn * nrm[i, 0])
                ay -= wc * (vyi - vn * nrm[i, 1])
                az -= wc * (vzi - vn * nrm[i, 2])
        if wind is not None:
            # free surface = density deficit: full drag below 0.77 rho0, none above 0.97 rho0
            s = min(max((0.97 * rho0 - rhoi) / (0.2 * rho0), 0.0), 1.0) * drag
            ax += s * (u_air[0] - vxi)
            ay += s * (u_air[1] - vyi)
            az += s * (u_air[2] - vzi)
        if attractor is not None:
            ex = a_pt[0] - xi
            ey = a_pt[1] - yi
            ez = a_pt[2] - zi
            e2 = ex * ex + ey * ey + ez * ez + soft2
            ca = a_k / (e2 * math.sqrt(e2))
            ax += ca * ex
            ay += ca * ey
            az += ca * ez
        acc[i, 0] = ax
        acc[i, 1] = ay
        acc[i, 2] = az
