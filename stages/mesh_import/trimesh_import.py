"""mesh_import.trimesh: every wall of the config (built-in shapes, mesh files, USD prims) to one cleaned
world-space WallMesh (walls.npz + walls.json) and walls.usdc.

Per wall: read (built-in / trimesh for OBJ, PLY, STL, OFF, GLB, GLTF / usd_import for USD), convert
file units (``meters_per_unit``) to scene units, place (scale, rotate, fit, translate), clean (weld,
drop zero-area and duplicate faces, count boundary and non-manifold edges, fix winding) and orient so
that normals point into the fluid (see the package docstring). The clean-up report is stored per wall
in walls.json.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from pydantic import Field

from pipeline.scene import BuiltinWall, FileWall, UsdWall
from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import WallMesh
from stages.common.motion import RigidMotion, config_motion
from stages.common.parts import solid_faces
from stages.common.sdf import DEFAULT_SHELL_THICKNESS
from stages.common.wall_hints import stray_text

from .builtin import builtin_mesh
from .cleanup import clean_mesh
from .polygons import UTF8_BOM
from stages.common.placement import apply_placement, placement_matrix, up_axis_matrix

# what a file reader says outside a stage's ctx.log (read_mesh_file is also the emitters' reader): under the stage's name
LOG = logging.getLogger("stage.mesh_import.trimesh")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
USD_FILE = "walls.usdc"
# OBJ that trimesh misreads (valid OBJ all the same): a relative (negative) index, which trimesh resolves against
# the file's last vertex rather than the last one read so far (plain ``f -4 -3 -2 -1`` after each quad put every
# face on the last quad; with /vt or /vn an IndexError), tabs or indented lines (no faces read), a comment after a
# face (ValueError); index 0, which is no OBJ index (trimesh took the last vertex); and a line continued by a
# final backslash (the spec's; trimesh read the backslash as a vertex). Read by polygons.obj_polygons, which
# names the line of a bad index.
_OBJ_RELATIVE_OR_ZERO = re.compile(rb"(?m)^f[ \t](?:[^\n]*?[ \t])?(?:-\d|0+(?![\d.]))")
_OBJ_TRAILING_COMMENT = re.compile(rb"(?:^|\n)[vf][ \t][^#\n]*#")
_OBJ_CONTINUED = re.compile(rb"\\[ \t]*\r?(?:\n|$)")


def _obj_trimesh_misreads(data: bytes) -> bool:
    # plain byte tests first: one regex of all four cost 80 ms on a 1.7 MB OBJ, these 12 ms. A byte order mark:
    # trimesh took the first line for a word of its own (a file's first vertex dropped, every index one off)
    return (b"\t" in data or data[:1] == b" " or data.startswith(UTF8_BOM) or b"\n " in data
            or _OBJ_RELATIVE_OR_ZERO.search(data) is not None
            or _OBJ_TRAILING_COMMENT.search(data) is not None
            or (b"\\" in data and _OBJ_CONTINUED.search(data) is not None))


class ImportParams(Params):
    weld_tolerance: float = Field(1e-7, gt=0, le=1e-2,
                                  description="vertices closer than this fraction of the wall's bounding-box diagonal are welded")
    open_box_thickness: float = Field(0.05, gt=0, lt=0.5,
                                      description="wall thickness of the builtin open_box, fraction of its smallest horizontal size")


def mesh_file_dependencies(path: Path) -> list[Path]:
    """The files a mesh file reads its geometry from besides itself: a .gltf's external buffers (its images
    do not shape the walls). Keyed as the stage's ``external_files``: an edit of the .bin is a new key."""
    if path.suffix.lower() != ".gltf" or not path.is_file():
        return []
    import json
    from urllib.parse import unquote

    try:
        buffers = json.loads(path.read_text(encoding="utf-8")).get("buffers", [])
    except (OSError, ValueError, AttributeError):
        return []  # the import says what is wrong with the file
    uris = [b.get("uri") for b in buffers if isinstance(b, dict)]
    return [path.parent / unquote(u) for u in uris if isinstance(u, str) and not u.startswith("data:")]


def to_scene_frame(v: np.ndarray, path: Path, meters_per_unit: float | None, up_axis: str | None, units) -> np.ndarray:
    """A mesh file's vertices in the scene's units and up axis: the file's as the config states them, else
    glTF's own (metres, +Y up: the format's specification; a GLB tank in a Z-up scene lay on its side), else
    the scene's (OBJ, STL, PLY and OFF carry neither)."""
    gltf = path.suffix.lower() in (".glb", ".gltf")
    mpu = meters_per_unit if meters_per_unit is not None else (1.0 if gltf else units.meters_per_unit)
    up = up_axis or ("Y" if gltf else units.up_axis)
    v = v * (mpu / units.meters_per_unit) if mpu != units.meters_per_unit else v
    if up != units.up_axis and len(v):
        v = v @ up_axis_matrix(up, units.up_axis)[:3, :3].T
    return v


def _text_with_a_bom(data: bytes, suffix: str) -> bool:
    """A text mesh file (OBJ, ASCII PLY / STL, OFF) that starts with a UTF-8 byte order mark: trimesh takes the
    mark for part of the first word (an OBJ's first vertex, an STL's 'solid'). A binary STL's 80-byte header is
    free bytes that may start so: only an ASCII one ('solid' after the mark) counts."""
    if not data.startswith(UTF8_BOM):
        return False
    return suffix != ".stl" or data[3:].lstrip()[:5].lower() == b"solid"


def _stl_with_a_wrong_count(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """A binary STL whose header's triangle count disagrees with its size (0 or a stale count from an exporter
    that streams, or trailing bytes): read as many whole 50-byte records as the file holds, and say so; None for
    any other file (trimesh refused these as 'not a valid STL file'). A file that ends inside a record short of
    the count it states is cut off (a download or copy that stopped): refused, not read as the records it kept
    (a tank with most of its walls missing)."""
    data = path.read_bytes()
    if len(data) < 84 + 50:
        return None
    head = data[:1024].removeprefix(UTF8_BOM).lstrip().lower()
    if head.startswith(b"solid") and (b"facet" in head or b"\0" not in head):
        return None  # ASCII (a long name on its 'solid' line: no facet yet, and no NUL a binary's records hold)
    stated = int(np.frombuffer(data, "<u4", 1, 80)[0])
    held = (len(data) - 84) // 50
    partial = (len(data) - 84) % 50
    if stated == held and partial == 0:
        return None
    if stated > held and partial:
        raise StageError(f"{path}: binary STL cut off: its header says {stated} triangles and the file ends "
                         f"{partial} bytes into triangle {held + 1} (an interrupted download or copy?)")
    record = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    tri = np.frombuffer(data, record, held, 84)["v"].astype(np.float64)
    if not np.isfinite(tri).all():
        return None
    LOG.warning("%s: binary STL whose header says %d triangles and whose size holds %d%s: read %d", path, stated, held,
                f" and {partial} bytes more" if partial else "", held)
    return tri.reshape(-1, 3), np.arange(3 * held, dtype=np.int64).reshape(-1, 3)


def read_mesh_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # imported where used: a cached run or `pipeline status` need not load it (~1 s)
    if not path.is_file():
        raise StageError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise StageError(f"{path}: unsupported mesh format {suffix or '(none)'!r}; expected one of {', '.join(MESH_SUFFIXES)} or .usd*")
    if suffix == ".stl":
        fixed = _stl_with_a_wrong_count(path)
        if fixed is not None:
            return fixed
    if suffix == ".off":
        from .polygons import off_polygons, triangulate
        try:
            polygons = off_polygons(path.read_bytes())
        except ValueError as e:
            raise StageError(f"{path}: cannot read as OFF ({str(e)[:160]})") from None
        if polygons is not None:
            return polygons[0], triangulate(*polygons)[0]
    if suffix == ".ply":
        from .polygons import ply_binary_polygons, triangulate
        try:
            polygons = ply_binary_polygons(path.read_bytes())  # None: ASCII, or faces trimesh reads
        except ValueError as e:
            raise StageError(f"{path}: cannot read as PLY ({str(e)[:160]})") from None
        if polygons is not None:
            if polygons[3]:
                LOG.warning("%s: %d bytes after the data its PLY header declares: ignored", path, polygons[3])
            return polygons[0], triangulate(*polygons[:3])[0]
    if suffix == ".obj":
        data = path.read_bytes()
        if _obj_trimesh_misreads(data):
            from .polygons import ObjIndexError, obj_polygons, triangulate
            try:
                polygons = obj_polygons(data, triangles_too=True)
            except ObjIndexError as e:
                raise StageError(f"{path}: {e}") from None
            except ValueError as e:
                raise StageError(f"{path}: cannot read as OBJ ({str(e)[:160]})") from None
            return polygons[0], triangulate(*polygons)[0]
    source, kwargs = str(path), {}
    if suffix in (".ply", ".stl"):
        with open(path, "rb") as fh:
            head = fh.read(64)
        if _text_with_a_bom(head, suffix):
            import io
            source, kwargs = io.BytesIO(path.read_bytes()[len(UTF8_BOM):]), {"file_type": suffix[1:]}
    if suffix in (".gltf", ".glb"):
        from .gltf import prepare

        rewritten = prepare(path)  # fans as triangles; Draco, points and lines refused in one line
        if rewritten is not None:
            source = rewritten[0]
            kwargs = {"file_type": rewritten[1], "resolver": trimesh.resolvers.FilePathResolver(str(path))}
    try:
        loaded = trimesh.load(source, force="mesh", process=False, maintain_order=True, **kwargs)
    except Exception as e:
        if suffix == ".obj":  # a token that is no face vertex: trimesh's error names no line, ours does
            from .polygons import ObjIndexError, obj_polygons
            try:
                obj_polygons(path.read_bytes(), triangles_too=True)
            except ObjIndexError as bad:
                raise StageError(f"{path}: {bad}") from None
            except ValueError:
                pass
        if isinstance(e, IndexError) or "range" in str(e):
            raise StageError(f"{path}: face index out of range ({str(e)[:120]})") from None
        raise StageError(f"{path}: cannot read as {suffix[1:].upper()} ({type(e).__name__}: {str(e)[:120]})") from None
    v = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    f = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), np.int64).reshape(-1, 3)
    if suffix == ".obj":
        _check_obj_indices(path, len(v), len(f))
    if suffix in (".obj", ".ply"):
        # trimesh fans every polygon from its first vertex: across the notch of a concave one (a phantom
        # wall). Re-triangulate from the file's polygons when some fan is wrong; else keep trimesh's
        # triangles as they were (same geometry and face order for existing scenes).
        from .polygons import ObjIndexError, fan, obj_polygons, ply_polygons, triangulate

        polygons = None
        if suffix == ".obj":
            try:
                polygons = obj_polygons(path.read_bytes())
            except ObjIndexError as e:
                raise StageError(f"{path}: {e}") from None
            except ValueError as e:
                raise StageError(f"{path}: cannot read as OBJ ({str(e)[:160]})") from None
        else:
            raw = (getattr(loaded, "metadata", None) or {}).get("_ply_raw")
            faces = ply_polygons(raw) if isinstance(raw, dict) else None
            if faces is not None and len(faces[1]) and 0 <= faces[1].min() and faces[1].max() < len(v):
                polygons = (v, *faces)
        if polygons is not None:
            pv, counts, idx = polygons
            tris, _ = triangulate(pv, counts, idx)
            if not np.array_equal(tris, idx[fan(counts)[0]]):
                v, f = pv, tris
    return v, f


def _check_obj_indices(path: Path, n_vertices: int, n_faces: int) -> None:
    """trimesh silently drops OBJ faces whose index is out of range; find them ourselves."""
    from .polygons import ObjIndexError, obj_index

    n_v = 0
    with open(path, "rb") as fh:
        for number, line in enumerate(fh, 1):
            if line.startswith(b"v "):
                n_v += 1
            elif line.startswith(b"f "):
                for tok in line.split()[1:]:
                    try:
                        i = obj_index(tok, number)
                    except ObjIndexError as e:
                        raise StageError(f"{path}: {e}") from None
                    if i > n_v if i > 0 else -i > n_v:
                        raise StageError(f"{path}: line {number}: face index {i} out of range "
                                         f"(only {n_v} vertices defined before it)")


def _wall_name(i: int, label: str) -> str:
    return f"wall{i}_" + re.sub(r"[^A-Za-z0-9_]", "_", label)[:40]


# A stray part: connected pieces holding less than STRAY_AREA of a wall's area whose box lies more than the rest's
# diagonal away from the rest's box, widening the wall's box more than STRAY_WIDENS times along some axis (a 1 mm
# triangle left 50 m away made the SDF grid 1254 x 83 x 54 instead of 83 x 83 x 54). Scale-free: no length in it.
STRAY_AREA = 0.01
STRAY_WIDENS = 2.0


def stray_part(v: np.ndarray, f: np.ndarray) -> dict | None:
    """The stray part of a cleaned wall (scene units): its triangles and pieces, area share, box, the rest's box,
    its distance from it, and how many times it widens the wall's box along its worst axis; None when there is
    none. Pieces are vertex-connected; a tiny piece near the rest counts as the rest."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(f) < 2:
        return None
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(len(v), len(v)))
    k, label = connected_components(graph, directed=False)
    if k < 2:
        return None
    piece = label[f[:, 0]]
    a, b = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    cross = np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                      a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)  # np.cross: 3x slower on a 1M-face wall
    area = 0.5 * np.sqrt(np.einsum("ij,ij->i", cross, cross))
    total = float(area.sum())
    share = np.bincount(piece, area, k) / (total or 1.0)
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True  # a vertex no face uses is no piece (the caller's mesh is cleaned: belt and braces)
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    np.minimum.at(lo, label[used], v[used])
    np.maximum.at(hi, label[used], v[used])
    has = np.isfinite(lo).all(axis=1)
    tiny = has & (share < STRAY_AREA)
    if total <= 0 or not tiny.any() or not (has & ~tiny).any():
        return None
    far = tiny
    while True:  # the rest grows by the tiny pieces near it until none is left to join
        rest_lo, rest_hi = lo[has & ~far].min(axis=0), hi[has & ~far].max(axis=0)
        gap = np.linalg.norm(np.maximum(0.0, np.maximum(rest_lo - hi, lo - rest_hi)), axis=1)
        diag = float(np.linalg.norm(rest_hi - rest_lo))
        now = tiny & (gap > diag)
        if (now == far).all():
            break
        far = now
    if not far.any():
        return None
    wall = hi[has].max(axis=0) - lo[has].min(axis=0)
    widens = wall / np.maximum(rest_hi - rest_lo, 1e-3 * diag)  # a flat wall (a plane): no 0 to divide by
    axis = int(np.argmax(widens))
    if widens[axis] <= STRAY_WIDENS:
        return None
    faces = far[piece]
    return {"triangles": int(faces.sum()), "pieces": int(far.sum()), "area_share": float(share[far].sum()),
            "min": lo[far].min(axis=0).tolist(), "max": hi[far].max(axis=0).tolist(),
            "rest_min": rest_lo.tolist(), "rest_max": rest_hi.tolist(), "distance": float(gap[far].min()),
            "widens": float(widens[axis]), "axis": "xyz"[axis]}


# An opening no wider than this many particle spacings does not make a mesh a shell: a shell's wall
# region (0.6 l0 thick, plus the push-out distance 0.5 l0 on each side) closes it for the fluid anyway.
SMALL_HOLE = 2.0


class TrimeshImport(Stage):
    """Wall meshes from built-in shapes, mesh files (trimesh) and USD prims."""

    kind = "mesh_import"
    name = "trimesh"
    version = "7"
    Params = ImportParams
    outputs = ("walls",)
    reads = ("scene.units", "walls", "fluid.spacing")  # fluid.spacing: a shell's default thickness
    default = True
    description = "walls from builtin shapes, OBJ/PLY/STL/OFF/GLB/GLTF (trimesh) and USD, cleaned, in world space"

    def external_files(self, ctx: Context, params: Params) -> list[Path]:
        """The layers and assets each USD wall composes, a .gltf wall's buffers (the wall files themselves the
        engine finds)."""
        from .usd_import import usd_dependencies

        return [f for w in ctx.scene["walls"] if isinstance(w, UsdWall) for f in usd_dependencies(ctx.resolve(w.usd))] \
            + [f for w in ctx.scene["walls"] if isinstance(w, FileWall) for f in mesh_file_dependencies(ctx.resolve(w.file))]

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: Params) -> None:
        import trimesh
        scene = ctx.scene["scene"]
        walls = ctx.scene["walls"]
        verts, faces, ids, solids, info = [], [], [], [], []
        offset = 0
        bar = ctx.progress("importing walls", len(walls))
        spacing = ctx.scene["fluid"].spacing if ctx.scene.get("fluid") is not None else None
        for i, w in enumerate(walls):
            v, f, fluid, source, extra = self._read(ctx, w, params)
            where = source
            if len(v) == 0 or len(f) == 0:
                raise StageError(f"{where}: {_why_no_faces(where)}")
            if f.min() < 0 or f.max() >= len(v):
                raise StageError(f"{where}: face index {int(f.max())} out of range (mesh has {len(v)} vertices)")
            used, inverse = np.unique(f, return_inverse=True)
            if len(used) < len(v):
                # a vertex no face uses shapes nothing: left out before the placement, whose fit: box it widened
                # (a stray point 10 x away shrank the wall 10 x), and a NaN in one does not refuse the file
                ctx.log.info("%s: %d vertices no face uses left out (%d with NaN or Inf coordinates)", where,
                             len(v) - len(used), int((~np.isfinite(v).all(axis=1)).sum()))
                v, f = v[used], inverse.reshape(-1, 3)
            if not np.isfinite(v).all():
                raise StageError(f"{where}: vertex coordinates contain NaN or Inf")
            v = apply_placement(v, w)
            motion = self._motion(w, v, extra.pop("animation", None), f"{where}:{extra['prims'][0]}" if "prims" in extra else where)
            diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) or 1.0
            mesh, report = clean_mesh(trimesh.Trimesh(v, f, process=False), params.weld_tolerance * diag)
            if len(mesh.faces) == 0:
                raise StageError(f"{where}: empty mesh after removing degenerate faces")
            stray = stray_part(np.asarray(mesh.vertices), np.asarray(mesh.faces))
            if stray is not None:
                # said here, and kept in the report: the SDF grid covers it (a refusal of its size can name it)
                report["stray_part"] = stray
                ctx.log.warning("%s: %s (and the SDF grid with it): delete it from the file if it is not meant to "
                                "be there", where, stray_text(stray))
            label = Path(source).stem if not isinstance(w, BuiltinWall) else w.builtin
            fluid, shell, solid = self._solid_or_shell(ctx, i, label, w, fluid, report, mesh)
            if fluid == "inside":
                mesh.invert()  # container: normals into the fluid, i.e. inwards
            asset_to_scene = extra.pop("asset_to_scene", None)
            report.update(extra)
            if not report["watertight"] and shell is None:
                wide = spacing and report["largest_hole"] > SMALL_HOLE * spacing
                # a wide opening the vote closes is a lid without a distance: the field jumps from +band to -band
                # there, so the solvers' wall terms never see it (a tank missing a side: 279 Pa at it against 960)
                lid = (f"; its opening, {report['largest_hole'] / spacing:.3g} l0 across, is closed as by a lid the "
                       f"field has no distance to (the water meets it without wall pressure): model the lid, or leave "
                       f"fluid: unset to make the wall a shell") if wide else ""
                # scan holes the vote outvotes are the normal case of a real model (the shipped dragon and Buddha):
                # said, not warned, so a warning still means something to do
                (ctx.log.warning if wide else ctx.log.info)(
                    "%s: not watertight (%d boundary edges, %d non-manifold); the SDF sign uses ray voting%s",
                    where, report["boundary_edges"], report["non_manifold_edges"], lid)
            # the file as the config names it (relative to its folder), not the resolved path: a copied or moved
            # project reuses this cache entry (same key) and must not publish the first project's absolute paths
            named = source if isinstance(w, BuiltinWall) else str(w.usd if isinstance(w, UsdWall) else w.file)
            info.append({"name": _wall_name(i, label), "fluid": fluid, "source": named, "report": report})
            if fluid == "both":
                info[-1]["shell"] = shell
            if asset_to_scene is not None:
                info[-1]["asset_to_scene"] = asset_to_scene
            if motion is not None:
                info[-1]["motion"] = motion.to_json()
            verts.append(np.asarray(mesh.vertices, np.float64))
            faces.append(np.asarray(mesh.faces, np.int64) + offset)
            ids.append(np.full(len(mesh.faces), i, np.int32))
            solids.append(np.zeros(len(mesh.faces), np.bool_) if solid is None else solid)
            offset += len(mesh.vertices)
            bar.advance()
        if verts:
            solid = np.concatenate(solids)
            wm = WallMesh(np.concatenate(verts), np.concatenate(faces).astype(np.int32), np.concatenate(ids), info,
                          solid if solid.any() else None)
        else:
            wm = WallMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int32), info)
        wm.save(ctx.out_dir)
        write_walls_usd(ctx.out_dir / USD_FILE, wm, scene.units.meters_per_unit, scene.units.up_axis)
        ctx.log.info("%d walls, %d triangles", len(info), len(wm.faces))

    @staticmethod
    def _motion(w: Any, v: np.ndarray, animation: tuple | None, where: str) -> RigidMotion | None:
        """The wall's rigid motion about its placed rest pose ``v``: the config's keyframes, or the USD
        prims' animation (times, rest -> world matrices in scene coordinates); the pivot defaults to the
        centre of the rest bounding box."""
        if w.motion is None and animation is None:
            return None
        if w.motion is not None:
            return config_motion(w.motion, v)
        pivot = 0.5 * (v.min(axis=0) + v.max(axis=0))
        try:
            return RigidMotion.from_matrices(*animation, pivot)
        except ValueError as e:
            raise StageError(f"{where}: {e}; only rigid animations (translate, rotate) can move a wall") from None

    @staticmethod
    def _solid_or_shell(ctx: Context, i: int, label: str, w: Any, fluid: str | None,
                        report: dict, mesh: Any) -> tuple[str, float | None, np.ndarray | None]:
        """(fluid side, shell thickness in scene units, the shell's solid faces) of wall ``i``: what the config
        says, else a shell for an open mesh (an opening wider than SMALL_HOLE l0) and a solid obstacle otherwise.
        A shell's fluid is "both"; its thickness is None when left to sdf_bake's default (no fluid spacing here).
        Chosen per part (sets of faces joined across edges, stages.common.parts) when the config says neither: a
        closed rock in the file of an open tank stays solid (its faces flagged, WallMesh.solid), where the whole
        wall became a shell and the rock hollow (the emitter filled it)."""
        shell = getattr(w, "shell", None)
        solid = None
        if fluid is not None and shell is None:
            return fluid, None, None
        spacing = ctx.scene["fluid"].spacing if ctx.scene.get("fluid") is not None else None
        closed = ""
        if shell is not None and shell.thickness is not None:
            thickness, why = shell.thickness, "shell in the config"
        else:
            if shell is None and report["boundary_edges"] == 0:
                ctx.log.info("wall %d (%s): closed mesh -> solid, fluid outside; set fluid: inside for a container",
                             i, label)
                return "outside", None, None
            if shell is None and spacing and report["largest_hole"] <= SMALL_HOLE * spacing:
                # closed but messy (scan holes, stray faces): no fluid passes an opening this narrow
                # either way, and a solid keeps its inside/outside (the sign vote outvotes the holes)
                ctx.log.info("wall %d (%s): closed but for small holes (%d boundary edges, widest %.2g l0) -> "
                             "solid, fluid outside; set fluid: or shell: to override", i, label,
                             report["boundary_edges"], report["largest_hole"] / spacing)
                return "outside", None, None
            thickness = DEFAULT_SHELL_THICKNESS * spacing if spacing else None  # None: sdf_bake's default
            why = "shell in the config" if shell is not None else f"open mesh ({report['boundary_edges']} boundary edges)"
            if shell is None:
                small = SMALL_HOLE * spacing if spacing else 0.0
                solid, parts = solid_faces(np.asarray(mesh.vertices)[np.asarray(mesh.faces)], small)
                n_solid = int(len(np.unique(parts.part[solid])))
                if n_solid:
                    n_open = parts.count - n_solid
                    report["parts"] = {"open": n_open, "closed": n_solid}
                    why = f"{n_open} open part{'s' * (n_open > 1)} ({report['boundary_edges']} boundary edges)"
                    closed = f", {n_solid} closed part{'s' * (n_solid > 1)} -> solid, fluid outside"
        size = f"{thickness:.4g} ({thickness / spacing:.3g} l0)" if spacing else f"{DEFAULT_SHELL_THICKNESS} l0"
        tail = "" if shell is not None else f"; set fluid: inside/outside to override{' (the whole wall)' * bool(closed)}"
        ctx.log.info("wall %d (%s): %s -> shell %s thick%s%s", i, label, why, size, closed, tail)
        return "both", thickness, solid if closed else None

    def _read(self, ctx: Context, w: Any, params: ImportParams) -> tuple[np.ndarray, np.ndarray, str, str, dict]:
        units = ctx.scene["scene"].units
        if isinstance(w, BuiltinWall):
            mesh, fluid = builtin_mesh(w, units.up_axis, params.open_box_thickness)
            return np.asarray(mesh.vertices), np.asarray(mesh.faces), fluid, f"builtin:{w.builtin}", {}
        if isinstance(w, UsdWall):
            from .usd_import import read_usd_wall

            path = ctx.resolve(w.usd)
            if path.suffix.lower() not in (".usd", ".usda", ".usdc", ".usdz"):
                raise StageError(f"{path}: unsupported USD format {path.suffix!r}; expected .usd, .usda, .usdc or .usdz")
            v, f, prims, to_units, animation, cages = read_usd_wall(path, w, units.meters_per_unit, units.up_axis,
                                                                    ctx.log)
            # the asset's frame -> the scene's, so export can reference the asset in place
            to_scene = placement_matrix(v[np.unique(f)], w) @ to_units  # as run() places them: used vertices
            extra = {"prims": prims, "asset_to_scene": to_scene.ravel().tolist()}
            if cages:
                extra["subdivision"] = cages
            if animation is not None:
                if w.motion is not None:
                    raise StageError(f"{path}: {prims[0]} is animated in the USD file and the wall has a motion "
                                     "in the config; keep one of them")
                # the stage's world frame -> the scene's: the same rigid motion seen from the scene
                times, mats = animation
                extra["animation"] = (times, to_scene @ mats @ np.linalg.inv(to_scene))
            return v, f, w.fluid, str(path), extra
        path = ctx.resolve(w.file)
        v, f = read_mesh_file(path)
        return to_scene_frame(v, path, w.meters_per_unit, w.up_axis, units), f, w.fluid, str(path), {}


def write_walls_usd(path: Path, wm: WallMesh, meters_per_unit: float, up_axis: str) -> None:
    """One UsdGeom.Mesh per wall under /Walls, with the stage metrics authored."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    from stages.common.formats import local_origin
    from stages.common.usd_points import local_frame

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    root = UsdGeom.Xform.Define(stage, "/Walls")
    stage.SetDefaultPrim(root.GetPrim())
    shift = np.zeros(3)
    if len(wm.vertices):  # far from the origin: the points relative to the walls' centre (point3f is float32)
        lo, hi = wm.vertices.min(axis=0), wm.vertices.max(axis=0)
        shift = local_frame(root, local_origin(lo, hi, 1e-3 * float((hi - lo).max())))
    for i, w in enumerate(wm.walls):
        sel = wm.wall_id == i
        f = wm.faces[sel]
        used, local = np.unique(f, return_inverse=True)
        pts = wm.vertices[used] - shift
        mesh = UsdGeom.Mesh.Define(stage, Sdf.Path("/Walls").AppendChild(w["name"]))
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(local.reshape(-1).astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateExtentAttr([Gf.Vec3f(*pts.min(axis=0).tolist()), Gf.Vec3f(*pts.max(axis=0).tolist())])
        mesh.GetPrim().SetCustomDataByKey("fluid", w["fluid"])
    stage.GetRootLayer().Save()


def _why_no_faces(source: str) -> str:
    """An empty file, or bytes the loader for its extension found no triangles in (an OBJ named .stl,
    a corrupt download): say which, rather than "empty mesh" for both."""
    path = Path(source)
    try:
        size = path.stat().st_size if path.is_file() else None
    except OSError:
        size = None
    if size is None:
        return "no triangles (empty mesh)"
    if size == 0:
        return "the file is empty"
    ext = path.suffix.lstrip(".").upper() or "a mesh"
    return (f"no triangles read from its {size} bytes as {ext}: not a valid {ext} file (a different format under "
            f"this extension, or damaged?)")
