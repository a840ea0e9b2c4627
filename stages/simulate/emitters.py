"""Fluid emitters: fill boxes, spheres and closed meshes with particles on a cubic lattice of
spacing l0, then drop the ones that start inside (or too close to) a wall. Shared by SPH and MPS."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.scene import BoxEmitter, MeshEmitter, SphereEmitter, is_usd
from pipeline.stage import StageError
from stages.common.wall_hints import box_text


# a size within this many spacings of a whole number of them counts as that number
LATTICE_SLACK = 1e-4


def lattice_counts(lo, hi, l0: float) -> np.ndarray:
    """Lattice points per axis in the box [lo, hi): its size in whole spacings."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    # sizes typed to 6-7 digits after a unit conversion are a whole number of spacings to 1e-6 of it (a box of
    # 8 spacings in feet read 7.999994 and lost a layer, 23 % of the water); the tolerance also grows with the
    # coordinates: (hi - lo) of a box 1e7 m off the origin is off by ~1e-9 m, which dropped a whole row there
    slack = LATTICE_SLACK + 16 * np.finfo(float).eps * np.maximum(np.abs(lo), np.abs(hi)) / l0
    return np.floor((hi - lo) / l0 + slack).astype(int)


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
        elif isinstance(em, MeshEmitter):
            pts = _mesh_points(em, l0, resolve, meters_per_unit, up_axis, log)
        else:  # pragma: no cover - the scene model admits only these
            raise StageError(f"unknown emitter {type(em).__name__}")
        xs.append(pts)
        vs.append(np.broadcast_to(np.asarray(em.velocity, float), pts.shape))
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
                      min_distance: float = 0.5, counts: dict | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Keep particles whose SDF distance is at least ``min_distance`` l0 (particles spawned inside a
    solid make the first step explode) and that lie in the SDF grid; warn with the count dropped.
    ``counts`` (optional) receives how many were dropped at walls ("in_wall") and outside the grid ("outside")."""
    if counts is not None:
        counts.update(in_wall=0, outside=0)
    if len(x) == 0:
        return x, v, 0
    d, _ = sdf.sample(x)
    in_grid = np.all((x >= sdf.origin) & (x <= sdf.upper), axis=1)
    clear = d >= (min_distance - 1e-3) * l0  # float32 SDF round-off
    keep = clear & in_grid
    x = np.array(x, np.float64)
    moved = _move_off_walls(x, in_grid & ~clear & (d > 0), keep, sdf, l0, min_distance)
    clear |= moved
    keep |= moved
    dropped = int(len(x) - keep.sum())
    near_wall, outside = int((in_grid & ~clear).sum()), int((~in_grid).sum())
    if near_wall:
        # inside a wall's solid (the emitter reaches into it: an open_box's walls stand inside its size) and only
        # near one (a wall off the lattice's axes) are different mistakes: the hint about tilted walls was given
        # for an emitter filling an axis-aligned open_box to its outer size
        solid, close = int((in_grid & ~clear & (d <= 0)).sum()), int((in_grid & ~clear & (d > 0)).sum())
        why = []
        if solid:
            why.append(f"{solid} inside a wall's solid: the emitter reaches into it (an open_box's walls are "
                       "mesh_import.open_box_thickness x its smaller horizontal size thick, inside its size)")
        if close:
            why.append(f"{close} within {min_distance:.2g} l0 of one" + (
                ": walls not aligned with the axes lose up to half a spacing of water along them (a finer spacing "
                "loses less)" if close >= 0.05 * len(x) else ""))
        log.warning("dropped %d of %d emitted particles (%.1f %% of what the emitters filled) at walls: %s",
                    near_wall, len(x), 100.0 * near_wall / len(x), "; ".join(why))
    if outside:
        log.warning("dropped %d of %d emitted particles outside the simulation domain, %s (scene.domain sets it; "
                    "without it, the walls' box and a margin)", outside, len(x), box_text(sdf.origin, sdf.upper))
    if counts is not None:
        counts.update(in_wall=near_wall, outside=outside)
    return np.ascontiguousarray(x[keep]), np.ascontiguousarray(v[keep]), dropped


def _move_off_walls(x: np.ndarray, near: np.ndarray, keep: np.ndarray, sdf, l0: float, min_distance: float,
                    room: float = 0.8) -> np.ndarray:
    """Lattice points inside the fluid's region but nearer a wall than ``min_distance`` l0 move out along the
    wall's normal to that distance (in place); those that then have ``room`` l0 to every other particle are
    kept (returned as a mask). The lattice is axis-aligned and the walls need not be: dropping every such
    point lost half a spacing of water along each wall the lattice does not line up with (a tank turned 45
    degrees held 0.80 of the water of the same tank unturned, and its dam break ran 20 % short); moved
    points closer than ``room`` to another would start the fluid compressed (0.75 l0: the near-wall kernel sum
    13 % over the lattice's before the wall's share; 0.8 l0: below it). What this recovers depends on where the
    lattice rows fall: a dam break's column in a tank turned 45 degrees keeps 0.89 of the water (was 0.80); a
    tank whose turned walls fall exactly between rows keeps 0.84 either way (its moved points have 0.75 l0)."""
    out = np.zeros(len(x), bool)
    idx = np.flatnonzero(near)
    if len(idx) == 0:
        return out
    from scipy.spatial import cKDTree

    y = x[idx].copy()
    for _ in range(4):  # along the normal, again where a second wall is near (an edge, a corner)
        d, n = sdf.sample(y)
        y += np.maximum(min_distance * l0 - d, 0.0)[:, None] * n
    others = x[keep]
    fixed = cKDTree(others) if len(others) else None
    d, _ = sdf.sample(y)
    ok = d >= (min_distance - 1e-3) * l0
    if fixed is not None:
        ok &= fixed.query(y, distance_upper_bound=room * l0)[0] >= room * l0
    cand = np.flatnonzero(ok)
    if len(cand) > 1:  # among the moved ones too: of two closer than room, the later goes
        pairs = cKDTree(y[cand]).query_pairs(room * l0 * (1 - 1e-9), output_type="ndarray")
        if len(pairs):
            ok[cand[np.unique(pairs.max(axis=1))]] = False
    x[idx[ok]] = y[ok]
    out[idx[ok]] = True
    return out


def emitter_files(ctx) -> list[Path]:
    """The layers and assets the USD mesh emitters compose, a .gltf emitter's buffers (the files themselves the
    engine finds): the simulate stages' ``external_files``, so an edit to a referenced layer is a new key."""
    from stages.mesh_import.trimesh_import import mesh_file_dependencies
    from stages.mesh_import.usd_import import usd_dependencies

    fluid = ctx.scene["fluid"]
    return [f for em in (fluid.emitters if fluid is not None else ()) if isinstance(em, MeshEmitter)
            for f in (usd_dependencies if is_usd(em.mesh) else mesh_file_dependencies)(ctx.resolve(em.mesh))]
