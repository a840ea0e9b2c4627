"""Fluid emitters: fill boxes, spheres and closed meshes with particles on a cubic lattice of
spacing l0, drop the ones that start inside a wall, and re-pack the band along walls the lattice does not
line up with (_fill_wall_band). Shared by every solver."""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Callable

import numba as nb
import numpy as np

from pipeline.scene import BoxEmitter, MeshEmitter, SphereEmitter, is_usd
from pipeline.stage import StageError
from stages.common.sdf import DEFAULT_SHELL_THICKNESS
from stages.common.sizes import LATTICE_SLACK, lattice_counts
from stages.common.wall_hints import box_text

from .kernels import rest_lattice
from .neighbours import cell_coords
from .walls.spline import flat_wall_tables, spline_coefs, spline_f, spline_np, spline_w



MAX_MESH_LATTICE = 1e8  # a mesh emitter's box tested point by point (2.4 GB of points): beyond, surely a scale slip


def lattice(lo, hi, l0: float) -> np.ndarray:
    """Cell-centred cubic lattice filling [lo, hi), centred in it: where the box is not a whole number of
    spacings the spare part of a spacing is split between the two faces (a lattice anchored at lo left it all
    on the hi side: a centred box started 0.25 l0 off centre and a symmetric dam break parted 3 l0 from its
    mirror image in 0.3 s)."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    n = lattice_counts(lo, hi, l0)
    if np.any(n <= 0):
        return np.zeros((0, 3))
    start = lo + 0.5 * np.maximum(hi - lo - n * l0, 0.0)
    axes = [start[a] + (np.arange(n[a]) + 0.5) * l0 for a in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def _read_mesh(em: MeshEmitter, path: Path, meters_per_unit: float, up_axis: str,
               log=None) -> tuple[np.ndarray, np.ndarray, bool]:
    """(vertices in scene units and up axis before the emitter's placement, triangles, closed?) of a mesh
    file or of the chosen meshes of a USD file (read as mesh_import reads a USD wall: world transforms,
    metersPerUnit, upAxis; an animated prim at its rest pose)."""
    from types import SimpleNamespace

    import trimesh

    from stages.mesh_import.trimesh_import import read_mesh_file, to_scene_frame

    if is_usd(em.mesh):
        from stages.mesh_import.usd_import import read_usd_wall

        # with the log: a file without units, layers in other units, cages are said as for a wall
        v, f = read_usd_wall(path, SimpleNamespace(prims=em.prims, include_invisible=False), meters_per_unit,
                             up_axis, log)[:2]
        mesh = trimesh.Trimesh(v, f)  # merges the prims' shared vertices, so a closed model reads as closed
        return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), bool(mesh.is_watertight)
    try:  # read as a wall file is: concave n-gons triangulated right (a fan across a notch filled it)
        v, f = read_mesh_file(path)
    except StageError as exc:
        raise StageError(f"fluid emitter mesh {exc}") from None
    if len(f) == 0:
        raise StageError(f"fluid emitter mesh {path}: has no triangles")
    mesh = trimesh.Trimesh(v, f)  # merged vertices: a closed model reads as closed
    # the file's units and up axis -> the scene's, as for a wall file
    v = to_scene_frame(np.asarray(mesh.vertices, np.float64), path, em.meters_per_unit, em.up_axis,
                       SimpleNamespace(meters_per_unit=meters_per_unit, up_axis=up_axis))
    return v, np.asarray(mesh.faces, np.int64), bool(mesh.is_watertight)


def _mesh_points(em: MeshEmitter, l0: float, resolve: Callable[[str], Path], meters_per_unit: float, up_axis: str,
                 log: logging.Logger) -> np.ndarray:
    """The lattice points inside the mesh by its generalized winding number (libigl, as sdf_bake's
    ``sign: winding``): |w| > 1/2 for either orientation, so duplicated or flipped faces and small cracks
    do not matter, and an open container (a bowl, a box without a lid) fills up to its rim, where w falls
    to 1/2. (open3d's three-ray occupancy vote filled an open box in an irregular pattern of layers.)"""
    from stages.common.meshes import winding_number
    from stages.common.placement import apply_placement

    path = resolve(em.mesh)
    v, faces, closed = _read_mesh(em, path, meters_per_unit, up_axis, log)
    v = apply_placement(v, em)
    points = int(np.prod(lattice_counts(v.min(axis=0), v.max(axis=0), l0).astype(float)))
    if points > MAX_MESH_LATTICE:
        # before allocating: a scale of 1000 asked for 35.8 TiB and ended in a MemoryError after the bake
        raise StageError(f"fluid emitter mesh {path}: placed, it spans {box_text(v.min(axis=0), v.max(axis=0))}: "
                         f"{points:,} lattice points at fluid.spacing {l0:g} to test, more than "
                         f"{MAX_MESH_LATTICE:,.0f}; check its scale and units")
    pts = lattice(v.min(axis=0), v.max(axis=0), l0)  # centred in the mesh's box, l0 / 2 inside a box mesh's faces
    if not closed:
        log.warning("fluid emitter mesh %s is not closed: filled where its winding number exceeds 1/2 (an open "
                    "container up to its rim)", path)
    w = winding_number(v, faces, pts)
    return pts[np.abs(w) > 0.5]


def emit(emitters, l0: float, resolve: Callable[[str], Path], meters_per_unit: float = 1.0,
         log: logging.Logger | None = None, up_axis: str = "Z") -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 3) and velocities (N, 3) of every emitter, in emitter order, in scene units
    (``meters_per_unit``, ``up_axis``: the scene's, for mesh files in other units and USD files)."""
    log = log or logging.getLogger(__name__)
    xs, vs = [], []
    for k, em in enumerate(emitters):
        if isinstance(em, BoxEmitter):
            pts = lattice(em.box.min, em.box.max, l0)
            size = np.subtract(em.box.max, em.box.min)
            held = len(pts) * l0 ** 3 / max(float(np.prod(size)), 1e-300)
            if len(pts) and held < 0.9:  # a 1.5-spacing slot holds one column: 0.67 of its water, silently
                log.warning("fluid.emitters.%d: the box holds %s particles, %.2f of its volume: its sides are not "
                            "whole numbers of the spacing %g (a lattice fills whole spacings); size it in whole "
                            "spacings or use a finer spacing", k,
                            " x ".join(map(str, lattice_counts(em.box.min, em.box.max, l0))), held, l0)
        elif isinstance(em, SphereEmitter):
            c = np.asarray(em.sphere.center, float)
            r = em.sphere.radius
            pts = lattice(c - r - 0.5 * l0, c + r + 0.5 * l0, l0)  # centred on c: symmetric about it
            # points on the sphere (a radius of whole spacings) are in, in any units: by rounding, the metre
            # scene kept 3 of 6 such points and the cm and mm scenes all 6 (254 against 257 particles)
            pts = pts[np.linalg.norm(pts - c, axis=1) <= r + LATTICE_SLACK * l0]
            if narrower_than_a_spacing(em, l0):
                # as a box: narrower than a spacing emits nothing (its centre point was 138 x the water of a
                # radius of 0.12 spacings, in silence)
                pts = pts[:0]
            held = len(pts) * l0 ** 3 / (4 / 3 * math.pi * r ** 3)
            if len(pts) and not 0.9 <= held <= 1 / 0.9:
                log.warning("fluid.emitters.%d: the sphere holds %d particles, %.2f of its volume: a radius of %.3g "
                            "spacings is coarse on the lattice; use a finer spacing or a larger radius", k, len(pts),
                            held, r / l0)
        elif isinstance(em, MeshEmitter):
            pts = _mesh_points(em, l0, resolve, meters_per_unit, up_axis, log)
        else:  # pragma: no cover - the scene model admits only these
            raise StageError(f"unknown emitter {type(em).__name__}")
        xs.append(pts)
        vs.append(np.broadcast_to(np.asarray(em.velocity, float), pts.shape))
    if any(len(pts) for pts in xs):  # none at all: simulate refuses the scene, naming the spacing
        for k, (em, pts) in enumerate(zip(emitters, xs)):
            if not len(pts) and isinstance(em, (BoxEmitter, SphereEmitter)):
                log.warning("fluid.emitters.%d: the %s is smaller than fluid.spacing (%g): it emits no particles", k,
                            "box" if isinstance(em, BoxEmitter) else "sphere", l0)
    x = np.concatenate(xs) if xs else np.zeros((0, 3))
    v = np.concatenate(vs) if vs else np.zeros((0, 3))
    return np.ascontiguousarray(x), np.ascontiguousarray(v)


def drop_overlaps(x: np.ndarray, v: np.ndarray, l0: float, log: logging.Logger) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop the particles that fall in the cell (the cube of side l0 it stands for) of one emitted before
    them: overlapping emitters give the volume of their union, and never two particles at one point (that
    doubles the density and blows the first step up: the stability suite's overlapping emitters). Every
    emitter fills an axis-aligned lattice, so the cells of one emitter tile its region; a distance rule
    (l0 / 2) kept both lattices where they were offset, up to twice the mass. Warns with the count."""
    if len(x) < 2:
        return x, v, 0
    from scipy.spatial import cKDTree
    # within l0 / 2 in every axis, the cell's boundary included (lattices offset by exactly half a spacing)
    pairs = cKDTree(x).query_pairs(0.5 * l0 * (1 + 1e-6), p=np.inf, output_type="ndarray")
    if len(pairs) == 0:
        return x, v, 0
    keep = np.ones(len(x), bool)
    keep[pairs.max(axis=1)] = False
    dropped = int(len(x) - keep.sum())
    log.warning("dropped %d of %d emitted particles inside the cells of particles emitted before them "
                "(overlapping emitters)", dropped, len(x))
    return np.ascontiguousarray(x[keep]), np.ascontiguousarray(v[keep]), dropped


def drop_inside_walls(x: np.ndarray, v: np.ndarray, sdf, l0: float, log: logging.Logger,
                      min_distance: float = 0.5, counts: dict | None = None,
                      progress=None) -> tuple[np.ndarray, np.ndarray, int]:
    """Keep particles whose SDF distance is at least ``min_distance`` l0 (particles spawned inside a
    solid make the first step explode) and that lie in the SDF grid, the band along walls off the lattice re-packed
    (_fill_wall_band); warn with the count dropped. ``counts`` (optional) receives how many were dropped at walls
    ("in_wall") and outside the grid ("outside"); ``progress`` (optional, Context.progress) shows the packing's."""
    if counts is not None:
        counts.update(in_wall=0, outside=0)
    if len(x) == 0:
        return x, v, 0
    d, _ = sdf.sample(x)
    in_grid = np.all((x >= sdf.origin) & (x <= sdf.upper), axis=1)
    clear = d >= (min_distance - 1e-3) * l0  # float32 SDF round-off
    keep = clear & in_grid
    x = np.array(x, np.float64)
    moved = _fill_wall_band(x, d, in_grid & ~clear & (d > 0), keep, sdf, l0, min_distance, log, progress)
    clear |= moved
    keep |= moved
    dropped = int(len(x) - keep.sum())
    near_wall, outside = int((in_grid & ~clear).sum()), int((~in_grid).sum())
    if near_wall:
        # inside a wall's solid (the emitter reaches into it: an open_box's walls stand inside its size) and only
        # near one (a wall off the lattice's axes) are different mistakes: the hint about tilted walls was given
        # for an emitter filling an axis-aligned open_box to its outer size
        # a point on a wall (d = 0 to the float32 SDF's round-off: a water mesh sharing a tilted container's faces)
        # is near it, not in it
        inside = d < -1e-3 * l0
        solid, close = int((in_grid & ~clear & inside).sum()), int((in_grid & ~clear & ~inside).sum())
        why = []
        if solid:
            why.append(f"{solid} inside a wall's solid: the emitter reaches into it (an open_box's walls are "
                       "mesh_import.open_box_thickness x its smaller horizontal size thick, inside its size; an open "
                       f"mesh's shell is walls[].shell.thickness thick, {DEFAULT_SHELL_THICKNESS:g} spacings unless set)")
        if close:
            why.append(f"{close} within {min_distance:.2g} l0 of one, with no room in the packing along it" + (
                " (a finer spacing loses less)" if close >= 0.05 * len(x) else ""))
        log.warning("dropped %d of %d emitted particles (%.1f %% of what the emitters filled) at walls: %s",
                    near_wall, len(x), 100.0 * near_wall / len(x), "; ".join(why))
    if outside:
        log.warning("dropped %d of %d emitted particles outside the simulation domain, %s (scene.domain sets it; "
                    "without it, the walls' box and a margin)", outside, len(x), box_text(sdf.origin, sdf.upper))
    if counts is not None:
        counts.update(in_wall=near_wall, outside=outside)
    return np.ascontiguousarray(x[keep]), np.ascontiguousarray(v[keep]), dropped


# the lattice's band along a wall it does not line up with is re-packed (emitters._fill_wall_band): particles this
# near a wall move, deeper ones stay on the lattice
FILL_BAND = 2.5  # l0
FILL_ROOM = 0.7  # l0: a point put back closer than this to another is left out (a stacked pair, not a packing)
FREE_GAP = 1.0  # l0: the band keeps this far from the empty cells beyond a free surface (the lattice keeps l0)
SPREAD_SWEEPS = 60
RELAX_SWEEPS = 200
CAP_ROUNDS, CAP_SWEEPS = 8, 40
FILL_DENSITY_SLACK = 0.02  # the band's kernel sum may exceed the lattice's by this before inserted points go
TABLE_SAMPLES = 256  # the walls' share tabulated over [0, h]


def _fill_wall_band(x: np.ndarray, d_all: np.ndarray, near: np.ndarray, keep: np.ndarray, sdf, l0: float,
                    min_distance: float, log: logging.Logger | None = None, progress=None) -> np.ndarray:
    """Put back the water a lattice loses along a wall it does not line up with. The lattice points inside the fluid's
    region but nearer a wall than ``min_distance`` l0 (``near``; ``d_all`` every point's SDF distance) move out
    along the wall's normal to that distance; then they and the kept particles within FILL_BAND l0 of a wall are
    re-packed: pushed apart where closer than 1.05 l0 (_spread), then moved down the gradient of their kernel sum
    (_relax: the cubic spline of support 2 l0, a wall counting as the lattice continued beyond a flat wall at the
    SDF distance), held ``min_distance`` l0 off the walls and FREE_GAP l0 from the empty cells next to the
    emitted ones, which count as fluid (a free surface stays where the lattice put it). Where the packing still
    sums above the lattice's (by FILL_DENSITY_SLACK), put-back points go. Positions change in place; returns the
    mask of the ``near`` points kept. ``progress`` (Context.progress) shows the sweeps; ``log`` gets a summary.

    Dropping every near point lost half a spacing of water along each such wall: a cylinder of radius 4.8 /
    9.6 / 19 spacings held 0.815 / 0.949 / 0.970 of its water and its level settled 1.7 spacings low; moving
    out only the points with 0.8 l0 of room (sessions 12-39) recovered a third of them. Now the count is close
    to the lattice's (every cell whose centre is in the fluid: the volume to the midpoint rule), 0.98-1.0 of the
    volume in a cylinder, a bowl and a turned box at 9.6 and 19 spacings, and WCSPH's density in the band at the
    start 0.98-1.005 of rho0 on average, against 0.93-0.95 before (tests/test_emission.py; benchmarks/rest_log.md,
    session 40). A wall on the lattice (a box tank) has no near points: nothing moves."""
    out = np.zeros(len(x), bool)
    idx = np.flatnonzero(near)
    if len(idx) == 0:
        return out
    from scipy.spatial import cKDTree

    started = time.perf_counter()
    # about 0.3 ms per particle of the band on 2 cores (bench_emission.py): a studio scene's band of 200k takes 60 s
    sweeps = SPREAD_SWEEPS + RELAX_SWEEPS + CAP_ROUNDS * CAP_SWEEPS
    bar = progress("packing the water along walls", sweeps) if progress is not None else None
    tick = bar.advance if bar is not None else (lambda amount=1.0: None)
    band = keep & (d_all < FILL_BAND * l0)
    movable = np.flatnonzero(band)
    mob = np.concatenate([movable, idx])
    inserted = np.zeros(len(mob), bool)
    inserted[len(movable):] = True
    # the particles the band's kernel reaches (2 l0) stay where they are; so do ghosts in the empty cells within
    # 2 l0 of the band that are not in a wall (beyond a free surface, or an emitter's side)
    held = x[keep & ~band & (d_all < (FILL_BAND + 2.0) * l0)]
    emitted = cKDTree(x[(d_all > -l0) & (d_all < (FILL_BAND + 2.5) * l0)])  # the emitted cells within 2 l0 of the band
    k = np.arange(-2, 3)
    steps = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3).astype(float)
    steps = steps[(np.abs(steps).sum(axis=1) > 0) & (np.linalg.norm(steps, axis=1) <= 2.0)] * l0
    ghosts = (x[mob][:, None, :] + steps[None]).reshape(-1, 3)
    ghosts = ghosts[emitted.query(ghosts, p=np.inf, distance_upper_bound=0.5 * l0)[0] > 0.5 * l0]
    if len(ghosts):
        ghosts = np.unique(np.round(ghosts / (1e-6 * l0)), axis=0) * (1e-6 * l0)
        ghosts = ghosts[sdf.sample(ghosts)[0] > 0]
    fixed = np.concatenate([held, ghosts])
    dmin = min_distance * l0

    def off_walls(y):
        for _ in range(4):  # along the normal, again where a second wall is near (an edge, a corner)
            d, n = sdf.sample(y)
            y += np.maximum(dmin - d, 0.0)[:, None] * n
        return y

    free = cKDTree(ghosts) if len(ghosts) else None

    def confined(y):
        # held FREE_GAP l0 from the ghosts (pushed out from the nearest, continuously: a tiny change of the walls makes
        # a tiny change of the fill): the band neither leaves the emitters' cells nor lifts the free surface
        if free is None:
            return y
        for _ in range(2):
            r, j = free.query(y, distance_upper_bound=FREE_GAP * l0)
            hit = np.flatnonzero(np.isfinite(r) & (r > 1e-9 * l0))
            y[hit] += ((FREE_GAP * l0 - r[hit]) / r[hit])[:, None] * (y[hit] - ghosts[j[hit]])
        return y

    y = off_walls(x[mob].copy())
    y = _spread(y, fixed, l0, off_walls, confined, tick)
    alive = np.ones(len(y), bool)
    y, dens = _relax(y, fixed, sdf, l0, off_walls, confined, RELAX_SWEEPS, tick)
    left = CAP_ROUNDS * CAP_SWEEPS
    for _ in range(CAP_ROUNDS):
        # the lattice's count can exceed the volume (the midpoint rule: a cylinder of radius 4.8 spacings holds 1.05
        # of it) and a packing denser than the lattice starts a weakly compressible fluid under pressure (5 % is 10
        # x the hydrostatic at c = 10 v): the inserted points where the sum is highest (no two within 2 l0) go
        y_alive = y[alive]
        over = np.flatnonzero(inserted[alive] & (dens > 1.0 + FILL_DENSITY_SLACK))
        if len(over):  # a point with no particle within l0 crowds none: its sum is the ghosts' and the walls'
            real = cKDTree(np.concatenate([y_alive, held]))
            over = over[real.query(y_alive[over], k=2, distance_upper_bound=l0)[0][:, 1] <= l0]
        if len(over) == 0:
            break
        order = over[np.argsort(-dens[over], kind="stable")]
        tree = cKDTree(y_alive[order])
        taken = np.zeros(len(order), bool)
        ids = np.flatnonzero(alive)
        for k in range(len(order)):
            if not taken[k]:
                taken[tree.query_ball_point(y_alive[order[k]], 2.0 * l0)] = True
                alive[ids[order[k]]] = False
        y[alive], dens = _relax(y[alive], fixed, sdf, l0, off_walls, confined, CAP_SWEEPS, tick)
        left -= CAP_SWEEPS
    tick(left)  # the rounds not needed
    # for the put-back points the walls win over the ghosts (the last sweep's confinement pushes points of a layer
    # thinner than FREE_GAP + dmin back towards the wall, and they were dropped); the kept particles end as the sweeps
    # left them, within 1e-3 l0 of dmin (projecting them too moved the stability suite's V trough by 4e-6 m and MPS's
    # peak there from 1.4 to 2.3 x the bound at one of three frame rates). A moved point still on top of another is
    # left out, nearest pairs first; so is one the walls hold too close
    y[inserted] = off_walls(y[inserted])
    alive &= ~(inserted & (sdf.sample(y)[0] < (min_distance - 1e-3) * l0))
    pairs = cKDTree(y).query_pairs(FILL_ROOM * l0, output_type="ndarray")
    if len(pairs):
        r = np.linalg.norm(y[pairs[:, 1]] - y[pairs[:, 0]], axis=1)
        for a, b in pairs[np.argsort(r, kind="stable")]:
            if alive[a] and alive[b] and (inserted[a] or inserted[b]):
                alive[b if inserted[b] else a] = False
    if len(fixed):
        alive &= ~(inserted & (cKDTree(fixed).query(y, distance_upper_bound=FILL_ROOM * l0)[0] < FILL_ROOM * l0))
    put = inserted & alive
    moved = ~inserted | put
    x[mob[moved]] = y[moved]
    out[mob[put]] = True
    if log is not None:
        log.info("packed the water along walls off the lattice: %d particles re-packed, %d of %d near points put "
                 "back (%.1f s)", len(movable), int(put.sum()), len(idx), time.perf_counter() - started)
    return out


def _spread(y, fixed, l0, off_walls, confined, tick):
    """Pairs closer than 1.05 l0 pushed apart (a moving particle a quarter of the overlap a sweep, half against a
    fixed one): the moved points start off their neighbours before the kernel sums take over."""
    from scipy.spatial import cKDTree

    r0 = 1.05 * l0
    fixed_tree = cKDTree(fixed) if len(fixed) else None
    for _ in range(SPREAD_SWEEPS):
        disp = np.zeros_like(y)
        pairs = cKDTree(y).query_pairs(r0, output_type="ndarray")
        if len(pairs):
            dv = y[pairs[:, 1]] - y[pairs[:, 0]]
            r = np.linalg.norm(dv, axis=1)
            ok = r > 1e-9 * l0
            push = (0.25 * (r0 - r[ok]) / r[ok])[:, None] * dv[ok]
            np.add.at(disp, pairs[ok, 1], push)
            np.subtract.at(disp, pairs[ok, 0], push)
        if fixed_tree is not None:
            r, j = fixed_tree.query(y, k=8, distance_upper_bound=r0)
            for c in range(r.shape[1]):
                hit = np.isfinite(r[:, c]) & (r[:, c] > 1e-9 * l0)
                disp[hit] += (0.5 * (r0 - r[hit, c]) / r[hit, c])[:, None] * (y[hit] - fixed[j[hit, c]])
        y = confined(off_walls(y + disp))
        tick()
    return y


def _relax(y, fixed, sdf, l0, off_walls, confined, sweeps, tick):
    """Each sweep moves every band particle by 0.1 l0^2 times minus the gradient of its kernel sum over the cubic
    lattice's (at most 0.05 l0): towards an even packing, the walls' share included (the flat-wall table at the
    SDF distance). Returns the positions and their kernel sums over the lattice's (1 inside a lattice)."""
    from .neighbours import CellGrid

    h = 2.0 * l0
    k, l = spline_coefs(h)
    # the walls' share: the spline's sum over the lattice continued beyond a flat wall (walls/spline.py's flat-wall
    # table), so a lattice's first two layers on a flat wall read the interior's sum exactly (the kernel's integral
    # over the half-space read 6 % high at l0 / 2); per unit mass, its derivative along the normal is -z_grad
    z_rho, z_grad, _ = flat_wall_tables(l0, h, 1.0, 1.0, TABLE_SAMPLES)
    dt = np.linspace(0.0, h, TABLE_SAMPLES)
    ref = float(spline_np(rest_lattice(l0, h)[1], h).sum())  # the sum inside a cubic lattice
    pts = np.concatenate([y, fixed])
    grid = CellGrid(pts.min(axis=0) - 2 * h, pts.max(axis=0) + 2 * h, h)
    in_cells = np.empty_like(pts)  # pts in cell order, refilled each sweep
    rho = np.zeros(len(y))
    grad = np.zeros_like(y)

    def sums(y):
        pts[:len(y)] = y
        np.take(pts, grid.sort(pts), axis=0, out=in_cells)
        _kernel_sums(y, in_cells, grid.starts, grid.lo, 1.0 / grid.cell, grid.dims, h, k, l, rho, grad)
        d, n = sdf.sample(y)
        dc = np.clip(d, 0.0, h)
        grad[:] -= np.interp(dc, dt, z_grad)[:, None] * n
        return (rho + np.interp(dc, dt, z_rho)) / ref

    for sweep in range(sweeps):
        sums(y)
        # the last quarter of the sweeps shrinks the step to nothing: the packing settles, so it changes smoothly with
        # the walls (a run of the same tank from a USD prop and from a config box started 1 % of l0 apart without it)
        step = (-0.1 * l0 * l0 / ref * min(1.0, 4.0 * (1.0 - sweep / sweeps))) * grad
        step *= np.minimum(1.0, 0.05 * l0 / np.maximum(np.linalg.norm(step, axis=1), 1e-300))[:, None]
        y = confined(off_walls(y + step))
        tick()
    return y, sums(y)


@nb.njit(cache=True, parallel=True)
def _kernel_sums(y, pts, starts, lo, inv_cell, dims, h, k, l, rho, grad):
    """The cubic spline's sum (support h, walls/spline.py's coefficients k, l) over ``pts`` (cell-sorted, cell size
    h, y among them) at each y, and its gradient with respect to y."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for i in nb.prange(y.shape[0]):
        xi, yi, zi = y[i, 0], y[i, 1], y[i, 2]
        cx, cy, cz = cell_coords(xi, yi, zi, lo[0], lo[1], lo[2], inv_cell, nx, ny, nz)
        s = 0.0
        gx = 0.0
        gy = 0.0
        gz = 0.0
        for kz in range(max(cz - 1, 0), min(cz + 2, nz)):
            for ky in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (kz * ny + ky) * nx
                for j in range(starts[base + max(cx - 1, 0)], starts[base + min(cx + 1, nx - 1) + 1]):
                    dx = xi - pts[j, 0]
                    dy = yi - pts[j, 1]
                    dz = zi - pts[j, 2]
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 < h * h:
                        r = math.sqrt(r2)
                        s += spline_w(r, h, k)
                        f = spline_f(r, h, l)  # -grad_i W = f (x_i - x_j)
                        gx -= f * dx
                        gy -= f * dy
                        gz -= f * dz
        rho[i] = s
        grad[i, 0] = gx
        grad[i, 1] = gy
        grad[i, 2] = gz


def emitter_files(ctx) -> list[Path]:
    """The layers and assets the USD mesh emitters compose, a .gltf emitter's buffers (the files themselves the
    engine finds): the simulate stages' ``external_files``, so an edit to a referenced layer is a new key."""
    from stages.mesh_import.trimesh_import import mesh_file_dependencies
    from stages.mesh_import.usd_import import usd_dependencies

    fluid = ctx.scene["fluid"]
    return [f for em in (fluid.emitters if fluid is not None else ()) if isinstance(em, MeshEmitter)
            for f in (usd_dependencies if is_usd(em.mesh) else mesh_file_dependencies)(ctx.resolve(em.mesh))]


def narrower_than_a_spacing(em, l0: float) -> bool:
    """A box or sphere emitter that emits nothing: some side under a spacing (a lattice fills whole spacings), a
    diameter under one. A mesh emitter's size is known only once it is read: False."""
    if isinstance(em, BoxEmitter):
        return bool(np.any(lattice_counts(em.box.min, em.box.max, l0) <= 0))
    if isinstance(em, SphereEmitter):
        return 2 * em.sphere.radius < l0 * (1 - LATTICE_SLACK)
    return False


def check_emitters(ctx, who: str) -> None:
    """The simulate stages' ``check``: a fluid of boxes and spheres all narrower than a spacing, with no inflow,
    is refused before anything runs (it was refused when simulate started, after the import and the bake).
    Their sizes are in the config; a mesh emitter's is known only once it is read."""
    fluid = ctx.scene["fluid"]
    if fluid is None or not fluid.emitters or fluid.inflow:
        return
    l0 = fluid.spacing
    if all(narrower_than_a_spacing(em, l0) for em in fluid.emitters):
        raise StageError(f"{who}: the emitters produced no particles in the fluid region: every emitter is smaller "
                         f"than fluid.spacing ({l0:g}) or empty")
