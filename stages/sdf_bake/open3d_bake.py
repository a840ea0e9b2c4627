"""sdf_bake.open3d: narrow-band signed distance of the walls on a regular grid (numba kernels in
mesh_distance.py; open3d ray casting as the reference and for the rare undecided signs).

Grid: node spacing ``cell * l0`` (l0 = fluid.spacing) covering scene.domain padded by ``margin * l0``,
or the walls' bounds padded by ``(min(band, GRID_BAND) + margin) * l0`` when no domain is given (the
grid's box is then the simulation's domain). A band wider than the default 4 l0 does not widen the grid:
it only makes more of it exact, and beyond the grid's edge consumers read the edge's nodes (band 100 padded
a 12-triangle box tank 24 l0 wide by 102 l0 a side: 88 M nodes, a 30 s bake, 4.8 GB, the simulation 8.5 x
slower). A grid of more than MAX_NODES nodes, the static and the moving walls' together, is refused in one
line naming the fields that size it (``grid_refusal``): before anything runs when the config tells its size
(builtin walls or scene.domain: ``check``), else before anything is allocated.

Band: |d| is exact up to ``band`` (4 l0 by default) and clamped to +-band beyond. The widest reach of
the default consumers sets it: MPS samples the wall distance up to its Laplacian radius r_e = 3.1 l0
(PHYSICS.md, MPS walls), SPH up to its support h = 2 l0 (eq. 11-16), wall_snap up to its band of
1 l0; a trilinear sample at distance r reads nodes up to r + sqrt(3) cell (0.87 l0 at cell 0.5), so
MPS needs 3.1 + 0.87 = 3.97 l0. A scene that runs SPH only can set band 3 (2 + 0.87, rounded up):
about a quarter fewer band nodes. At most 8 l0: no consumer reads farther at its widest settings (SPH and
DFSPH support, MPS r_e and surface_extract's radius 4 l0, wall_snap's band 5 l0 and its 0.75 l0 wet probe,
plus sqrt(3) cell at cell 1: 7.5 l0); beyond a wall's band only the sign is read.

Distance (mesh_distance.band_distance): nodes within ``exact_reach`` grid spacings of a wall are
measured against every triangle near them (exact); beyond, each node takes the closest of the
triangles its neighbours nearer the wall found (breadth first, then once more in order of distance).
That is the exact distance to some triangle of the wall (never below the true distance) and on the
dragon at 256^3 differs from open3d's exact distance at 0.2 % of the band nodes, by at most 0.05 grid
spacings (benchmarks/bench_sdf.py reports it). The work follows the band, i.e. the wall's area, not the
domain's volume.

Sign (PHYSICS.md: d > 0 in the fluid, n = grad d into the fluid): per wall, six votes from the parity
of crossings along the grid lines through each node (both ways along x, y and z;
mesh_distance.inside_votes). For a watertight mesh all six agree. A hole flips only the lines through
it and on such a line only one of its two votes, so holes and stray faces are outvoted; a node whose
votes tie (3 to 3, all three of its lines through holes) is decided by majority over ``sign_rays``
random directions with open3d (``count_intersections``). The wall's ``fluid`` side from walls.json says
whether inside is fluid (container) or solid (obstacle). For an open bowl (a surface with a big
opening, fluid "inside"), the cavity below the rim votes inside (five of six lines meet the bowl
twice) and the space above the opening outside, as if the bowl had a lid at its rim. Model open
containers as solids with thickness (mesh_import's builtin open_box does) and fluid "outside" so fluid
may leave them. Walls are combined by the minimum over walls: a point is fluid only if every wall
allows it. ``sign: auto`` (the default) is parity, but a wall whose closed parts cut into each other
(``interpenetrating_parts``; a tank kitbashed from overlapping boxes) is signed by the winding number: parity
calls their overlap open space, and the water filled the tank's wall posts. A shell wall whose closed parts
mesh_import made solids (an open tank and a rock in one file; WallMesh.solid) is baked as its open parts' shell
and its closed parts' solid, folded in by the minimum (``wall_pieces``).

Moving walls (walls.json "motion"): each is baked alone, in its rest pose, on its own bounds padded
by band + margin at the same node spacing (the whole band: beyond its box a body reads its border's nodes,
and posed_field takes those as at least the band), into bodies/<k>.npz (listed in bodies.json; loaded with
stages.common.sdf.load_bodies); sdf.npz holds the static walls only, on a box that also covers every
moving wall's swept bounds when no domain is given (+band everywhere when no wall stands still).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Mapping

import numpy as np
from pydantic import Field, field_validator

from pipeline.memory import human
from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import WallMesh
from stages.common.meshes import boundary_edge_count, winding_number
from stages.common.parts import mesh_parts, weld_equal
from stages.common.sdf import BODIES_DIR, BODIES_FILE, DEFAULT_SHELL_THICKNESS, SDFGrid, min_shell_thickness
from stages.common.sizes import BYTES_PER_SDF_NODE, sdf_estimate
from stages.common.wall_hints import spacing_hint, stray_text, write_wall_boxes
from stages.mesh_import.builtin import builtin_corners

from .mesh_distance import band_distance, inside_votes

if TYPE_CHECKING:  # imported where used (about 1.7 s); here for the annotations only
    import open3d as o3d

# 23-33 bytes per node while baking (the band's work arrays; 33 when the band fills the grid): 2.3-3.3 GB here.
# Beyond it the spacing is surely a mistake, whatever the memory (--yes does not lift it)
MAX_NODES = 100_000_000
GRID_BAND = 4.0  # l0: the most of the band that pads the walls' bounds into the grid (the default band)


class BakeParams(Params):
    cell: float = Field(0.5, gt=0, le=1.0, description="grid node spacing, in units of the particle spacing l0 (at "
                        "most 1: coarser grids misplace walls off their nodes; a box tank's lattice lost 1.3 % of its "
                        "water at 1.5 l0, 11.7 % at 10, its surface below the floor)")
    band: float = Field(4.0, ge=2.5, le=8, description="narrow-band half width where the distance is exact, in l0: "
                        "the widest consumer's reach plus sqrt(3) cell (MPS r_e 3.1 l0: 4; SPH only, support 2 l0: 3; "
                        "at most 8: no consumer reads farther at any of its settings); the grid pads the walls by at "
                        "most 4 of it")
    margin: float = Field(2.0, ge=0, le=100, description="padding of the grid around the domain, in l0")
    exact_reach: float = Field(4.0, ge=1.0, le=100, description="nodes within this many grid spacings of a wall are "
                               "measured against every triangle near them; beyond, closest triangles are handed "
                               "outwards from neighbours (a reach >= band / cell makes the whole band brute force)")
    sign_rays: int = Field(7, ge=1, le=99, description="random rays voting on inside/outside where the six grid-line "
                           "votes tie (odd)")
    sign: Literal["auto", "parity", "winding"] = Field("auto", description="inside/outside of a solid wall: parity "
                                                       "votes along the grid lines, or the generalized winding number "
                                                       "(libigl); auto: parity, and the winding number for a wall "
                                                       "whose closed parts cut into each other (parity calls their "
                                                       "overlap open space)")
    min_thickness: float | None = Field(None, ge=0, le=10, description="shells and the parts of watertight solids "
                                        "thinner than this (in l0) are baked this thick, so no particle crosses them; "
                                        "default: the least proven leak-free at this cell for WCSPH and MPS steps "
                                        "(cell + 0.05 l0); DFSPH at CFL 0.8 needs cell + 0.6 (1.1)")

    def min_thickness_l0(self) -> float:
        return min_shell_thickness(self.cell) if self.min_thickness is None else self.min_thickness

    @field_validator("sign_rays")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError("sign_rays must be odd")
        return v


def _raycasting_scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    import open3d as o3d  # imported where used: a cached run or `pipeline status` need not load it (~1 s)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene


class WallField:
    """One wall's exact signed distance (d > 0 on its fluid side) at arbitrary points."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, fluid: str, watertight: bool, sign_rays: int,
                 shell: float = 0.0):
        # open3d works in float32: about the mesh's box centre, not in world coordinates (8 mm steps 1e5 m out)
        used = np.asarray(vertices, np.float64)[np.unique(faces)]
        self.centre = 0.5 * (used.min(axis=0) + used.max(axis=0)) if len(used) else np.zeros(3)
        self.scene = _raycasting_scene(vertices - self.centre, faces)
        self.shell = shell  # > 0: the wall is the surface thickened to this (|d| - shell / 2)
        self.fluid_sign = 1.0 if fluid == "outside" else -1.0  # sign of d outside the mesh
        self.rays = 1 if watertight else sign_rays
        self.seconds = {"distance": 0.0, "sign": 0.0}

    def distance(self, pts: np.ndarray) -> np.ndarray:
        import open3d as o3d
        t0 = time.perf_counter()
        d = self.scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(pts - self.centre, np.float32))).numpy()
        self.seconds["distance"] += time.perf_counter() - t0
        return d

    def sign(self, pts: np.ndarray, rays: int | None = None) -> np.ndarray:
        """+-1 by ray parity, majority over ``rays`` fixed random directions (never axis-aligned, so rays
        of symmetric meshes do not run through vertices). open3d's own compute_occupancy(nsamples) was
        not used: it returned the same wrong vote for any nsamples next to holes."""
        import open3d as o3d
        t0 = time.perf_counter()
        k = rays or self.rays
        dirs = np.random.default_rng(12345).normal(size=(k, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        inside = np.zeros(len(pts), np.int32)
        pts32 = np.ascontiguousarray(pts - self.centre, np.float32)
        for d in dirs:  # one direction at a time keeps the ray buffer at (N, 6)
            rays6 = np.concatenate([pts32, np.broadcast_to(d.astype(np.float32), pts32.shape)], axis=1)
            inside += self.scene.count_intersections(o3d.core.Tensor(rays6)).numpy() % 2
        self.seconds["sign"] += time.perf_counter() - t0
        return np.where(2 * inside > k, -self.fluid_sign, self.fluid_sign).astype(np.float32)

    def signed(self, pts: np.ndarray) -> np.ndarray:
        if self.shell > 0:
            return self.distance(pts) - np.float32(0.5 * self.shell)
        return self.distance(pts) * self.sign(pts)


def wall_fields(wm: WallMesh, sign_rays: int, shells: np.ndarray | None = None) -> list[WallField]:
    shells = wm.shell_thickness() if shells is None else shells
    fields = []
    for i in range(len(wm.walls)):
        for tri, fluid, shell, watertight in wall_pieces(wm, i, float(shells[i])):
            faces = np.arange(3 * len(tri)).reshape(-1, 3)
            fields.append(WallField(tri.reshape(-1, 3), faces, fluid, watertight, sign_rays, shell))
    return fields


def exact_signed_distance(fields: list[WallField], pts: np.ndarray) -> np.ndarray:
    """Exact combined signed distance (min over walls) at ``pts``; reference for accuracy checks."""
    d = np.full(len(pts), np.inf, np.float32)
    for w in fields:
        d = np.minimum(d, w.signed(pts))
    return d


def _closed_parts(tri: np.ndarray):
    """The parts of ``tri`` (T, 3, 3) (vertices welded where equal; parts.mesh_parts: triangles joined across
    edges) and which are closed shells (every edge of the part met once each way): (part of each triangle,
    number of parts, the closed shells, each part's box lo / hi and size eps / 1000, each triangle's centroid
    moved a hair into its part); None for fewer than two parts or no closed shell."""
    if len(tri) < 8:
        return None
    # parts joined across edges, not vertices: kitbashed boxes sharing corners (or an edge) were one part,
    # and their overlap went unsaid (parts.mesh_parts)
    found = mesh_parts(*weld_equal(tri))
    part, n_parts = found.part, found.count
    if n_parts < 2:
        return None
    shells = np.flatnonzero(found.closed)
    if len(shells) == 0:
        return None
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vol = np.bincount(part, np.einsum("ij,ij->i", tri[:, 0], cross), minlength=n_parts)  # 6 x signed volume
    lo = np.full((n_parts, 3), np.inf)
    hi = np.full((n_parts, 3), -np.inf)
    np.minimum.at(lo, part, tri.min(axis=1))
    np.maximum.at(hi, part, tri.max(axis=1))
    eps = 1e-3 * np.linalg.norm(hi - lo, axis=1)
    unit = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)
    probe = tri.mean(axis=1) - (np.sign(vol) * eps)[part][:, None] * unit  # a hair into the part
    return part, n_parts, shells, lo, hi, eps, probe


def _inside_shell(tri: np.ndarray, part: np.ndarray, d: int, points: np.ndarray) -> np.ndarray:
    """|w| > 1/2 of closed shell ``d`` at ``points``."""
    own = tri[part == d].reshape(-1, 3)
    w = winding_number(own, np.arange(len(own), dtype=np.int64).reshape(-1, 3), points)
    return np.abs(w) > 0.5


def shell_depths(tri: np.ndarray) -> np.ndarray | None:
    """Nesting depth of each triangle of ``tri`` (T, 3, 3): how many closed shells hold its part
    (``_closed_parts``). Part c lies in closed shell d when every one of c's triangle centroids, moved a hair
    into c, has |w_d| > 1/2 (so an obstacle standing on a tank's floor counts, two interpenetrating parts do
    not); parts that hold each other (duplicates) do not count. None when nothing is nested (the common case)."""
    found = _closed_parts(tri)
    if found is None:
        return None
    part, n_parts, shells, lo, hi, eps, probe = found
    holds: set[tuple[int, int]] = set()  # (d, c): closed shell d holds part c
    for d in shells:
        cand = np.flatnonzero(np.all(lo >= lo[d] - eps[d], axis=1) & np.all(hi <= hi[d] + eps[d], axis=1))
        cand = cand[cand != d]
        if len(cand) == 0:
            continue
        sel = np.flatnonzero(np.isin(part, cand))
        inside = _inside_shell(tri, part, d, probe[sel])
        outside = np.zeros(n_parts, np.bool_)
        outside[part[sel][~inside]] = True
        holds.update((int(d), int(c)) for c in cand[~outside[cand]])
    depth = np.zeros(n_parts, np.int64)
    for d, c in holds:
        if (c, d) not in holds:
            depth[c] += 1
    return depth[part] if depth.any() else None


def interpenetrating_parts(tri: np.ndarray, probes_per_part: int = 64) -> int:
    """How many pairs of closed parts of ``tri`` cut into each other: some of one part's surface inside the
    other closed shell and some outside it (a part wholly inside another is a nested shell, not counted).
    Parity calls such an overlap outside the solid; the winding number does not. Sampled: at most
    ``probes_per_part`` surface points of each part, shells checked against parts their boxes overlap."""
    found = _closed_parts(tri)
    if found is None:
        return 0
    part, n_parts, shells, lo, hi, eps, probe = found
    rng = np.random.default_rng(0)
    order = np.argsort(part, kind="stable")
    starts = np.searchsorted(part[order], np.arange(n_parts + 1))
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    pairs = set()
    for d in shells:
        cand = np.flatnonzero(np.all(lo <= hi[d] + eps[d], axis=1) & np.all(hi >= lo[d] - eps[d], axis=1))
        cand = cand[cand != d]
        for c in cand:
            if (min(c, d), max(c, d)) in pairs:
                continue
            tris = order[starts[c]:starts[c + 1]]
            # points spread over the part's surface by area (a centroid per triangle missed two crossing
            # boxes: no box's triangle centre lies in the other), each moved a hair into the part
            w = area[tris] / max(area[tris].sum(), 1e-300)
            pick = rng.choice(tris, probes_per_part, p=w)
            ab = rng.random((probes_per_part, 2))
            ab = np.where(ab.sum(axis=1, keepdims=True) > 1.0, 1.0 - ab, ab)
            pts = tri[pick, 0] + ab[:, :1] * (tri[pick, 1] - tri[pick, 0]) + ab[:, 1:] * (tri[pick, 2] - tri[pick, 0])
            pts += probe[pick] - tri[pick].mean(axis=1)  # the centroid's hair-inward shift
            inside = _inside_shell(tri, part, d, pts)
            if inside.any() and not inside.all():
                pairs.add((min(c, d), max(c, d)))
    return len(pairs)


def winding_inside(tri: np.ndarray, origin: np.ndarray, h: float, shape: tuple[int, int, int],
                   near: np.ndarray, closed: bool = True, band: float = 0.0) -> np.ndarray:
    """Inside/outside of the triangles ``tri`` (T, 3, 3) at every node by the generalized winding number
    (Jacobson et al. 2013; Barill et al. 2018's fast approximation, libigl): |w| > 1/2 is inside, for
    either orientation, so interpenetrating parts make a union. A closed shell nested in another
    (an obstacle in a tank, each wound as it would be exported alone: w = 2 in it) is a cavity: the
    triangles are split by nesting depth (``shell_depths``) and the levels' insides alternate (XOR),
    as parity does, whichever way the inner shell is wound. Holes, flipped or duplicated faces move w
    by the solid angle they subtend: small defects matter only near them, but a large share of
    flipped faces (half of a sphere's) takes w towards 0 everywhere. Evaluated at the ``near`` (band)
    nodes and, for a ``closed`` mesh, at one node of each connected region of the others: such a region
    does not touch the wall, so w is the same all over it. An open mesh's w is not: a tank missing a side
    has its inside and outside in one region, joined through the opening, where w goes from 1 to 0 (the
    tank's middle took the outside's sign: solid). Its far nodes take w at the nearest node of a coarse
    lattice (every band / 2 / h nodes, 1/64 of the nodes by default: each far node's lattice node is within
    0.43 band of it, on its side of the wall and over half the band off it)."""
    from scipy import ndimage

    near_idx = np.flatnonzero(near.reshape(-1))
    if closed:
        labels, n = ndimage.label(~near)
        flat = labels.reshape(-1)
        _, first = np.unique(flat, return_index=True)
        far = first[flat[first] > 0]  # one node per far region (label 0: the band)
    else:
        step = max(1, int(0.5 * band / h))
        coarse = tuple(len(range(0, m, step)) for m in shape)
        far = np.ravel_multi_index(np.meshgrid(*(np.arange(0, m, step) for m in shape), indexing="ij"),
                                   shape).reshape(-1)
    idx = np.concatenate([near_idx, far])
    pts = origin + h * np.stack(np.unravel_index(idx, shape), axis=1).astype(np.float64)
    depth = shell_depths(tri)
    levels = [tri] if depth is None else [tri[depth == k] for k in np.unique(depth)]
    w = np.zeros(len(idx), np.bool_)
    for part in levels:
        faces = np.arange(3 * len(part), dtype=np.int64).reshape(-1, 3)
        w ^= np.abs(winding_number(part.reshape(-1, 3), faces, pts)) > 0.5
    if closed:
        region = np.zeros(n + 1, np.bool_)
        region[flat[far]] = w[len(near_idx):]
        inside = region[flat]
    else:  # each node the nearest lattice node's
        near_lattice = [np.minimum(np.rint(np.arange(m) / step).astype(np.int64), c - 1) for m, c in zip(shape, coarse)]
        inside = w[len(near_idx):].reshape(coarse)[np.ix_(*near_lattice)].reshape(-1)
    inside[near_idx] = w[:len(near_idx)]
    return inside.reshape(shape)


def face_thickness(tri: np.ndarray) -> np.ndarray:
    """Thickness of a closed solid behind each triangle: the first hit of a ray from its centroid along
    its back side (the solid, by mesh_import's convention that normals face the fluid); inf if none.
    open3d casts in float32, so about the model's box centre, each ray starting 1e-5 of the model's size
    behind its face (in world coordinates, with an offset of 1e-6 (max |x| + 1), a bunny 1e5 m out started
    its rays 10 spacings inside itself, and the offset changed with the units)."""
    import open3d as o3d
    tri = tri - 0.5 * (tri.reshape(-1, 3).min(axis=0) + tri.reshape(-1, 3).max(axis=0))
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    start = tri.mean(axis=1) - 1e-5 * np.abs(tri).max() * n
    scene = _raycasting_scene(tri.reshape(-1, 3), np.arange(3 * len(tri), dtype=np.int64).reshape(-1, 3))
    rays = np.concatenate([start, -n], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)


def bake_wall(tri: np.ndarray, fluid: str, origin: np.ndarray, h: float, shape: tuple[int, int, int], band: float,
              exact_reach: float, sign_rays: int, out: np.ndarray, seconds: dict, shell: float = 0.0,
              sign: str = "parity", min_thickness: float = 0.0, watertight: bool = False) -> dict:
    """Fold one wall's narrow-band signed distance (triangles ``tri`` (T, 3, 3)) into ``out`` (min).

    ``shell`` > 0: the wall is the surface thickened to ``shell`` (|d| - shell/2, no inside/outside).
    Else a solid, signed by ``sign`` ("parity": grid-line votes with open3d rays on ties; "winding":
    the generalized winding number); a watertight solid's parts thinner than ``min_thickness`` are
    thickened to it (the faces' thickness by ray, each dilated by half the missing thickness)."""
    t0 = time.perf_counter()
    if shell > 0:
        dist, counts = band_distance(tri, origin, h, shape, band, exact_reach * h)
        np.minimum(out, (dist - 0.5 * shell).astype(np.float32), out=out)
        seconds["distance"] += time.perf_counter() - t0
        return {**counts, "sign_ties": 0, "thin_faces": 0}
    dist, counts = band_distance(tri, origin, h, shape, band, exact_reach * h)
    t1 = time.perf_counter()
    tie = np.zeros(0, np.int64)
    if sign == "winding":
        inside = winding_inside(tri, origin, h, shape, dist < band, watertight, band)
    else:
        votes = inside_votes(tri, origin, h, shape)
        inside = votes >= 4
        tie = np.flatnonzero(votes.reshape(-1) == 3)
        if len(tie):  # every line through the node crosses a hole: ask open3d's random rays
            faces = np.arange(3 * len(tri), dtype=np.int64).reshape(-1, 3)
            field = WallField(tri.reshape(-1, 3), faces, "outside", False, sign_rays)
            pts = origin + h * np.stack(np.unravel_index(tie, shape), axis=1)
            inside.reshape(-1)[tie] = field.sign(pts) < 0
    fluid_sign = np.float32(1.0 if fluid == "outside" else -1.0)  # sign of d outside the mesh
    signed = dist.astype(np.float32)
    signed[inside] *= -1
    if fluid_sign < 0:
        np.negative(signed, out=signed)
    t2 = time.perf_counter()
    n_thin = 0
    if min_thickness > 0 and watertight:
        grow = 0.5 * (min_thickness - face_thickness(tri))
        thin = np.flatnonzero(grow > 0)
        n_thin = len(thin)
        if n_thin:  # the thin parts' distance minus each closest face's missing half thickness
            d_thin, _, ids = band_distance(tri[thin], origin, h, shape, band, exact_reach * h, return_ids=True)
            hit = ids >= 0
            np.minimum(signed, np.where(hit, d_thin - grow[thin][np.maximum(ids, 0)], band).astype(np.float32),
                       out=signed)
    np.minimum(out, signed, out=out)
    t3 = time.perf_counter()
    seconds["distance"] += (t1 - t0) + (t3 - t2)
    seconds["sign"] += t2 - t1
    return {**counts, "sign_ties": int(len(tie)), "thin_faces": n_thin}


def wall_thicknesses(wm: WallMesh, l0: float, p: "BakeParams", log=None) -> np.ndarray:
    """(walls,) the thickness each shell is baked with (scene units; 0 for a solid): the imported one,
    raised to the least thickness that does not leak at this cell (``min_thickness``)."""
    floor = p.min_thickness_l0() * l0
    out = wm.shell_thickness(DEFAULT_SHELL_THICKNESS * l0)
    for i in np.flatnonzero((out > 0) & (out < floor)):
        if log is not None:
            log.warning("wall %d (%s): shell %.4g thick is below the least leak-free thickness %.4g "
                        "(%.3g l0 at cell %.3g l0): baked %.4g thick", i, wm.walls[i]["name"], out[i], floor,
                        floor / l0, p.cell, floor)
        out[i] = floor
    return out


def grid_box(wm: WallMesh, domain, l0: float, p: BakeParams, up_axis: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The static grid's box: scene.domain padded by the margin; without a domain, the fluid's reach:
    the static walls' bounds and every moving wall's swept bounds, padded by min(band, GRID_BAND) + margin
    (a wider band would only grow the grid, whose edge consumers read as it is beyond it). Its low
    corner is moved down (less than a node) onto the first moving wall's nodes, or, with ``up_axis``
    and no moving wall, so that the widest wall along each axis is on the wall maps' nodes (_on_wall_nodes)."""
    if domain is not None:
        pad = p.margin * l0
        return _on_nodes(wm, np.asarray(domain.min, np.float64) - pad, l0, p, up_axis), np.asarray(domain.max, np.float64) + pad
    moving = wm.motions()
    still = ~np.isin(wm.wall_id, [i for i, _ in moving])
    boxes = []
    if not moving and len(wm.vertices):
        boxes.append((wm.vertices.min(axis=0), wm.vertices.max(axis=0)))
    elif still.any():
        used = wm.vertices[np.unique(wm.faces[still])]
        boxes.append((used.min(axis=0), used.max(axis=0)))
    for i, motion in moving:
        used = wm.vertices[np.unique(wm.faces[wm.wall_id == i])]
        boxes.append(motion.swept_bounds(used.min(axis=0), used.max(axis=0)))
    if not boxes:
        raise StageError("sdf_bake: no walls and no scene.domain: nothing to bound the grid")
    pad = (min(p.band, GRID_BAND) + p.margin) * l0
    return _on_nodes(wm, np.min([b[0] for b in boxes], axis=0) - pad, l0, p, up_axis), \
        np.max([b[1] for b in boxes], axis=0) + pad


def _on_nodes(wm: WallMesh | None, lo: np.ndarray, l0: float, p: BakeParams, up_axis: str | None) -> np.ndarray:
    """``lo`` moved down onto the first moving wall's nodes, or, where no wall moves, so that the widest wall
    along each axis, the floor along the up axis, is on the wall maps' nodes (with ``up_axis``)."""
    if wm is None or not len(wm.faces):
        return lo
    if wm.motions():
        return _on_body_nodes(wm, lo, l0, p)
    return lo if up_axis is None else _on_wall_nodes(wm, lo, l0, up_axis, wall_thicknesses(wm, l0, p))


def _on_wall_nodes(wm: WallMesh, lo: np.ndarray, l0: float, up_axis: str, shells: np.ndarray) -> np.ndarray:
    """``lo`` moved down (less than l0 / 2 per axis) so that, along each axis, the static walls' widest plane
    facing along it lies on the wall maps' nodes (every l0 / 2 from the grid's corner); along the up axis the
    widest upward-facing one, a floor where the water's weight rests (a downward-facing one if none faces up:
    a single-sided floor seen from below). The maps interpolate a wall's curved density profile trilinearly:
    a quarter of a node off, the first row over a flat wall reads 2.7 % too dense, on the nodes 0.03 %
    (benchmarks/bench_wall_offset.py), and a tank's edges 3.6-4.4 % against 1.0-1.3 % where both walls are on them
    (their trilinear SDF is biased towards the walls). A box tank whose sides are whole multiples of l0 / 2 apart
    then has every wall and edge on the nodes. A shell's (``shells``: each wall's baked thickness, 0 for a
    solid) surface is half its thickness off its faces: the upper one along the up axis, where water rests,
    else the one its faces' normal points to. An axis without such a plane keeps its corner."""
    tri = wm.vertices[wm.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(n, axis=1)
    node = 0.5 * l0
    out = np.array(lo, np.float64)
    up = "XYZ".index(up_axis)
    for k in range(3):
        facing = (area > 0) & (np.abs(n[:, k]) > 0.9999 * area)
        if k == up and (facing & (n[:, k] > 0)).any():
            facing &= n[:, k] > 0  # the floor before a lid
        if not facing.any():
            continue
        half = 0.5 * shells[wm.wall_id[facing]]
        at = tri[facing][:, :, k].mean(axis=1) + (half if k == up else half * np.sign(n[facing, k]))
        _, plane = np.unique(np.round(at / (1e-6 * l0)), return_inverse=True)
        sums = np.bincount(plane, area[facing])
        wall = at[plane == np.argmax(sums >= sums.max() * (1.0 - 1e-9))][0]  # the widest; the lowest of equals
        steps = (wall - lo[k]) / node
        if abs(steps - round(steps)) > 1e-6:  # not on the nodes already (as the builtin tanks are)
            out[k] = wall - np.ceil(steps) * node
    return out


def _on_body_nodes(wm: WallMesh, lo: np.ndarray, l0: float, p: BakeParams) -> np.ndarray:
    """``lo`` moved down onto the first moving wall's grid nodes (less than a cell): at its rest pose that
    wall's field is then resampled node for node onto the static grid, exactly. Off its nodes, trilinear
    resampling rounded a turning tank's concave corners at t = 0 below l0 / 2: 24 of 640 particles of a
    dam break were dropped from its bottom edges, and their columns started without hydrostatic compression."""
    boxes = body_boxes(wm, l0, p)
    if not boxes:
        return lo
    h = p.cell * l0
    body_lo = boxes[0][0]
    return body_lo + np.floor((lo - body_lo) / h + 1e-9) * h


def split_moving(wm: WallMesh) -> tuple[WallMesh, list[tuple[int, WallMesh]]]:
    """The static walls (the moving walls' faces dropped) and per moving wall (index, that wall alone);
    every part keeps the whole walls list, so per-wall arrays (shell thickness) keep their indices."""
    moving = [i for i, info in enumerate(wm.walls) if info.get("motion") is not None]
    static = ~np.isin(wm.wall_id, moving)
    return wm.subset(static), [(i, wm.subset(wm.wall_id == i)) for i in moving]


def bake_bodies(wm: WallMesh, out_dir: Path, l0: float, p: BakeParams, shells: np.ndarray, log=None) -> list[dict]:
    """Bake each moving wall alone in its rest pose (the bake of the static walls, on its own bounds
    padded by band + margin, at the same node spacing) into bodies/<k>.npz; write bodies.json."""
    _, bodies = split_moving(wm)
    if not bodies:
        return []
    (out_dir / BODIES_DIR).mkdir()
    entries = []
    for k, ((i, body), (lo, hi)) in enumerate(zip(bodies, body_boxes(wm, l0, p))):
        grid, stats = bake(body, lo, hi, p.cell * l0, p.band * l0,
                           p.exact_reach, p.sign_rays, shells, p.sign, p.min_thickness_l0() * l0)
        name = f"{BODIES_DIR}/{k}.npz"
        grid.save_file(out_dir / name)
        entries.append({"wall": i, "name": wm.walls[i]["name"], "motion": wm.walls[i]["motion"], "file": name})
        if log is not None:
            log.info("moving wall %d (%s): body sdf %s nodes, %.2f s", i, wm.walls[i]["name"],
                     "x".join(map(str, stats["shape"])), stats["seconds"])
            say_signs(log, stats)
    (out_dir / BODIES_FILE).write_text(json.dumps(entries, indent=2, sort_keys=True))
    return entries


def body_boxes(wm: WallMesh, l0: float, p: BakeParams) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each moving wall's own grid box: its rest bounds padded by band + margin."""
    pad = (p.band + p.margin) * l0
    boxes = []
    for i, _ in wm.motions():
        used = wm.vertices[np.unique(wm.faces[wm.wall_id == i])]
        boxes.append((used.min(axis=0) - pad, used.max(axis=0) + pad))
    return boxes


def grids_estimate(wm: WallMesh | None, domain, l0: float, p: BakeParams) -> tuple[list[tuple], dict]:
    """The shapes of every grid the bake allocates (the static one, then each moving wall's) and their
    nodes and memory together. ``wm`` None: scene.domain alone (no moving wall known yet)."""
    boxes = [grid_box(wm, domain, l0, p)] + (body_boxes(wm, l0, p) if wm is not None else [])
    sizes = [sdf_estimate(lo, hi, p.cell * l0) for lo, hi in boxes]
    return [shape for shape, _ in sizes], {k: sum(size[k] for _, size in sizes) for k in sizes[0][1]}


def grid_refusal(shapes: list[tuple], domain, l0: float, p: BakeParams) -> str | None:
    """The one-line refusal of grids (``shapes``, as grids_estimate gives them) of more than MAX_NODES nodes in
    all, naming what sizes them: the box (scene.domain, or the walls' bounds), its padding (band, margin) and the
    node spacing (cell, fluid.spacing); None for smaller grids."""
    nodes = sum(math.prod(int(n) for n in s) for s in shapes)  # exact: 800009^3 as a float ends ...704
    if nodes <= MAX_NODES:
        return None
    if domain is not None:
        box, smaller = f"scene.domain padded by stages.sdf_bake.margin {p.margin:g} l0", "a smaller scene.domain"
    else:
        band = f"{p.band:g}" if p.band <= GRID_BAND else f"{p.band:g} (of which {GRID_BAND:g} pads)"
        box = f"the walls' bounds (no scene.domain) padded by stages.sdf_bake.band {band} + margin {p.margin:g} l0"
        smaller = "a scene.domain around the fluid"
    grids = " + ".join("x".join(map(str, s)) for s in shapes)
    return (f"the SDF grid would have {nodes:,} nodes ({grids}; about {human(nodes * BYTES_PER_SDF_NODE)} while "
            f"baking), more than the {MAX_NODES:,} a bake allows: {box} at stages.sdf_bake.cell {p.cell:g} l0 "
            f"(fluid.spacing {l0:g}); raise cell (at most 1) or fluid.spacing, lower margin, or give {smaller}")


def builtin_boxes(corners: np.ndarray, walls: list) -> WallMesh:
    """The builtin walls as their placed boxes' corners (8 per wall, three triangles using all 8) with
    their config motions: enough for grid_box and body_boxes before mesh_import has run."""
    from stages.common.motion import config_motion

    n = len(corners) // 8
    faces = (np.arange(n)[:, None, None] * 8 + np.array([[0, 1, 2], [3, 4, 5], [6, 7, 0]])).reshape(-1, 3)
    info = []
    for k, w in enumerate(walls):
        motion = None if w.motion is None else config_motion(w.motion, corners[8 * k:8 * k + 8]).to_json()
        info.append({"motion": motion})
    return WallMesh(corners, faces.astype(np.int32), np.repeat(np.arange(n), 3).astype(np.int32), info)


def bake(wm: WallMesh, lo: np.ndarray, hi: np.ndarray, h: float, band: float, exact_reach: float = 4.0,
         sign_rays: int = 7, shells: np.ndarray | None = None, sign: str = "parity",
         min_thickness: float = 0.0) -> tuple[SDFGrid, dict]:
    """Bake the combined field of ``wm`` on the node grid from ``lo`` with spacing ``h`` covering ``hi``
    (``band`` in scene units, ``exact_reach`` in grid spacings). ``shells``: per wall the shell thickness
    to bake (scene units, 0 for a solid; default: as imported); ``min_thickness`` (scene units): thinner
    parts of watertight solids are thickened to it."""
    shells = wm.shell_thickness(np.nan) if shells is None else np.asarray(shells, np.float64)
    if np.isnan(shells).any():
        raise ValueError("bake: a shell's thickness was left to the default; pass shells (wall_thicknesses)")
    shape, _ = sdf_estimate(lo, hi, h)
    if np.prod(shape, dtype=np.int64) > MAX_NODES:
        raise StageError(f"sdf_bake: grid {shape} has more than {MAX_NODES:,} nodes; increase cell or shrink scene.domain")
    t0 = time.perf_counter()
    dist = np.full(shape, band, np.float32)
    seconds = {"distance": 0.0, "sign": 0.0}
    counts = {"exact_nodes": 0, "propagated_nodes": 0, "sign_ties": 0, "thin_faces": 0}
    cutting: dict[str, int] = {}  # wall -> pairs of its closed parts that cut into each other (sign: parity)
    winding: dict[str, int] = {}  # the same, signed by the winding number instead (sign: auto)
    for i, info in enumerate(wm.walls):
        name = info.get("name") or f"walls[{i}]"
        for piece, fluid, shell, watertight in wall_pieces(wm, i, float(shells[i])):
            how = "parity" if sign == "auto" else sign
            if sign != "winding" and not shell > 0:  # parity calls the overlap of two closed parts outside
                n = interpenetrating_parts(piece)
                if n and sign == "auto":
                    how, winding[name] = "winding", n
                elif n:
                    cutting[name] = n
            c = bake_wall(piece, fluid, np.asarray(lo, np.float64), h, shape, band, exact_reach, sign_rays, dist,
                          seconds, shell=shell, sign=how, min_thickness=min_thickness, watertight=watertight)
            counts = {k: counts[k] + c[k] for k in counts}
    stats = {"shape": list(shape), "nodes": int(np.prod(shape)), "seconds": time.perf_counter() - t0,
             "distance_seconds": seconds["distance"], "sign_seconds": seconds["sign"], **counts,
             "interpenetrating": cutting, "winding": winding}
    return SDFGrid(origin=np.asarray(lo, np.float64), spacing=float(h), dist=dist, band=float(band),
                   shell_thickness=shells), stats


def wall_pieces(wm: WallMesh, i: int, shell: float) -> list[tuple[np.ndarray, str, float, bool]]:
    """Wall ``i``'s triangles as baked, (triangles, fluid side, shell thickness, watertight) each: the whole wall,
    or, for a shell with solid faces (its closed parts, WallMesh.solid), its open faces as the shell and the
    solid ones as a solid with the fluid outside, folded in by the minimum (the union of the two)."""
    info, faces = wm.walls[i], np.flatnonzero(wm.wall_id == i)
    solid = wm.solid[faces] if wm.solid is not None and shell > 0 else np.zeros(len(faces), np.bool_)
    if not solid.any():
        tri = wm.vertices[wm.faces[faces]]
        return [(tri, info["fluid"], shell, bool(info.get("report", {}).get("watertight", False)))] if len(tri) else []
    closed = boundary_edge_count(wm.faces[faces[solid]]) == 0  # else closed but for small holes
    return [p for p in ((wm.vertices[wm.faces[faces[~solid]]], "both", shell, False),
                        (wm.vertices[wm.faces[faces[solid]]], "outside", 0.0, closed)) if len(p[0])]


def say_signs(log, stats: dict) -> None:
    """The walls whose closed parts cut into each other: signed by the winding number (sign: auto), or, with
    sign: parity, a warning that their overlap is open space."""
    for wall, n in stats["winding"].items():
        log.info("sdf_bake: %s: %d pair(s) of its closed parts cut into each other: signed by the winding number "
                 "(parity would call their overlap open space, and fluid fill it)", wall, n)
    for wall, n in stats["interpenetrating"].items():
        log.warning("sdf_bake: %s: %d pair(s) of its closed parts cut into each other; the parity sign calls "
                    "their overlap open space (fluid may fill it): set sdf_bake: {sign: winding} (or auto) for "
                    "such a model", wall, n)


def accuracy(grid: SDFGrid, fields: list[WallField], wm: WallMesh, n_points: int = 20000, seed: int = 0) -> dict:
    """Sampled (trilinear) vs exact signed distance at random points within the band, in grid spacings.

    Points: random surface points pushed along a random direction by up to 0.9 band, kept if inside
    the grid and within the band of the exact field. Sign errors are counted beyond half a spacing."""
    import trimesh

    rng = np.random.default_rng(seed)
    surf, _ = trimesh.sample.sample_surface(trimesh.Trimesh(wm.vertices, wm.faces, process=False), n_points, seed=seed)
    dirs = rng.normal(size=(n_points, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = surf + dirs * rng.uniform(0, 0.9 * grid.band, (n_points, 1))
    inside = ((pts >= grid.origin) & (pts <= grid.upper)).all(axis=1)
    pts = pts[inside]
    exact = exact_signed_distance(fields, pts).astype(np.float64)
    keep = np.abs(exact) < 0.9 * grid.band
    sampled, _ = grid.sample(pts[keep])
    err = np.abs(sampled - exact[keep]) / grid.spacing
    return {"points": int(keep.sum()), "max_error_cells": float(err.max()), "rms_error_cells": float(np.sqrt(np.mean(err ** 2))),
            "p99_error_cells": float(np.quantile(err, 0.99)), "sign_errors": int(np.sum((np.sign(sampled) != np.sign(exact[keep])) & (np.abs(exact[keep]) > 0.5 * grid.spacing)))}


class Open3dBake(Stage):
    """Narrow-band signed distance field of the walls (numba exact/propagated distance, grid-line ray votes)."""

    kind = "sdf_bake"
    name = "open3d"
    version = "8"
    Params = BakeParams
    inputs = ("walls",)
    outputs = ("sdf",)
    reads = ("fluid.spacing", "scene.domain", "scene.units.up_axis")
    estimate_reads = ("walls", "scene.units")  # builtin walls' bounds (not keyed: the walls input's key holds them)
    default = True
    description = "narrow-band SDF on a grid (exact distance near the walls, sign by grid-line ray votes)"

    def _config_grids(self, ctx: Context, params: Params) -> tuple[list[tuple], dict] | None:
        # run's grid_box over scene.domain, or else over the builtin walls' placed boxes
        scene, fluid = ctx.scene["scene"], ctx.scene["fluid"]
        if fluid is None:
            return None
        config_walls = ctx.scene["walls"] or []
        corners = builtin_corners(config_walls, scene.units.up_axis)
        if corners is None or not len(corners):
            if scene.domain is None:
                return None  # walls from files: run checks the grid once they are loaded, before allocating
            walls = None  # the moving walls' own grids are checked by run too
        else:
            walls = builtin_boxes(corners, config_walls)
        return grids_estimate(walls, scene.domain, fluid.spacing, params)

    def check(self, ctx: Context, params: Params) -> None:
        # before the plan's memory check: a grid past MAX_NODES is refused whatever the memory or --yes
        grids = self._config_grids(ctx, params)
        if grids is not None:
            refused = grid_refusal(grids[0], ctx.scene["scene"].domain, ctx.scene["fluid"].spacing, params)
            if refused:
                raise StageError(f"{self.qualname()}: {refused}")

    def estimate(self, ctx: Context, params: Params) -> dict | None:
        grids = self._config_grids(ctx, params)
        return None if grids is None else grids[1]

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: Params) -> None:
        fluid = ctx.scene["fluid"]
        if fluid is None:
            raise StageError("sdf_bake: the scene has no 'fluid' section; its spacing sets the grid spacing")
        l0 = fluid.spacing
        wm = WallMesh.load(inputs["walls"].path)
        lo, hi = grid_box(wm, ctx.scene["scene"].domain, l0, params, ctx.scene["scene"].units.up_axis)
        shapes, size = grids_estimate(wm, ctx.scene["scene"].domain, l0, params)
        try:  # both before any grid (a moving wall's either) is allocated
            refused = grid_refusal(shapes, ctx.scene["scene"].domain, l0, params)
            if refused:
                raise StageError(refused)
            ctx.check_memory(size["memory_bytes"], f"{int(size['sdf_nodes']):,} SDF nodes, grid "
                             + " + ".join("x".join(map(str, shape)) for shape in shapes))
        except StageError as e:  # a model in millimetres in a metre scene: say so beside "make the scene smaller"
            hint = spacing_hint(wm.vertices.min(axis=0), wm.vertices.max(axis=0), l0) if len(wm.vertices) else ""
            # a stray triangle far off is the likelier cause than the units (2 km away, the advice was meters_per_unit)
            stray = next(((i, w) for i, w in enumerate(wm.walls) if (w.get("report") or {}).get("stray_part")), None)
            if stray is not None:
                i, w = stray
                hint = (f"; wall {i} ({w.get('source')}) has {stray_text(w['report']['stray_part'])}: delete it from "
                        "the file, or give a scene.domain around the fluid")
            raise StageError(f"{e}{hint}") from None
        shells = wall_thicknesses(wm, l0, params, ctx.log)
        # a moving wall is baked apart, in its own frame (bodies/); sdf.npz holds the static walls only
        # (+band everywhere when every wall moves)
        static, _ = split_moving(wm)
        bake_bodies(wm, ctx.out_dir, l0, params, shells, ctx.log)
        grid, stats = bake(static, lo, hi, params.cell * l0, params.band * l0, params.exact_reach, params.sign_rays,
                           shells, params.sign, params.min_thickness_l0() * l0)
        grid.save(ctx.out_dir)
        write_wall_boxes(ctx.out_dir, wm.walls, wm.vertices, wm.wall_id, wm.faces)  # simulate's advice
        ctx.log.info("sdf %s nodes, %d exact + %d propagated band nodes, %d tied signs, %d faces of thin parts "
                     "thickened, %.2f s", "x".join(map(str, stats["shape"])), stats["exact_nodes"],
                     stats["propagated_nodes"], stats["sign_ties"], stats["thin_faces"], stats["seconds"])
        say_signs(ctx.log, stats)
