"""The numba kernels of one weakly compressible SPH step with distance-function walls.

Every particle loop is a prange over i that writes only particle i (no scatter, no atomics), so the
result is bitwise deterministic whatever the thread count. Arrays are in cell order (see
neighbours.py). All lengths SI (metres), see driver.py.

One SPHSolver step: ``density_verlet`` and ``forces`` over a Verlet list (neighbours.neighbour_list
at radius h + skin, built with the cell sort only every few steps, when particles may have closed in
by the skin): the cell scan of ~290 candidates per particle happens once per build instead of twice
per step, and the kernel sums run over the ~30 real neighbours. The cell-scan forms
(``density_pressure``, ``forces`` without ``neighbours``) are the references in tests; DFSPH calls
the cell-scan ``forces`` for its non-pressure accelerations.

Effects are compile-time (issue 8). ``forces`` is ONE fused neighbour-loop kernel; each effect is an
optional argument that is either a tuple of its constants or None. Numba types None as NoneType and
prunes every ``if arg is not None:`` branch before lowering (dead-branch pruning), and cache=True keeps
one machine-code build per effect set on disk, so an absent effect costs nothing per pair.

    forces(x, v, rho, d, nrm, starts, lo, inv_cell, dims, h, mass, rho0, walls, gravity, acc,
           pressure, viscosity, tension, adhesion, friction, wind, attractor, neighbours=None, inv_rho=None,
           correction=None, wall_gradient=None, mirrored_wall=None)

    common   x, v (N,3) positions m, velocities m/s; rho (N,) density kg/m^3; d (N,) SDF distance m and
             nrm (N,3) SDF normal (into the fluid) of the nearest wall, both from density_pressure;
             starts/lo/inv_cell/dims the cell grid (neighbours.py); h support m; mass kg; rho0 kg/m^3;
             walls the walls.maps.Walls bundle (static SDF and bricked map, the moving walls and their
             poses, the flat-wall factor fix_rho and the tables' 1/dr); gravity (3,) m/s^2 (always added;
             zeros without the effect); acc (N,3) output, m/s^2 (overwritten).
    pressure   (p, grad_coef, av): p (N,) Pa; grad_coef the Spiky gradient coefficient (eq. 8, divided by
               the lattice factor); av = alpha c h, Monaghan's artificial viscosity (part of the WCSPH
               pressure term). The wall force is -(p_i / rho_i^2) grad of every wall's density share
               (walls.maps.wall_density). None: no pressure at all (DFSPH calls it this way for the
               non-pressure accelerations).
    viscosity  (mu, lap_coef, fix_vis): Pa s, eq. 9 coefficient, the Z_vis table (zeros = no wall term).
    tension    (k, normals, coh_coef): Akinci 2013 constant k (effects.tension_constant), the (N,3)
               particle normals from ``surface_normals`` (pointing into the fluid), 32 / (pi h^9).
    adhesion   (accel,): table over [0, h] of the wall adhesion acceleration m/s^2 (effects.py).
    friction   (rate,): tangential decay rate at wall contact, 1/s.
    wind       (u, drag): air velocity (3,) m/s, drag 1/s; on free-surface particles only.
    attractor  (point, k, soft): point (3,) m, a = k / r^2 (m^3/s^2), softening radius m.
    correction (L,): the kernel-gradient correction of ``gradient_correction`` on the pressure term.
    wall_gradient (t_nn, t_tt): the walls' share of the hydrostatic gradient (kernels.wall_gradient_tables).
    mirrored_wall (fix_press,): the former non-conservative wall pressure (mirrored particles at the
    neighbours' mean pressure along the map's Spiky channels 1-3, fix_press the flat-wall table over the
    lattice factor) instead of -(p_i / rho_i^2) grad Z.
    spline     not None: the pressure pair term with the cubic spline's gradient (walls.spline.spline_f;
               ``grad_coef`` its coefficient l), the gradient of the density's own kernel.
    These are pressure-term options (ignored without ``pressure``), None = off, compiled out like the effects.
"""
from __future__ import annotations

import math

import numba as nb

from stages.common.sdf import sdf_sample

from .kernels import FASTMATH
from .walls.spline import spline_f, spline_w
from .neighbours import cell_coords
from .walls.maps import (bodies_density, bodies_nearest, bodies_push_out, bodies_viscous, brick_sample,
                         brick_sample_1234, nearest_wall_velocity, push_out, static_distance,
                         wall_density)
from .walls.tables import table_lookup

EOS_LINEAR = 0
EOS_TAIT = 1


@nb.njit(cache=True, inline="always")
def _walls_and_pressure(i, s, xi, yi, zi, h, poly6_coef, mass, rho0, walls, eos, stiffness, clamp, rho, p, d, nrm,
                        lazy=False):
    """Particle i's density from its kernel sum ``s`` = sum_j (h^2 - r^2)^3 plus the wall term, its
    pressure, SDF distance and normal (the tail of eq. 11, 12 and eq. 5). ``lazy``: d[i] holds a lower
    bound of i's wall distance (``integrate`` keeps one); beyond h it is kept and the SDF not sampled
    (no wall term there, and nrm is only read within h). With moving walls (walls.pose) d and nrm are
    the nearest wall's, static or moving, and the wall term sums every wall (lazy must be False: the
    bound holds for static walls only)."""
    zw = 0.0
    if lazy and d[i] > h:
        dw = d[i]
    else:
        dw, gx, gy, gz = sdf_sample(walls.sdf, walls.sdf_o[0], walls.sdf_o[1], walls.sdf_o[2], walls.sdf_inv, xi, yi, zi)
        if dw < h:  # only particles within h of a wall have wall terms
            zw = brick_sample(walls.index, walls.bricks, walls.shape, walls.wo[0], walls.wo[1], walls.wo[2], walls.winv,
                              xi, yi, zi, 0) * table_lookup(walls.fix_rho, dw, walls.inv_dr)
        zw += bodies_density(walls, walls.pose, h, xi, yi, zi)
        dw, gx, gy, gz = bodies_nearest(walls, walls.pose, xi, yi, zi, dw, gx, gy, gz)
        d[i] = dw
        nrm[i, 0] = gx
        nrm[i, 1] = gy
        nrm[i, 2] = gz
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
def density_pressure(x, starts, lo, inv_cell, dims, h, poly6_coef, mass, rho0, walls, eos, stiffness, clamp, rho, p,
                     d, nrm, spline=None):
    """Eq. 11: rho_i = sum_j m W(r_ij) (eq. 4, 10, self included) + Z_rho (eq. 12) from the 3D wall
    map (walls/maps.py) times the flat-wall factor at the SDF distance r_iw; eq. 5 pressure
    p = k (rho - rho0) (or Tait, B = stiffness), optionally clamped at 0. Also stores the SDF distance
    ``d`` and wall normal ``nrm`` of each particle. Grid cells of size >= h (27 cells scanned);
    SPHSolver uses ``density_verlet`` instead. ``spline`` not None: the cubic spline instead of Poly6
    (``poly6_coef`` is then its coefficient k, walls.spline; the walls must be its SplineWallMaps)."""
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
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
                        if spline is not None:
                            s += spline_w(math.sqrt(r2), h, 1.0)
                        else:
                            q = h2 - r2
                            s += q * q * q
        _walls_and_pressure(i, s, xi, yi, zi, h, poly6_coef, mass, rho0, walls, eos, stiffness, clamp, rho, p, d, nrm)


@nb.njit(cache=True, parallel=True)
def density_verlet(x, nbr, cnt, cnt_in, h, poly6_coef, mass, rho0, walls, eos, stiffness, clamp, rho, p, d, nrm, inv_rho,
                   exact=True, spline=None):
    """``density_pressure`` (eq. 11, 12, 5) over a Verlet list, plus ``inv_rho`` = 1 / rho for ``forces``.
    nbr[i, :cnt[i]] holds every particle that was within h + skin of i when the list was built
    (neighbours.neighbour_list with that radius), so while no pair has closed in by more than the skin
    it holds every pair r < h. Each pass partitions the row in place, the pairs r < h first in their
    list order (the rest keep their slots for later steps), sums eq. 11 over them and leaves their
    count in ``cnt_in`` for ``forces``. Per particle only, so the result does not depend on the thread
    count. With a list at radius h (skin 0) in cell-scan order, bitwise ``density_pressure``.
    ``exact`` False: ``d`` holds the lower bounds ``integrate`` left, and particles further than h
    from a wall skip the SDF sample. ``spline`` as in ``density_pressure``."""
    h2 = h * h
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        s = 0.0
        k = 0
        for jj in range(cnt[i]):
            j = nbr[i, jj]
            dx = xi - x[j, 0]
            dy = yi - x[j, 1]
            dz = zi - x[j, 2]
            r2 = dx * dx + dy * dy + dz * dz
            # branch-free partition (selects, not jumps: about a quarter of the candidates are out)
            inside = r2 < h2
            if spline is not None:
                s += spline_w(math.sqrt(r2), h, 1.0)  # zero at r >= h
            else:
                q = max(h2 - r2, 0.0)
                s += q * q * q
            a = nbr[i, k]
            nbr[i, jj] = a if inside else j
            nbr[i, k] = j if inside else a
            k += inside
        cnt_in[i] = k
        _walls_and_pressure(i, s, xi, yi, zi, h, poly6_coef, mass, rho0, walls, eos, stiffness, clamp, rho, p, d, nrm,
                            not exact)
        inv_rho[i] = 1.0 / rho[i]


@nb.njit(cache=True, parallel=True)
def gradient_correction(x, nbr, cnt, inv_rho, rho, rho0, h, grad_coef, mass, none, full, d, nrm, wall_t, inv_dr,
                        wall_fade, out):
    """Kernel-gradient correction (Bonet and Lok 1999; Khayyer and Gotoh 2011 for MPS) for the eq. 6/8
    pressure force: out[i] = L_i = T_i^-1 stored as (xx, yy, zz, xy, xz, yz), with
    T_i = sum_j (m / rho_j) grad_i W_ij (x) (x_j - x_i) over the fluid neighbours (``grad_coef`` the
    normalised eq. 8 coefficient, so T = I on the rest lattice), plus the wall's share t_nn n n^T +
    t_tt (I - n n^T) from the tables ``wall_t`` = (t_nn, t_tt) at the SDF distance d (None: fluid only).
    Then sum_j V_j (p_j - p_i) L_i grad W_ij is exact for a linear pressure on any packing. Without the
    wall's share a particle beside a wall gets L far from I (1 / 0.64 along the normal), L_i != L_j
    across the first rows, and the spurious pair forces stir the tank at rest (measured).
    Blended towards the identity where the support is not full (the free surface): weight
    s = (rho_i / rho0 - none) / (full - none) clamped to [0, 1] on the FULL density (fluid + wall term, so
    a particle at a wall counts as full); identity too when det T < 0.05 (ill conditioned)."""
    h2 = h * h
    cg = mass * grad_coef
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        txx = 0.0
        tyy = 0.0
        tzz = 0.0
        txy = 0.0
        txz = 0.0
        tyz = 0.0
        for jj in range(cnt[i]):
            j = nbr[i, jj]
            dx = xi - x[j, 0]
            dy = yi - x[j, 1]
            dz = zi - x[j, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 > 1e-24 and r2 < h2:
                r = math.sqrt(r2)
                w = (h - r) * (h - r) / r * inv_rho[j]
                txx += w * dx * dx
                tyy += w * dy * dy
                tzz += w * dz * dz
                txy += w * dx * dy
                txz += w * dx * dz
                tyz += w * dy * dz
        txx *= cg
        tyy *= cg
        tzz *= cg
        txy *= cg
        txz *= cg
        tyz *= cg
        if wall_t is not None and d[i] < h:  # the wall's share (kernels.wall_gradient_tables)
            tnn = table_lookup(wall_t[0], d[i], inv_dr)
            ttt = table_lookup(wall_t[1], d[i], inv_dr)
            ex = nrm[i, 0]
            ey = nrm[i, 1]
            ez = nrm[i, 2]
            dt = tnn - ttt
            txx += ttt + dt * ex * ex
            tyy += ttt + dt * ey * ey
            tzz += ttt + dt * ez * ez
            txy += dt * ex * ey
            txz += dt * ex * ez
            tyz += dt * ey * ez
        # inverse of the symmetric 3x3 by cofactors
        cxx = tyy * tzz - tyz * tyz
        cyy = txx * tzz - txz * txz
        czz = txx * tyy - txy * txy
        cxy = txz * tyz - txy * tzz
        cxz = txy * tyz - tyy * txz
        cyz = txy * txz - txx * tyz
        det = txx * cxx + txy * cxy + txz * cxz
        s = min(max((rho[i] / rho0 - none) / (full - none), 0.0), 1.0)
        if wall_fade and d[i] < h:
            s *= min(max(2.0 * d[i] / h - 1.0, 0.0), 1.0)
        if det < 0.05:
            s = 0.0
        else:
            det = s / det
        out[i, 0] = 1.0 - s + cxx * det
        out[i, 1] = 1.0 - s + cyy * det
        out[i, 2] = 1.0 - s + czz * det
        out[i, 3] = cxy * det
        out[i, 4] = cxz * det
        out[i, 5] = cyz * det


@nb.njit(cache=True, parallel=True)
def surface_normals(x, rho, starts, lo, inv_cell, dims, h, grad_coef, mass, out, neighbours=None):
    """Akinci et al. 2013 particle normals n_i = h sum_j m/rho_j grad_i W_ij (Spiky gradient, eq. 8):
    |n| ~ 1 at the free surface, ~ 0 inside, pointing INTO the fluid as in the paper (the curvature term
    -k (n_i - n_j) then pushes a surface particle out and its inner neighbour in, which is what
    counteracts the cohesion's clustering at the surface; with outward normals a drop turns into a
    hollow shell). A pass after the density, run only when surface tension is declared. ``neighbours``
    as in ``forces`` (then the grid arguments are unused)."""
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    n_spans = 9
    if neighbours is not None:
        nbr = neighbours[0]
        cnt = neighbours[1]
        n_spans = 1
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        x0 = max(cx - 1, 0)
        x1 = min(cx + 1, nx - 1)
        sx = 0.0
        sy = 0.0
        sz = 0.0
        for span in range(n_spans):
            if neighbours is not None:
                first = 0
                last = min(cnt[i], nbr.shape[1])
            else:
                kz = cz - 1 + span // 3
                ky = cy - 1 + span % 3
                if kz < 0 or kz >= nz or ky < 0 or ky >= ny:
                    continue
                base = (kz * ny + ky) * nx
                first = starts[base + x0]
                last = starts[base + x1 + 1]
            for jj in range(first, last):
                if neighbours is not None:
                    j = nbr[i, jj]
                else:
                    j = jj
                dx = xi - x[j, 0]
                dy = yi - x[j, 1]
                dz = zi - x[j, 2]
                r2 = dx * dx + dy * dy + dz * dz
                if r2 < h2 and r2 > 1e-24:
                    r = math.sqrt(r2)
                    f = (h - r) * (h - r) / (r * rho[j])
                    sx += f * dx
                    sy += f * dy
                    sz += f * dz
        c = -h * mass * grad_coef  # grad_i W = -c (h - r)^2 (x_i - x_j) / r
        out[i, 0] = c * sx
        out[i, 1] = c * sy
        out[i, 2] = c * sz


# fastmath: lets LLVM contract and reorder the pair arithmetic (22 % faster at 20k, accelerations within
# 1e-15 relative of the strict build); still one fixed instruction sequence per particle, so the result
# does not depend on the thread count. FASTMATH keeps NaN/Inf semantics (the blow-up check needs them)
@nb.njit(cache=True, parallel=True, fastmath=FASTMATH)
def forces(x, v, rho, d, nrm, starts, lo, inv_cell, dims, h, mass, rho0, walls, gravity, acc, pressure, viscosity, tension, adhesion, friction, wind, attractor, neighbours=None, inv_rho=None,
           correction=None, wall_gradient=None, mirrored_wall=None, spline=None):
    """Acceleration of every particle: gravity plus the declared effects (module docstring). Pressure
    eq. 6, 8 (+ Monaghan av) and the wall pressure -(p_i / rho_i^2) grad Z of the wall density Z (or the
    mirrored form, ``mirrored_wall``); viscosity eq. 7, 9 and the wall term eq. 13-15; tension, adhesion,
    friction, wind, attractor as in PHYSICS.md "Effects".

    ``neighbours`` = (nbr, cnt_in) from ``density_verlet`` at the same positions: the pairs r < h are
    taken from the list instead of the 9 cell rows (the same sums to rounding).
    ``inv_rho`` (N,) = 1 / rho from ``density_verlet``, optional: saves a division per pair.
    ``correction`` (L,) with L (N, 6) from ``gradient_correction``, optional: the pressure pair term
    uses the symmetrised corrected gradient 0.5 (L_i + L_j) grad W_ij (the pair force stays
    antisymmetric, so momentum is conserved) and the wall pressure term L_i G_w.
    ``wall_gradient`` (t_nn, t_tt) from kernels.wall_gradient_tables, optional: the wall's share of the
    hydrostatic pressure gradient, -T_wall(r_iw) g (Adami et al. 2012: wall pressure extrapolated with
    p_w = p_f + rho g . (x_w - x_f), the wall particles' pressure varying along the wall; with one uniform
    wall pressure a particle beside a side wall misses that share of its vertical support)."""
    h2 = h * h
    nx, ny, nz = dims[0], dims[1], dims[2]
    wo, winv, inv_dr = walls.wo, walls.winv, walls.inv_dr
    if correction is not None:
        lc = correction[0]
    if neighbours is not None:
        nbr = neighbours[0]
        cnt = neighbours[1]
        n_spans = 1
    else:
        n_spans = 9  # the (z, y) rows of 3 x-contiguous cells around particle i
    gx0 = gravity[0]
    gy0 = gravity[1]
    gz0 = gravity[2]
    if pressure is not None:
        p, grad_coef, av = pressure
    if viscosity is not None:
        mu, lap_coef, fix_vis = viscosity
    if tension is not None:
        k_ten, normals, coh_coef = tension
        h6_64 = h2 * h2 * h2 / 64.0
        # the curvature term has no weight, so it steps at its cutoff: just inside h, where no lattice
        # distance lies (h = 2 l0 is the start lattice's second neighbours': rounding of the unit
        # conversion put them in or out, and m and cm runs of one scene parted by 5 l0 in 0.3 s)
        h2_curv = h2 * (1.0 - 1e-9)
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
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
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
        if inv_rho is not None:
            inv_rhoi = inv_rho[i]
        else:
            inv_rhoi = 1.0 / rhoi
        if correction is not None:
            lxx = lc[i, 0]
            lyy = lc[i, 1]
            lzz = lc[i, 2]
            lxy = lc[i, 3]
            lxz = lc[i, 4]
            lyz = lc[i, 5]
        if tension is not None:
            nxi = normals[i, 0]
            nyi = normals[i, 1]
            nzi = normals[i, 2]
        near_wall = d[i] < h  # loop-invariant: LLVM unswitches the Shepard sum out of other particles' loops
        for span in range(n_spans):
            if neighbours is not None:
                first = 0
                last = min(cnt[i], nbr.shape[1])
            else:
                kz = cz - 1 + span // 3
                ky = cy - 1 + span % 3
                if kz < 0 or kz >= nz or ky < 0 or ky >= ny:
                    continue
                base = (kz * ny + ky) * nx
                first = starts[base + x0]
                last = starts[base + x1 + 1]
            for jj in range(first, last):
                if neighbours is not None:
                    j = nbr[i, jj]
                else:
                    j = jj
                dx = xi - x[j, 0]
                dy = yi - x[j, 1]
                dz = zi - x[j, 2]
                r2 = dx * dx + dy * dy + dz * dz
                if mirrored_wall is not None and pressure is not None:
                    if near_wall and r2 < h2:
                        q = h2 - r2
                        q = q * q * q
                        sp += p[j] * q
                        sw += q
                if r2 < h2 and r2 > 1e-24:
                    r = math.sqrt(r2)
                    hr = h - r
                    if inv_rho is not None:
                        inv_rhoj = inv_rho[j]
                    else:
                        inv_rhoj = 1.0 / rho[j]
                    if pressure is not None:
                        # eq. 6 with the Spiky gradient (eq. 8): -grad W = c (h - r)^2 (x_i - x_j) / r.
                        # Without eq. 6's factor 1/2 (Monaghan's symmetric form at rho ~ rho0): with
                        # it, sum V (p_i + p_j) / 2 grad W gives only half of grad p on a lattice,
                        # and the hydrostatic pressure came out twice rho g h
                        # Monaghan's artificial viscosity on approaching pairs (av = alpha c h): it
                        # dissipates the acoustic noise of the weakly compressible EOS; without it a
                        # dam break never settles and sprays into a gas. Symmetric in i, j.
                        vdx = (vxi - v[j, 0]) * dx + (vyi - v[j, 1]) * dy + (vzi - v[j, 2]) * dz
                        # f = [(p_i + p_j) / rho_j + av max(-vdx, 0) / (r^2 + eps) 2 rho_i / (rho_i + rho_j)]
                        #     (h - r)^2 / r
                        #   = [(p_i + p_j) D + av (|vdx| - vdx)] (h - r)^2 / (rho_j D r),
                        # D = (r^2 + eps) (1/rho_i + 1/rho_j): one division per pair, not three, and no
                        # rho_j read (|vdx| - vdx = 2 max(-vdx, 0) exactly: a receding pair adds an exact
                        # +0.0 without a branch, which was mispredicted for about half the pairs)
                        den = (r2 + eps) * (inv_rhoi + inv_rhoj)
                        if spline is not None:
                            # the derivative of sum m e(rho) exactly: (p_i / rho_i^2 + p_j / rho_j^2) rho_i
                            # (times m grad_coef / rho_i below)
                            f = ((pi * inv_rhoi * inv_rhoi + p[j] * inv_rhoj * inv_rhoj) * rhoi
                                 + inv_rhoj * av * (abs(vdx) - vdx) / den) * spline_f(r, h, 1.0)
                        else:
                            f = inv_rhoj * ((pi + p[j]) * den + av * (abs(vdx) - vdx)) * (hr * hr) / (den * r)
                        if correction is not None:
                            # 0.5 (L_i + L_j) applied to the pair direction (symmetric in i, j)
                            mxx = 0.5 * (lxx + lc[j, 0])
                            myy = 0.5 * (lyy + lc[j, 1])
                            mzz = 0.5 * (lzz + lc[j, 2])
                            mxy = 0.5 * (lxy + lc[j, 3])
                            mxz = 0.5 * (lxz + lc[j, 4])
                            myz = 0.5 * (lyz + lc[j, 5])
                            ax += f * (mxx * dx + mxy * dy + mxz * dz)
                            ay += f * (mxy * dx + myy * dy + myz * dz)
                            az += f * (mxz * dx + myz * dy + mzz * dz)
                        else:
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
                        if r2 < h2_curv:
                            ux -= kij * (nxi - normals[j, 0])
                            uy -= kij * (nyi - normals[j, 1])
                            uz -= kij * (nzi - normals[j, 2])
        w4 = 0.0
        if near_wall:  # the wall map's Z_vis
            w4 = brick_sample(walls.index, walls.bricks, walls.shape, wo[0], wo[1], wo[2], winv, xi, yi, zi, 4)
        if pressure is not None:
            c = mass * grad_coef * inv_rhoi
            ax = ax * c + gx0
            ay = ay * c + gy0
            az = az * c + gz0
            if near_wall:  # only particles within h of a wall have wall terms
                # the wall's pressure force is the derivative of the pressure energy through the wall's
                # share of the density, Z(x) = Z_rho(x) fix_rho(d(x)) (eq. 11-12): a = -(p_i / rho_i^2) grad Z.
                # Conservative, so a resting tank settles (with viscosity) instead of circulating: a wall
                # force along another direction or with another pressure (the Spiky sums of the map with the
                # neighbours' mean pressure) did work around closed loops (README, Water at rest)
                if mirrored_wall is not None:
                    # the former form: the wall as mirrored particles of pressure p_w = max(p_i, the
                    # neighbours' Shepard mean) along the map's Spiky direction (not conservative; kept
                    # for the gradient-corrected hydrostatic option, whose wall share was fitted to it)
                    w1, w2, w3, _ = brick_sample_1234(walls.index, walls.bricks, walls.shape, wo[0], wo[1], wo[2], winv,
                                                      xi, yi, zi)
                    cw = (pi + max(pi, sp / sw)) * inv_rhoi * table_lookup(mirrored_wall[0], d[i], inv_dr)
                    wx = cw * w1
                    wy = cw * w2
                    wz = cw * w3
                else:
                    # grad Z by central differences of Z = Z_rho fix_rho(d) half a map node apart: continuous
                    # in x, where the trilinear interpolants' own gradients (the map's, the SDF's normal) jump
                    # at node planes, and lattice particles sit on them (rounding then chose the side: a scene
                    # in mm ran differently from the same scene in m)
                    e = 0.5 / winv
                    ce = 0.5 / e
                    zx = ce * (wall_density(walls, h, xi + e, yi, zi)
                               - wall_density(walls, h, xi - e, yi, zi))
                    zy = ce * (wall_density(walls, h, xi, yi + e, zi)
                               - wall_density(walls, h, xi, yi - e, zi))
                    zz = ce * (wall_density(walls, h, xi, yi, zi + e)
                               - wall_density(walls, h, xi, yi, zi - e))
                    cw = -pi * inv_rhoi * inv_rhoi
                    wx = cw * zx
                    wy = cw * zy
                    wz = cw * zz
                if wall_gradient is not None:
                    # -T_wall g, T_wall = t_nn n n^T + t_tt (I - n n^T) along the SDF normal
                    tnn = table_lookup(wall_gradient[0], d[i], inv_dr)
                    ttt = table_lookup(wall_gradient[1], d[i], inv_dr)
                    gn = gx0 * nrm[i, 0] + gy0 * nrm[i, 1] + gz0 * nrm[i, 2]
                    wx -= ttt * gx0 + (tnn - ttt) * gn * nrm[i, 0]
                    wy -= ttt * gy0 + (tnn - ttt) * gn * nrm[i, 1]
                    wz -= ttt * gz0 + (tnn - ttt) * gn * nrm[i, 2]
                if correction is not None:  # the wall's share corrected like the fluid's
                    ax += lxx * wx + lxy * wy + lxz * wz
                    ay += lxy * wx + lyy * wy + lyz * wz
                    az += lxz * wx + lyz * wy + lzz * wz
                else:
                    ax += wx
                    ay += wy
                    az += wz
        else:
            ax = gx0
            ay = gy0
            az = gz0
        if viscosity is not None:
            if near_wall:
                # eq. 13-14: the resting wall's viscous term -mu v_i Z_vis(r_iw); a moving wall's -mu (v_i - v_w) Z_vis
                ds = static_distance(walls, walls.pose, d[i], xi, yi, zi)
                zw = 0.0
                if ds < h:
                    zw = mu * inv_rhoi * table_lookup(fix_vis, ds, inv_dr) * w4
                ax -= zw * vxi
                ay -= zw * vyi
                az -= zw * vzi
                mx, my, mz = bodies_viscous(walls, walls.pose, fix_vis, h, xi, yi, zi, vxi, vyi, vzi)
                cm = mu * inv_rhoi
                ax += cm * mx
                ay += cm * my
                az += cm * mz
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
                # the tangential velocity relative to the nearest wall (a moving wall carries its contact layer)
                wvx, wvy, wvz = nearest_wall_velocity(walls, walls.pose, d[i], xi, yi, zi)
                rx = vxi - wvx
                ry = vyi - wvy
                rz = vzi - wvz
                vn = rx * nrm[i, 0] + ry * nrm[i, 1] + rz * nrm[i, 2]
                ax -= wc * (rx - vn * nrm[i, 0])
                ay -= wc * (ry - vn * nrm[i, 1])
                az -= wc * (rz - vn * nrm[i, 2])
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


# the most sub-steps a move takes: a move longer than this many max_move in one step (hundreds of spacings) is a
# blow-up the guard reports after the step, and sub-stepping an unbounded move (a diverged solve's 1e30 m/s, or
# inf) would never return to it
MAX_SUB_STEPS = 1024


# walls.maps.push_out and move_near_walls are called, not inlined: numba inlines at its own IR level, so each
# kernel that inlined them typed and compiled their bodies again (integrate's two builds in the demo 27 -> 14 s);
# LLVM still inlines the machine code, and their callers are not fastmath, so the arithmetic is the same.
# (_walls_and_pressure above stays inlined: called, numba built it twice, for more than it saved.)
@nb.njit(cache=True, inline="always")
def sub_steps(step, max_move):
    """How many sub-steps a move of length ``step`` takes: moves no longer than ``max_move`` each (at most
    MAX_SUB_STEPS; one for a non-finite move, which the guard stops after the step)."""
    if not step > max_move:  # also NaN
        return 1
    return int(math.ceil(min(step / max_move, MAX_SUB_STEPS)))


@nb.njit(cache=True)
def move_near_walls(x0, y0, z0, vx, vy, vz, dt, walls, r_rep, max_corr, max_move):
    """x += dt v for a particle near a wall, in sub-steps no longer than ``max_move``, each followed by
    the eq. 16 push-out: a thin wall or shell on the trilinear SDF grid holds only against moves that
    short between two push-outs (stages.common.sdf.wall_move_limit). A particle moving less than
    ``max_move`` takes the single step it always took (bitwise). Moving walls are taken at their pose at
    the end of the step. Returns the new (x, v)."""
    n = sub_steps(dt * math.sqrt(vx * vx + vy * vy + vz * vz), max_move)
    h = dt / n
    px = x0
    py = y0
    pz = z0
    for _ in range(n):
        px += h * vx
        py += h * vy
        pz += h * vz
        px, py, pz, vx, vy, vz = push_out(walls, None, -1, px, py, pz, vx, vy, vz, r_rep, max_corr, True)
        px, py, pz, vx, vy, vz = bodies_push_out(walls, walls.pose, px, py, pz, vx, vy, vz, r_rep, max_corr, True)
    return px, py, pz, vx, vy, vz


@nb.njit(cache=True, parallel=True)
def integrate(x, v, acc, dt, walls, r_rep, max_corr, max_move, travel=None, d=None):
    """Symplectic Euler (v += dt a; x += dt v), then the wall pressure of eq. 16 as a position
    correction along the SDF normal for r_iw < r_rep, capped at ``max_corr`` per step, and removal of
    the velocity component into the wall; near walls the move is split into sub-steps of at most
    ``max_move``, each pushed out (``move_near_walls``), so fast particles do not tunnel through thin
    walls and shells. ``travel`` (N,), optional: each particle's path length is
    added to it (how far it can have moved since the Verlet list was built). ``d`` (N,), optional: a
    lower bound of each particle's wall distance before the move; where it stays above r_rep after
    the move, the SDF is not sampled (the eq. 16 test would find nothing: the trilinear SDF changes by
    at most sqrt(3) per unit length, so d - 2 |dx| bounds the new distance) and d is lowered by
    2 |dx|; elsewhere d is set to -1 (unknown, ``density_verlet`` samples it). Same result, less
    random access to the SDF grid for the particles in the bulk (static walls only: with moving walls
    ``d`` must be None)."""
    for i in nb.prange(x.shape[0]):
        vx = v[i, 0] + dt * acc[i, 0]
        vy = v[i, 1] + dt * acc[i, 1]
        vz = v[i, 2] + dt * acc[i, 2]
        step = dt * math.sqrt(vx * vx + vy * vy + vz * vz)
        if d is not None and d[i] - 2.0 * step >= r_rep:
            d[i] -= 2.0 * step
            # the sub-steps move_near_walls would take (no push-out finds anything): the same sums, bitwise
            n = sub_steps(step, max_move)
            h = dt / n
            px = x[i, 0]
            py = x[i, 1]
            pz = x[i, 2]
            for _ in range(n):
                px += h * vx
                py += h * vy
                pz += h * vz
        else:
            if d is not None:
                d[i] = -1.0
            px, py, pz, vx, vy, vz = move_near_walls(x[i, 0], x[i, 1], x[i, 2], vx, vy, vz, dt, walls, r_rep, max_corr,
                                                     max_move)
        if travel is not None:
            ex = px - x[i, 0]
            ey = py - x[i, 1]
            ez = pz - x[i, 2]
            travel[i] += math.sqrt(ex * ex + ey * ey + ez * ez)
        v[i, 0] = vx
        v[i, 1] = vy
        v[i, 2] = vz
        x[i, 0] = px
        x[i, 1] = py
        x[i, 2] = pz


@nb.njit(cache=True)
def max_speed2_accel2(v, acc):
    """(max |v|^2, max |a|^2) for the time-step limits, serial: 20k particles take ~20 us, less than
    waking the thread pool (measured in DFSPH); an exact max either way, so deterministic."""
    mv = 0.0
    ma = 0.0
    for i in range(v.shape[0]):
        mv = max(mv, v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
        ma = max(ma, acc[i, 0] * acc[i, 0] + acc[i, 1] * acc[i, 1] + acc[i, 2] * acc[i, 2])
    return mv, ma


@nb.njit(cache=True)
def max_of(a):
    """max(a) (0 for an empty array), serial: exact, so deterministic."""
    m = 0.0
    for i in range(a.shape[0]):
        m = max(m, a[i])
    return m
