"""mesh_import.usd: wall meshes from OpenUSD (.usda/.usdc/.usdz) read with usd-core.

Selects ``UsdGeom.Mesh`` prims and the implicit shapes (Cube, Sphere, Cylinder, Cone, Capsule, Plane:
tessellated here) by path or glob pattern (``fnmatch``: ``*`` also crosses ``/``, so ``/World/*`` is
every descendant of /World), skips prims whose computed visibility is invisible unless the wall sets
``include_invisible``, and never uses other prims (Xform, Scope, curves, points). Each mesh goes to world space through ``UsdGeom.XformCache``
(nested xformOps, resetXformStack), n-gons are triangulated from faceVertexCounts (ear clipping where a fan would cross a concave face), faces listed in
``holeIndices`` are dropped, left-handed meshes are re-wound, and the points are converted to the
scene's units and up axis from the stage's metersPerUnit (USD's fallback: centimetres) and upAxis.

The implementation reads every wall kind (built-ins and mesh files too, like ``trimesh``), so a
scene mixing kinds works with either; it exists so a config can name the USD reader explicitly.
"""
from __future__ import annotations

import fnmatch
import math
from pathlib import Path

import numpy as np

from pipeline.scene import UsdWall
from pipeline.stage import StageError

from stages.common.placement import up_axis_matrix
from .trimesh_import import TrimeshImport

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def usd_dependencies(path: Path) -> list[Path]:
    """Every layer and asset the stage at ``path`` composes (sublayers, references, payloads, textures)."""
    from pxr import UsdUtils

    if not path.is_file():
        return [path]
    quiet = UsdUtils.CoalescingDiagnosticDelegate()  # a missing reference: read_usd_wall says it in one line
    try:
        layers, assets, _unresolved = UsdUtils.ComputeAllDependencies(str(path))
    except Exception as e:  # a damaged layer: say so now rather than when hashing
        from stages.common.usd_stage import usd_error

        raise StageError(f"{path}: cannot open as USD ({usd_error(e)})") from None
    finally:
        del quiet
    files = {Path(layer.realPath) for layer in layers if layer.realPath}
    files |= {Path(a) for a in assets}
    files.add(path)
    return sorted(f for f in files if f.is_file())


def _triangulate(counts: np.ndarray, indices: np.ndarray, holes: np.ndarray, where: str,
                 points: np.ndarray) -> np.ndarray:
    """Triangulate polygons (a fan where it is right, else ear clipping: see polygons.py); faces in
    ``holes`` are skipped. Returns (F, 3) int64."""
    from .polygons import triangulate  # imported where used: it loads numba

    if (counts < 3).any():
        raise StageError(f"{where}: faceVertexCounts has a face with fewer than 3 vertices")
    if counts.sum() != len(indices):
        raise StageError(f"{where}: faceVertexCounts sums to {counts.sum()} but there are {len(indices)} faceVertexIndices")
    keep = np.ones(len(counts), bool)
    if len(holes):
        keep[holes[(holes >= 0) & (holes < len(counts))]] = False
    tris, face_of_tri = triangulate(points, counts, indices)
    return tris[keep[face_of_tri]]


# UsdGeom's implicit shapes a layout places without a mesh (a Cube floor, Sphere rocks): tessellated here
# finely enough that the distance field is the shape's own (sagitta <= 2e-4 of the radius)
GPRIMS = ("Cube", "Sphere", "Cylinder", "Cylinder_1", "Cone", "Capsule", "Capsule_1", "Plane")
_SECTIONS = 160
_SHAPE_ATTRS = ("size", "radius", "radiusTop", "radiusBottom", "height", "width", "length", "axis")


def _is_shape(prim) -> bool:
    from pxr import UsdGeom

    return prim.IsA(UsdGeom.Mesh) or prim.GetTypeName() in GPRIMS


def _shape_triangles(prim, t, where: str, log, subdivide: int = 0,
                     record: dict | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """A Mesh or gprim as (points, outward triangles) in its own frame at time ``t``; None for a mesh
    without points or faces. An animated shape is read at ``t`` (walls move rigidly only). A subdivision
    cage (catmullClark, USD's fallback, or loop) is refined ``subdivide`` levels, or taken as it is;
    ``record`` maps the prim to what was done with an authored cage."""
    from pxr import UsdGeom

    if prim.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get(t) or [], np.float64).reshape(-1, 3)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(t) or [], np.int64)
        idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(t) or [], np.int64)
        holes = np.asarray(mesh.GetHoleIndicesAttr().Get(t) or [], np.int64)
        if len(pts) == 0 or len(counts) == 0:
            return None
        animated = "points" if mesh.GetPointsAttr().GetNumTimeSamples() > 1 else ""
        if not np.isfinite(pts).all():
            raise StageError(f"{where}: points contain NaN or Inf")
        if len(idx) and (idx.min() < 0 or idx.max() >= len(pts)):
            raise StageError(f"{where}: face vertex index {int(idx.max())} out of range (mesh has {len(pts)} points)")
        scheme = str(mesh.GetSubdivisionSchemeAttr().Get())
        authored = mesh.GetSubdivisionSchemeAttr().HasAuthoredValue()
        if subdivide and scheme in ("catmullClark", "loop"):
            pts, tris = _subdivided(pts, counts, idx, holes, scheme, subdivide, where, prim, log)
        else:
            tris = _triangulate(counts, idx, holes, where, pts)
        if record is not None and scheme in ("catmullClark", "loop"):
            # unauthored is USD's fallback, catmullClark: a renderer that subdivides (Karma, RenderMan) draws
            # the limit surface, up to a third of a spacing off the cage the water met; said as for an authored one
            record[str(prim.GetPath())] = f"{scheme} cage " + (f"refined {subdivide} levels" if subdivide else "as-is") \
                + ("" if authored else " (no subdivisionScheme authored: USD's fallback)")
    else:
        attrs = {n: prim.GetAttribute(n) for n in _SHAPE_ATTRS if prim.GetAttribute(n)}
        animated = ", ".join(n for n, a in attrs.items() if a.GetNumTimeSamples() > 1)
        pts, tris = _gprim_triangles(prim.GetTypeName(), {n: a.Get(t) for n, a in attrs.items()}, where)
    if animated and log is not None:
        log.warning("%s: animated %s (a deforming shape); the wall is its shape at the first sample "
                    "(walls move rigidly only)", where, animated)
    if UsdGeom.Gprim(prim).GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tris = tris[:, ::-1]
    return pts, tris


def _subdivided(pts, counts, idx, holes, scheme: str, levels: int, where: str, prim,
                log) -> tuple[np.ndarray, np.ndarray]:
    """The cage refined ``levels`` times by its scheme, as triangles. Hole faces refine with the rest (their
    neighbours' limit surface is the closed cage's, as OpenSubdiv draws it) and their children are left out."""
    import trimesh

    from .subdivision import catmull_clark

    if (counts < 3).any() or counts.sum() != len(idx):
        _triangulate(counts, idx, holes, where, pts)  # its one-line refusal
    keep = np.ones(len(counts), bool)
    keep[holes[(holes >= 0) & (holes < len(counts))]] = False
    sharp = [n for n in ("creaseIndices", "cornerIndices") if prim.GetAttribute(n).HasAuthoredValue()]
    if sharp and log is not None:
        log.warning("%s: its %s are not applied by the refinement (smooth there)", where, " and ".join(sharp))
    if scheme == "loop":  # (trimesh's loop refinement keeps no parent faces: holes are left out first)
        tris = _triangulate(counts, idx, holes, where, pts)
        v, f = trimesh.remesh.subdivide_loop(pts, tris, iterations=levels)
        return np.asarray(v, np.float64), np.asarray(f, np.int64)
    v, c, i = catmull_clark(pts, counts, idx, levels)
    # the quads come in their cage face's order: n per n-gon at the first level, then 4 per quad
    parent = np.repeat(np.arange(len(counts)), counts)[np.arange(len(c)) // 4 ** (levels - 1)]
    return v, _triangulate(c, i, np.flatnonzero(~keep[parent]), where, v)


def _gprim_triangles(kind: str, a: dict, where: str) -> tuple[np.ndarray, np.ndarray]:
    """The UsdGeom schema's shape (its attributes ``a``; the schema's fallbacks where unauthored): centred
    on the origin, round shapes about ``axis``; a Plane is an open sheet (a shell), the rest closed."""
    import trimesh

    def size(name: str, fallback: float, zero: bool = False) -> float:
        v = a.get(name)
        v = fallback if v is None else float(v)
        if not (math.isfinite(v) and (v > 0 or (zero and v == 0))):
            raise StageError(f"{where}: {kind} {name} {v} must be a positive number")
        return v

    axis = str(a.get("axis") or "Z")
    if kind == "Cube":
        m = trimesh.creation.box(extents=[size("size", 2.0)] * 3)
        return m.vertices, m.faces
    if kind == "Sphere":
        m = trimesh.creation.icosphere(subdivisions=5, radius=size("radius", 1.0))
        return m.vertices, m.faces
    if kind == "Plane":
        w, l = size("width", 2.0) / 2, size("length", 2.0) / 2
        # width and length along (z, y) for axis X, (x, z) for Y, (x, y) for Z; the normal along +axis
        corners = {"X": [[0, -l, w], [0, -l, -w], [0, l, -w], [0, l, w]],
                   "Y": [[-w, 0, -l], [-w, 0, l], [w, 0, l], [w, 0, -l]],
                   "Z": [[-w, -l, 0], [w, -l, 0], [w, l, 0], [-w, l, 0]]}[axis]
        return np.array(corners, np.float64), np.array([[0, 1, 2], [0, 2, 3]])
    h = size("height", 1.0 if kind.startswith("Capsule") else 2.0) / 2
    r_fallback = 0.5 if kind.startswith("Capsule") else 1.0
    if kind.endswith("_1"):
        bottom, top = size("radiusBottom", r_fallback, zero=True), size("radiusTop", r_fallback, zero=True)
        if bottom == top == 0:
            raise StageError(f"{where}: {kind} radiusBottom and radiusTop are both 0")
    else:
        bottom = size("radius", r_fallback)
        top = 0.0 if kind == "Cone" else bottom
    # a profile (radius, height) from the axis back to it, turned about z
    if kind.startswith("Capsule"):  # the hull of spheres of the two radii on the ends of the spine
        if abs(bottom - top) >= 2 * h:  # one sphere holds the other: the hull is the larger sphere
            c, r = (-h, bottom) if bottom > top else (h, top)
            q = np.linspace(-np.pi / 2, np.pi / 2, _SECTIONS // 2 + 1)
            profile = np.c_[r * np.cos(q), c + r * np.sin(q)]
        else:  # the cone tangent to both meets them at latitude a, sin a = (bottom - top) / spine length
            a = math.asin((bottom - top) / (2 * h))
            lo = np.linspace(-np.pi / 2, a, _SECTIONS // 4 + 1)
            hi = np.linspace(a, np.pi / 2, _SECTIONS // 4 + 1)
            profile = np.concatenate([np.c_[bottom * np.cos(lo), -h + bottom * np.sin(lo)],
                                      np.c_[top * np.cos(hi), h + top * np.sin(hi)]])
        profile[[0, -1], 0] = 0.0  # the poles exactly on the axis
    else:
        profile = np.array([[0.0, -h], [bottom, -h], [top, h], [0.0, h]])
    v, f = _revolve(profile, _SECTIONS)
    # turn z onto the axis (a cyclic permutation: a rotation, the winding stays outward)
    v = {"X": v[:, [2, 0, 1]], "Y": v[:, [1, 2, 0]], "Z": v}[axis]
    return np.ascontiguousarray(v), f


def _revolve(profile: np.ndarray, sections: int) -> tuple[np.ndarray, np.ndarray]:
    """The closed surface of a profile (radius, height) from a pole on the z axis to a pole, turned about
    z: a ring of ``sections`` vertices per inner point, fans at the poles, outward faces (trimesh's
    revolve dropped a pole whose neighbour was close to the axis and left the mesh open)."""
    inner = profile[1:-1][profile[1:-1, 0] > 0]  # a cone's tip is its pole
    t = np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    rings = np.stack([np.outer(inner[:, 0], np.cos(t)), np.outer(inner[:, 0], np.sin(t)),
                      np.repeat(inner[:, 1:2], sections, axis=1)], axis=-1).reshape(-1, 3)
    v = np.concatenate([[[0.0, 0.0, profile[0, 1]]], rings, [[0.0, 0.0, profile[-1, 1]]]])
    n, top = len(inner), len(v) - 1
    j = np.arange(sections)
    ring = lambda k: 1 + k * sections + j  # noqa: E731 - vertex indices of ring k
    nxt = lambda k: 1 + k * sections + (j + 1) % sections  # noqa: E731
    faces = [np.stack([np.zeros(sections, np.int64), nxt(0), ring(0)], axis=1),
             np.stack([np.full(sections, top), ring(n - 1), nxt(n - 1)], axis=1)]
    for k in range(n - 1):
        faces += [np.stack([ring(k), nxt(k), nxt(k + 1)], axis=1), np.stack([ring(k), nxt(k + 1), ring(k + 1)], axis=1)]
    f = np.concatenate(faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() < 0:  # wound inwards: turn every face
        f = f[:, ::-1]
    return v, np.ascontiguousarray(f)


def _xform_ops(prim, stop=None) -> list:
    """The xformOps of ``prim`` and its ancestors (below ``stop``): what moves it in the stage's world."""
    from pxr import UsdGeom

    ops, p = [], prim
    while p and p.IsValid() and not p.IsPseudoRoot() and p != stop:
        if p.IsA(UsdGeom.Xformable):
            ops += UsdGeom.Xformable(p).GetOrderedXformOps()
        p = p.GetParent()
    return ops


def _sample_codes(prim, stop=None) -> list[float]:
    """The time codes at which the xformOps of ``prim`` or any ancestor (below ``stop``) are sampled (sorted;
    empty when its world transform is static)."""
    return sorted({c for op in _xform_ops(prim, stop) for c in op.GetAttr().GetTimeSamples()})


TURN_STEP = 45.0  # degrees: the most a sampled motion turns between two samples (its slerp takes the short arc)


def _sample_times(prim, codes: list[float]) -> tuple[list[float], bool]:
    """The codes to sample an animated prim at, and whether it is moved by a time-sampled matrix op.

    - Every whole code between the samples, and more where a rotate op turns further than TURN_STEP between
      two of them: USD interpolates a rotate op's angle linearly, so a mixer keyed +270 degrees a code turned
      the short way (-90) at a third of its speed when sampled at whole codes.
    - A matrix op (xformOp:transform) is interpolated element by element, which shrinks a turn between its keys
      (0.94 of the size between two keys 90 degrees apart): such a prim is sampled at its keys only and moves
      rigidly between them (the authored keys are what the user posed)."""
    from pxr import UsdGeom

    ops = [op for op in _xform_ops(prim) if op.GetAttr().GetNumTimeSamples() > 1]
    matrix = any(op.GetOpType() == UsdGeom.XformOp.TypeTransform for op in ops)
    lo, hi = codes[0], codes[-1]
    every = sorted(set(codes) if matrix else set(codes) | {float(c) for c in range(int(np.ceil(lo)), int(np.floor(hi)) + 1)})
    turns = [op.GetAttr() for op in ops if "rotate" in str(op.GetOpType()).lower()]
    out = [every[0]]
    for a, b in zip(every[:-1], every[1:]):
        swing = max((np.abs(np.subtract(np.atleast_1d(t.Get(b)), np.atleast_1d(t.Get(a)))).max() for t in turns),
                    default=0.0)
        n = min(int(np.ceil(swing / TURN_STEP)), 1024)
        out += [a + (b - a) * k / n for k in range(1, n)] + [b]
    return out, matrix


def _animation(stage, prim, codes: list[float], log=None, where: str = "") -> tuple[np.ndarray, np.ndarray]:
    """(times (K,) s, (K, 4, 4) column-vector matrices M(t) M(t0)^-1 in the stage's world frame) of an
    animated prim, at the codes ``_sample_times`` picks (so a turn keyed at two codes is followed as USD
    interpolates it, not cut to the short arc between its ends)."""
    from pxr import Usd, UsdGeom

    every, matrix = _sample_times(prim, codes)
    if matrix and log is not None:
        log.warning("%s: moved by a time-sampled xformOp:transform: simulated rigidly between its keys, which USD "
                    "interpolates element by element (a turn shrinks between keys in a viewer); key it at every "
                    "frame, or animate translate and rotate ops, for the two to agree", where)
    cache = UsdGeom.XformCache()
    mats = []
    for c in every:
        cache.SetTime(Usd.TimeCode(c))
        mats.append(np.asarray(cache.GetLocalToWorldTransform(prim), np.float64).T)  # pxr: row vectors
    rest_inv = np.linalg.inv(mats[0])
    from stages.common.usd_stage import shot_start

    times = (np.asarray(every) - shot_start(stage)) / float(stage.GetTimeCodesPerSecond())  # the file's shot start is t = 0
    return times, np.array([m @ rest_inv for m in mats])


def _instances(stage, instancer, path: Path, hidden_too: bool) -> list[tuple]:
    """(prototype mesh, name, (4, 4) row-vector matrix mesh -> instancer space) of every instance of a
    PointInstancer (each mesh of its prototype), at its earliest time; instances masked by inactiveIds or
    invisibleIds are left out, and meshes hidden within their prototype unless ``hidden_too``. An animated
    instancer (its per-instance arrays, or a prototype's xformOps, time-sampled) is refused rather than
    frozen; the instancer's own transform may move (a rigid wall)."""
    from pxr import Usd, UsdGeom

    pi = UsdGeom.PointInstancer(instancer)
    where = f"{path}:{instancer.GetPath()}"
    animated = [n for n in pi.GetSchemaAttributeNames(False) if instancer.GetAttribute(n).GetNumTimeSamples() > 1]
    if animated:
        raise StageError(f"{where}: a PointInstancer with animated {', '.join(animated)} cannot be a wall "
                         "(walls move rigidly; bake it to meshes)")
    t = Usd.TimeCode.EarliestTime()
    xforms = pi.ComputeInstanceTransformsAtTime(t, t, UsdGeom.PointInstancer.IncludeProtoXform,
                                                UsdGeom.PointInstancer.IgnoreMask)
    protos = [stage.GetPrimAtPath(q) for q in pi.GetPrototypesRel().GetForwardedTargets()]
    index = list(pi.GetProtoIndicesAttr().Get(t) or [])
    if len(xforms) != len(index) or any(i < 0 or i >= len(protos) or not protos[i] for i in index):
        raise StageError(f"{where}: PointInstancer's protoIndices, positions or prototypes do not match")
    mask = list(pi.ComputeMaskAtTime(t))
    cache = UsdGeom.XformCache(t)
    parts: dict[int, list] = {}  # prototype -> [(mesh, name suffix, mesh -> prototype root's own frame)]
    for i in set(index):
        root = protos[i]
        # the instance transform includes the prototype root's own xformOps: place meshes relative to the root
        to_root = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(root), np.float64))
        parts[i] = []
        prims = list(Usd.PrimRange(root, Usd.TraverseInstanceProxies()))
        nested = next((p for p in prims if p.IsA(UsdGeom.PointInstancer)), None)
        if nested is not None:  # its instances would need placing twice; its prototype came in at its own place
            raise StageError(f"{where}: prototype {root.GetPath()} holds another PointInstancer ({nested.GetPath()}); "
                             "nested instancers are not read as walls (flatten the inner one to meshes)")
        purposes = {p: UsdGeom.Imageable(p).ComputePurpose() for p in prims if _is_shape(p)}
        has_render = UsdGeom.Tokens.render in purposes.values()
        for mesh in prims:
            if not _is_shape(mesh) or (not hidden_too and _hidden_below(mesh, root)):
                continue
            # as outside instancers: guides (rigs, helpers) are no walls, nor proxies beside render shapes
            if purposes[mesh] == UsdGeom.Tokens.guide or (has_render and purposes[mesh] == UsdGeom.Tokens.proxy):
                continue
            if _sample_codes(mesh, stop=root.GetParent()):
                raise StageError(f"{where}: prototype {mesh.GetPath()} is animated; an instancer wall must be static "
                                 "(bake it to meshes)")
            suffix = "" if mesh == root else "/" + str(mesh.GetPath().MakeRelativePath(root.GetPath()))
            parts[i].append((mesh, suffix, np.asarray(cache.GetLocalToWorldTransform(mesh), np.float64) @ to_root))
    return [(mesh, f"{instancer.GetPath()}[{k}]{suffix}", m @ np.asarray(xf, np.float64))
            for k, (xf, i) in enumerate(zip(xforms, index)) if not mask or mask[k] for mesh, suffix, m in parts[i]]


def _hidden_below(prim, root) -> bool:
    """A prototype's mesh made invisible within the prototype (the prototype's ancestors do not count: a
    scope hiding prototypes does not hide the instances), at the earliest time as every wall."""
    from pxr import Usd, UsdGeom

    p = prim
    while True:
        if UsdGeom.Imageable(p).GetVisibilityAttr().Get(Usd.TimeCode.EarliestTime()) == UsdGeom.Tokens.invisible:
            return True
        if p == root:
            return False
        p = p.GetParent()


def _animated_visibility(prim) -> list:
    """The prim and ancestors whose visibility changes between its time samples."""
    out = []
    p = prim
    while p and p.IsValid() and not p.IsPseudoRoot():
        attr = p.GetAttribute("visibility")
        if attr and attr.GetNumTimeSamples() > 1 and len({attr.Get(c) for c in attr.GetTimeSamples()}) > 1:
            out.append(p)
        p = p.GetParent()
    return out


def read_usd_wall(path: Path, wall: UsdWall, scene_mpu: float, scene_up: str,
                  log=None) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray, tuple | None, dict]:
    """World-space vertices (scene units, scene up axis), triangles, the prim paths used, the 4x4
    matrix (column vectors) from the stage's world frame to the scene's units and up axis, the
    wall's animation (None when static, else (times s, (K, 4, 4) matrices taking the rest pose to the
    pose at each time, in the stage's world frame)) and what became of each authored subdivision cage
    (prim -> "catmullClark cage as-is" or "... refined N levels"; the wall's ``subdivide``). An animated wall's vertices are in its rest pose:
    the world transform at its earliest time sample. Every prim of one wall must move alike (one rigid
    body). Points authored only as time samples (a cached or deforming mesh) are read at their earliest sample
    (read at the default time, such a prim was left out without a word); guide meshes (purpose guide: rigs,
    helpers a renderer never draws) are left out, and so are proxies where render meshes are chosen too (the
    same object twice). ``log`` hears what was left out and why."""
    from pxr import Usd, UsdGeom

    from stages.common.usd_stage import open_stage, stage_units, unresolved_assets

    if not path.is_file():
        raise StageError(f"{path}: USD file not found")
    diagnostics: list[str] = []
    stage = open_stage(path, diagnostics=diagnostics)
    # a reference or payload whose file is missing: USD composes on without its prims (a wall gone, exit 0)
    missing = [what for prim, what in unresolved_assets(stage) if not prim or _selects(wall.prims, prim)]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise StageError(f"{path}: {missing[0]}{more}")
    if diagnostics and log is not None:  # kept off stderr while composing; said here, in the log
        for text in diagnostics[:3]:
            log.warning("%s: USD: %s", path, text[:300])
    unstated = [key for key in ("metersPerUnit", "upAxis") if not stage.HasAuthoredMetadata(key)]
    if unstated and log is not None:
        # USD's fallbacks are centimetres and Y up: a file written in metres without them comes in 100 x small
        log.warning("%s states no %s: USD's fallback (%s) is used", path, " and no ".join(unstated),
                    ", ".join({"metersPerUnit": "centimetres", "upAxis": "Y up"}[k] for k in unstated))
    mpu, up = stage_units(stage, str(path))
    if log is not None:  # USD composes with the root layer's metadata only: a layer in other units is not rescaled
        stated = {"metersPerUnit": mpu, "upAxis": up}
        other = {}  # layer name -> what it states otherwise
        for layer in stage.GetUsedLayers():
            says = [f"{key} {layer.pseudoRoot.GetInfo(key)}" for key, value in stated.items()
                    if layer.pseudoRoot.HasInfo(key) and layer.pseudoRoot.GetInfo(key) != value]
            if says:
                other[Path(layer.identifier).name] = ", ".join(says)
        other = [f"{name} ({says})" for name, says in other.items()]
        if other:
            log.warning("%s: %d layer(s) state other units than the stage's (metersPerUnit %s, upAxis %s): %s; "
                        "USD does not convert them, so their prims are read in the stage's", path, len(other),
                        mpu, up, ", ".join(other[:3]) + (", ..." if len(other) > 3 else ""))
    to_scene = up_axis_matrix(up, scene_up)[:3, :3] * (mpu / scene_mpu)

    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    prims = [p for p in stage.Traverse(Usd.TraverseInstanceProxies())]
    chosen = []
    for pattern in wall.prims:
        if not any(ch in pattern for ch in "*?["):
            prim = stage.GetPrimAtPath(pattern)
            if not prim or not prim.IsValid():
                raise StageError(f"{path}: prim path {pattern} not found")
            # an explicit path selects the prim and the meshes under it
            matched = [p for p in prims if str(p.GetPath()) == pattern or str(p.GetPath()).startswith(pattern.rstrip("/") + "/")]
        else:
            matched = [p for p in prims if fnmatch.fnmatchcase(str(p.GetPath()), pattern)]
        chosen += [p for p in matched if p not in chosen]

    verts, faces, used, offset = [], [], [], 0
    animation: tuple | None = None
    cages: dict[str, str] = {}  # prim -> what became of its authored subdivision cage
    shapes = [p for p in chosen if _is_shape(p)]
    purposes = {p: UsdGeom.Imageable(p).ComputePurpose() for p in shapes}
    left_out = {p: "purpose guide" for p in shapes if purposes[p] == UsdGeom.Tokens.guide}
    # a PointInstancer's prototypes are no walls themselves (the /** traversal picked them up at the
    # prototype's own place and dropped the instances): each instance is, placed as the instancer places it
    owner = {}
    for pi in (p for p in prims if p.IsA(UsdGeom.PointInstancer)):
        roots = [pi.GetPath(), *UsdGeom.PointInstancer(pi).GetPrototypesRel().GetForwardedTargets()]
        owner.update({p: pi for p in prims if p != pi and p not in owner
                      and any(p.GetPath().HasPrefix(r) for r in roots)})
    left_out.update({p: f"prototype of {owner[p].GetPath()}" for p in shapes if p in owner})
    items = [(p, None) for p in shapes]
    # visibility is read when the geometry is, at the earliest time (a shot's start): at the default time a prim
    # keyed invisible only in time samples (from 1001) was a wall; walls do not appear or vanish in a shot
    first = Usd.TimeCode.EarliestTime()  # the default value, or the earliest sample of a prim with samples only
    warned: set = set()

    def invisible(prim) -> bool:
        for p in _animated_visibility(prim):
            if p not in warned and log is not None:
                attr = p.GetAttribute("visibility")
                log.warning("%s:%s: visibility is animated (%s); the wall takes it at its first sample, %s, for "
                            "the whole shot (walls do not appear or vanish)", path, p.GetPath(),
                            ", ".join(f"{c:g}: {attr.Get(c)}" for c in attr.GetTimeSamples()[:4]), attr.Get(first))
            warned.add(p)
        return UsdGeom.Imageable(prim).ComputeVisibility(first) == UsdGeom.Tokens.invisible

    for pi in (p for p in chosen if p.IsA(UsdGeom.PointInstancer) and p not in owner):
        if wall.include_invisible or not invisible(pi):
            items += [(m, (pi, name, xf)) for m, name, xf in _instances(stage, pi, path, wall.include_invisible)]
    if any(purposes[p] == UsdGeom.Tokens.render for p in shapes):
        left_out.update({p: "purpose proxy beside render meshes" for p in shapes if purposes[p] == UsdGeom.Tokens.proxy})
    for prim, instance in items:
        if instance is None and prim in left_out:
            continue
        if instance is None and not wall.include_invisible and invisible(prim):
            left_out[prim] = "invisible"
            continue
        name = str(prim.GetPath()) if instance is None else instance[1]
        where = f"{path}:{name}"
        shape = _shape_triangles(prim, first, where, log, getattr(wall, "subdivide", 0), cages)
        if shape is None:
            left_out[prim] = "no points or faces"
            continue
        pts, tris = shape
        mover = prim if instance is None else instance[0]  # an instance moves with its instancer
        codes = _sample_codes(mover)
        moves = _animation(stage, mover, codes, log, where) if codes else None
        if moves is not None and np.allclose(moves[1], np.eye(4), rtol=0, atol=1e-12):
            moves = None  # sampled but standing still (e.g. a single sample): a static wall
        if used and not _same_motion(animation, moves):
            raise StageError(f"{where}: moves differently from {used[0]}; a wall is one rigid body: "
                             "give each differently moving prim its own wall")
        animation = moves
        if codes:  # the rest pose: the earliest sample
            cache.SetTime(Usd.TimeCode(codes[0]))
        world = np.asarray(cache.GetLocalToWorldTransform(mover), np.float64)  # row-vector convention
        if instance is not None:
            world = instance[2] @ world
        cache.SetTime(Usd.TimeCode.Default())
        p = pts @ world[:3, :3] + world[3, :3]
        if np.linalg.det(world[:3, :3]) < 0:  # a mirroring transform flips the winding
            tris = tris[:, ::-1]
        verts.append(p @ to_scene.T)
        faces.append(tris + offset)
        offset += len(p)
        used.append(name)
    as_is = [p for p, what in cages.items() if "as-is" in what]
    if as_is and log is not None:
        log.info("%s: %s %s subdivision cage(s), taken as-is (the wall's subdivide: N refines them as a "
                 "renderer does)", path, ", ".join(as_is[:3]) + (", ..." if len(as_is) > 3 else ""),
                 cages[as_is[0]].split()[0])
    if left_out and log is not None and used:
        log.info("%s: left out %s", path, ", ".join(f"{p.GetPath()} ({why})" for p, why in left_out.items()))
    if not used:
        why = f" (left out: {', '.join(f'{p.GetPath()} ({w})' for p, w in left_out.items())})" if left_out else ""
        raise StageError(f"{path}: no visible UsdGeom.Mesh or shape prim (Cube, Sphere, ...) with faces matches {wall.prims}{why}")
    units = np.eye(4)
    units[:3, :3] = to_scene
    return np.concatenate(verts), np.concatenate(faces), used, units, animation, cages


def _selects(patterns: list[str], prim: str) -> bool:
    """Whether the wall's prim patterns select ``prim`` or a prim under or above it (the prims an arc to it
    would have brought)."""
    for pattern in patterns:
        if any(ch in pattern for ch in "*?["):
            if fnmatch.fnmatchcase(prim, pattern) or fnmatch.fnmatchcase(prim + "/_", pattern):
                return True
        elif (prim == pattern.rstrip("/") or prim.startswith(pattern.rstrip("/") + "/")
              or pattern.startswith(prim.rstrip("/") + "/")):
            return True
    return False


def _same_motion(a: tuple | None, b: tuple | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return (len(a[0]) == len(b[0]) and np.allclose(a[0], b[0], rtol=0, atol=1e-12)
            and np.allclose(a[1], b[1], rtol=1e-9, atol=1e-9 * max(1.0, float(np.abs(a[1][:, :3, 3]).max()))))


class UsdImport(TrimeshImport):
    """Wall meshes from OpenUSD stages (and built-ins / mesh files, as ``trimesh`` does)."""

    name = "usd"
    version = "5"
    default = False
    description = "walls from OpenUSD UsdGeom.Mesh prims and shapes (world transforms, units, up axis)"
