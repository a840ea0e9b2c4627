"""Export a composed OpenUSD scene: a small scene.usda root that sublayers one layer per department.

    usd/scene.usda            root: stage metrics, default prim /World, the camera; sublayers the rest
    usd/fluid_surface.usdc    time-sampled UsdGeom.Mesh /World/Fluid/Surface + its water material
    usd/particles.usdc        time-sampled UsdGeom.Points (the particles artifact's layer when it is
                              in the export's frame, else written here)
    usd/walls.usdc            wall meshes that did not come from a USD asset (a moving wall: its rest
                              mesh under an xformOp:transform time-sampled at every exported frame)
    usd/assets/...            copies of studio USD assets the walls came from (with their local
                              dependencies): sublayered so their prim paths stay as they are, unless
                              they need a transform or have prims under /World (then referenced as
                              /World/Asset_k/Asset, so they cannot move or restyle our prims)
    usd/scene.usdz            optional package of all of the above

Every path inside is relative, so the folder works wherever the engine publishes it. With a studio
asset, ``fluid_units: asset`` (the default when there is one) writes every layer in the asset's units
and up axis, with the placement of the asset in the scene undone, so the fluid layer lines up with the
asset and can be sublayered straight into the shot.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Literal, Mapping

import numpy as np
from pydantic import Field, field_validator, model_validator

from pipeline.scene import UsdWall
from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.camera import camera_files, fluid_bounds, shot_camera, usd_camera_moves
from stages.common.formats import ParticleMeta, WallMesh, load_particle_frame, load_surface, local_origin
from stages.common.usd_points import local_frame

from . import usd_layers as ul
from .surface_velocity import surface_velocities


def _inside_path(v: str | None) -> str | None:
    """A relative path that stays inside the artifact folder (no absolute path, no '..', a USD suffix)."""
    if v is None:
        return v
    p = PurePosixPath(v.replace("\\", "/"))
    if not v.strip() or p.is_absolute() or PureWindowsPath(v).drive or any(part in ("..", "") for part in p.parts) \
            or p.parts[0] == ".":
        raise ValueError("expected a relative path inside the usd output folder, e.g. layers/fluid.usdc")
    if p.suffix.lower() not in (".usd", ".usda", ".usdc"):
        raise ValueError("expected a .usd, .usda or .usdc file name")
    # the export's own files (known before anything runs: refused after the whole simulation, it cost the shot)
    if p.as_posix().lower() in OWN_FILES or p.parts[0].lower() == "assets":
        raise ValueError(f"{p.as_posix()} is a file the export itself writes ({', '.join(sorted(OWN_FILES))}, "
                         "assets/...); choose another name, e.g. layers/fluid.usdc")
    return p.as_posix()


OWN_FILES = ("scene.usda", "fluid_surface.usdc", "particles.usdc", "walls.usdc")


class UsdParams(Params):
    surface: bool = Field(True, description="export the fluid surface (needs the wall_snap stage)")
    particles: bool = Field(True, description="export the particles as time-sampled UsdGeom.Points")
    surface_velocities: bool = Field(True, description="author the surface's velocities, interpolated from the "
                                     "particles: a renderer's motion blur of a mesh whose topology changes every "
                                     "frame needs them")
    fluid_units: Literal["auto", "scene", "asset"] = Field(
        "auto", description="frame of the written layers: the scene's units/up axis, or the studio asset's "
        "(auto: the asset's when a wall came from a USD asset)")
    fluid_layer_path: str | None = Field(
        None, description="also write the fluid layer alone to this path inside the published usd folder "
        "(relative, e.g. layers/fluid.usdc; the pipeline writes only inside its cache and output folder)")
    usdz: bool = Field(False, description="also package everything as scene.usdz")
    # 0.1-10 holds every film and phone format (1e-9 wrote a camera whose film back is a line)
    camera_aspect: float | None = Field(None, ge=0.1, le=10, description="the USD camera's image width / height, 0.1 "
                                        "to 10; default: "
                                        "camera.resolution's (the shot's, which render draws), else 16 / 9 (the view "
                                        "itself is the scene's camera section)")

    _fluid_layer_inside = field_validator("fluid_layer_path")(_inside_path)

    @model_validator(mode="after")
    def _layer_needs_surface(self):
        if self.fluid_layer_path and not self.surface:  # it was skipped without a word
            raise ValueError("fluid_layer_path is the surface's layer: it needs surface: true")
        if not (self.surface or self.particles):  # a USD of walls and a camera, published as the shot's fluid
            raise ValueError("surface and particles are both false: the USD would hold no fluid; set one true, or "
                             "leave usd out of outputs")
        return self


USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def _usd_source(info: dict) -> str | None:
    """The USD asset a walls.json entry came from: its "usd" key, or a "source" that is a USD file
    (mesh_import.trimesh records the resolved file path as source, the prims under report)."""
    if info.get("usd"):
        return str(info["usd"])
    source = str(info.get("source", ""))
    return source if source.lower().endswith(USD_SUFFIXES) else None


ASSET_WITHOUT_USD_WALL = "export.usd: fluid_units: asset needs a wall from a USD asset (walls: - usd: ...)"
ROOT = "/World"  # every prim the export authors is under it (fluid, particles, walls, camera, Asset_k)


def _has_own_prims(asset: Path) -> bool:
    """Whether the asset has opinions at or under ROOT. Sublayered, they would compose over ours: a set
    whose /World is translated 1 cm moved the fluid, the walls and the camera with it (and its kind,
    visibility or a /World/Fluid of its own would land on ours too), so such an asset is referenced."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(asset), Usd.Stage.LoadNone)  # held: a prim of a dropped stage is invalid
    return stage.GetPrimAtPath(ROOT).IsValid()


def write_fx_layer(source: Path, target: Path, assets: list[Path]) -> None:
    """The fluid layer alone, for a shot's FX sublayer. Its prims are under ROOT, unless an asset in its frame
    has a ROOT prim of its own: sublayered beside that set, the two /World merged and the set's root transform
    (and kind, visibility) landed on the water (3 cm high in a set whose /World is translated). The copy is
    then rooted at /FX (or /FX_k, a name no asset has), its material binding remapped with it."""
    from pxr import Sdf, Usd

    src = Sdf.Layer.FindOrOpen(str(source))
    if not any(_has_own_prims(a) for a in assets):
        src.Export(str(target))
        return
    stages = [Usd.Stage.Open(str(a), Usd.Stage.LoadNone) for a in assets]  # held: their prims die with them
    taken = {p.GetName() for stage in stages for p in stage.GetPseudoRoot().GetChildren()}
    name = next(n for n in ("FX", *(f"FX_{k}" for k in range(1, len(taken) + 2))) if n not in taken)
    layer = Sdf.Layer.CreateNew(str(target))
    layer.TransferContent(src)
    Sdf.CopySpec(src, ROOT, layer, f"/{name}")  # relationship and connection targets follow the copy
    del layer.rootPrims[ROOT.lstrip("/")]
    layer.defaultPrim = name
    layer.Save()


def _shot_offset(asset: Path, fps: float):
    """The layer offset that puts the asset's startTimeCode at our code 0 (studios start shots at 1001;
    mesh_import simulated the asset's animation from its start), or None when it starts at 0. USD scales
    the time codes by the two layers' timeCodesPerSecond itself; the offset is in our codes."""
    from pxr import Sdf, Usd

    from stages.common.usd_stage import shot_start

    stage = Usd.Stage.Open(str(asset), Usd.Stage.LoadNone)
    start = shot_start(stage)
    return Sdf.LayerOffset(-start * fps / stage.GetTimeCodesPerSecond(), 1.0) if start else None


def _reference_roots(asset: Path, infos: list[dict]) -> list[str | None]:
    """The asset's root prims to reference: its default prim (None) and any other root holding a wall's
    prim; without a default prim, the roots holding the walls (a reference to the missing default prim
    brought nothing: the walls vanished from the scene)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(asset), Usd.Stage.LoadNone)
    paths = [p for info in infos for p in (info.get("report", {}).get("prims") or info.get("prims") or [])]
    roots = {"/" + p.strip("/").split("/")[0] for p in paths if p.strip("/")}
    roots = sorted(r for r in roots if stage.GetPrimAtPath(r).IsValid())
    default = stage.GetDefaultPrim()
    if default:
        return [None] + [r for r in roots if r != str(default.GetPath())]
    return roots or [str(p.GetPath()) for p in stage.GetPseudoRoot().GetChildren()][:1]


def _safe_name(name: str, used: set[str]) -> str:
    from pxr import Tf

    base = Tf.MakeValidIdentifier(str(name) or "wall")
    out, k = base, 1
    while out in used:
        k += 1
        out = f"{base}_{k}"
    used.add(out)
    return out


class UsdExport(Stage):
    kind = "export"
    name = "usd"
    version = "7"
    Params = UsdParams
    inputs = ("walls", "particles")
    optional_inputs = ("surface",)
    outputs = ("usd",)
    # the USD assets walls came from are in the upstream walls key (mesh_import hashes them)
    reads = ("scene.units", "scene.frames.fps", "scene.frames.count", "camera", "frames")
    estimate_reads = ("walls",)  # check: fluid_units: asset without a USD wall
    default = True
    description = "scene.usda composing walls, particles, fluid surface and camera layers (usd-core)"

    def input_names(self, params: UsdParams) -> tuple[str, ...]:
        return ("walls", "particles", "surface") if params.surface else ("walls", "particles")

    def external_files(self, ctx: Context, params: UsdParams) -> list[Path]:
        return camera_files(ctx)  # the layers a camera.usd composes: the exported camera is read from them

    def check(self, ctx: Context, params: UsdParams) -> None:
        # the walls are the config's: refused before the simulation, not after it (run keeps its own check for
        # walls only mesh_import's output shows)
        if params.fluid_units == "asset" and not any(isinstance(w, UsdWall) for w in ctx.scene["walls"] or []):
            raise StageError(ASSET_WITHOUT_USD_WALL)

    # -- the studio asset's frame -------------------------------------------------------------------
    def _asset_path(self, ctx: Context, info: dict) -> Path:
        path = ctx.resolve(_usd_source(info))
        if not path.is_file():
            raise StageError(f"export.usd: wall {info.get('name')!r}: USD asset {path} not found")
        return path

    @staticmethod
    def _asset_to_scene(info: dict) -> np.ndarray:
        """4x4 matrix (column vectors) from the asset's coordinates to the scene's, as mesh_import
        recorded it in walls.json: unit and up-axis change, then the wall's placement (incl. fit)."""
        if "asset_to_scene" not in info:
            raise StageError(f"export.usd: wall {info.get('name')!r} has no asset_to_scene in walls.json; "
                             "re-run mesh_import (pipeline run --from mesh_import)")
        return np.asarray(info["asset_to_scene"], float).reshape(4, 4)

    # -- run -----------------------------------------------------------------------------------------
    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: UsdParams) -> None:
        from pxr import Sdf, Usd, UsdGeom, UsdUtils

        out = Path(ctx.out_dir)
        scene = ctx.scene["scene"]
        fps, count = scene.frames.fps, scene.frames.count
        frames = sorted(ctx.frames)
        walls = WallMesh.load(inputs["walls"].path)

        # studio assets the walls came from, and the frame every layer is written in
        usd_walls = {i: info for i, info in enumerate(walls.walls) if _usd_source(info)}
        assets: dict[Path, np.ndarray] = {}
        asset_walls: dict[Path, list[dict]] = {}
        for info in usd_walls.values():
            path = self._asset_path(ctx, info)
            assets.setdefault(path, self._asset_to_scene(info))
            asset_walls.setdefault(path, []).append(info)
        mode = params.fluid_units if params.fluid_units != "auto" else ("asset" if assets else "scene")
        if mode == "asset" and not assets:
            raise StageError(ASSET_WITHOUT_USD_WALL)
        if mode == "asset":
            if len(assets) > 1 and any(not np.allclose(m, next(iter(assets.values()))) for m in assets.values()):
                raise StageError("export.usd: fluid_units: asset with several USD assets placed differently; "
                                 "use fluid_units: scene")
            asset = next(iter(assets))
            stage = Usd.Stage.Open(str(asset), Usd.Stage.LoadNone)
            up, mpu = str(UsdGeom.GetStageUpAxis(stage)), UsdGeom.GetStageMetersPerUnit(stage)
            to_target = np.linalg.inv(assets[asset])
        else:
            up, mpu, to_target = scene.units.up_axis, scene.units.meters_per_unit, np.eye(4)
        metrics = dict(up_axis=up, meters_per_unit=mpu, fps=fps, frames=frames)

        sublayers: list[str] = []
        progress = ctx.progress("writing USD layers", len(frames) * (params.surface + params.particles) + 2)

        # far from the origin, point3f cannot hold the points: written relative to the walls' centre (formats.
        # local_origin; their prims translated back in double precision), else as they are
        origin = None
        if len(walls.vertices) and inputs["particles"].path is not None:
            box = ul.apply(to_target, walls.vertices)
            scale = ParticleMeta.load(inputs["particles"].path).spacing * ul.uniform_scale(to_target)
            origin = local_origin(box.min(axis=0), box.max(axis=0), scale)
        if params.surface:
            self._write_surface(out / "fluid_surface.usdc", inputs["surface"], frames, to_target, metrics, progress,
                                inputs["particles"] if params.surface_velocities else None, origin)
            sublayers.append("./fluid_surface.usdc")
        if params.particles:
            whole = frames == list(range(count))
            sublayers.append(self._write_particles(out, inputs["particles"], frames, whole, to_target, metrics,
                                                   progress, origin))
        if self._write_walls(out / "walls.usdc", walls, set(usd_walls), to_target, metrics, frames, origin):
            sublayers.append("./walls.usdc")
        references: list[tuple[str, np.ndarray, list[str | None], object]] = []
        offsets: dict[str, object] = {}  # sublayer -> its layer offset
        for asset, asset_to_scene in assets.items():
            rel = self._copy_asset(asset, out / "assets", ctx.log)
            asset_to_target = to_target @ asset_to_scene
            offset = _shot_offset(asset, scene.frames.fps)
            if np.allclose(asset_to_target, np.eye(4), atol=1e-9) and not _has_own_prims(asset):
                sublayers.append(f"./{rel}")  # prim paths kept exactly
                offsets[f"./{rel}"] = offset
            else:
                references.append((f"./{rel}", asset_to_target, _reference_roots(asset, asset_walls[asset]), offset))
        progress.advance()

        # the root: metrics, camera, sublayers (strongest first), assets that need a transform
        root = ul.new_stage(out / "scene.usda", **metrics)
        root.GetRootLayer().subLayerPaths = sublayers
        for i, layer in enumerate(sublayers):
            if offsets.get(layer) is not None:
                root.GetRootLayer().subLayerOffsets[i] = offsets[layer]
        for k, (rel, m, prims, offset) in enumerate(references):
            xf = UsdGeom.Xform.Define(root, f"/World/Asset_{k}")
            if not np.allclose(m, np.eye(4), atol=1e-9):  # an asset referenced only for its /World prims
                xf.AddTransformOp().Set(ul.to_gf_matrix(m))
            # the reference one level down: on Asset_k itself, our xformOpOrder replaced the asset root's
            # own (a set whose default prim is translated came in 3 cm off the simulated walls)
            used = {"Asset"}
            for j, prim in enumerate(prims):
                name = "Asset" if j == 0 else _safe_name(prim.lstrip("/"), used)
                refs = root.DefinePrim(f"/World/Asset_{k}/{name}").GetReferences()
                shift = offset if offset is not None else Sdf.LayerOffset()
                if prim is None:
                    refs.AddReference(rel, shift)
                else:
                    refs.AddReference(rel, prim, shift)
        ul.model_hierarchy(root, surface=params.surface, particles=params.particles, assets=len(references))
        cam = ctx.scene["camera"]
        aspect = params.camera_aspect or (cam.resolution[0] / cam.resolution[1] if cam.resolution else 16 / 9)

        def pose(seconds: float):  # the shot's camera at a time, in the layer's frame
            eye, target, up, view_angle = shot_camera(walls, scene.units, cam, ctx.resolve, "export.usd", seconds,
                                                      aspect, fluid_bounds(getattr(inputs.get("particles"), "path", None)))
            return (ul.apply(to_target, eye[None])[0], ul.apply(to_target, target[None])[0],
                    ul.apply_linear(to_target, up[None])[0], view_angle)

        first = pose(frames[0] / scene.frames.fps)
        camera = ul.define_camera(root, "/World/Camera", *first, aspect, mpu)
        eyes = [first[0]]
        if cam.usd is not None and usd_camera_moves(ctx.resolve(cam.usd), cam.prim, "export.usd"):
            # an animated shot camera is exported with its motion, sampled at the frames (as render draws them)
            poses = [(f, *pose(f / scene.frames.fps)) for f in frames]
            ul.animate_camera(camera, poses)
            eyes = [p[1] for p in poses]
        if len(walls.vertices):  # the walls' box (at rest), in the layer's frame
            lo, hi = walls.vertices.min(axis=0).astype(float), walls.vertices.max(axis=0).astype(float)
            box = ul.apply(to_target, np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                                for z in (lo[2], hi[2])]))
            ul.fit_clipping(camera, np.array(eyes), box.min(axis=0), box.max(axis=0))
        root.GetRootLayer().Save()
        progress.advance()

        errors, _ = ul.compliance_problems(out / "scene.usda")
        for line in errors:  # the tests hold this at zero; a user's asset may still bring its own
            ctx.log.warning("export.usd: USD compliance: %s", line)

        if params.fluid_layer_path and params.surface:
            target = out / params.fluid_layer_path  # inside the entry: published with it, atomically
            if target.exists():
                raise StageError(f"export.usd: fluid_layer_path {params.fluid_layer_path} is a file the export "
                                 f"itself writes; choose another name")
            target.parent.mkdir(parents=True, exist_ok=True)
            write_fx_layer(out / "fluid_surface.usdc", target, list(assets) if mode == "asset" else [])
            ctx.log.info("fluid layer written to usd/%s", params.fluid_layer_path)  # where it is published
        if params.usdz:
            # the zip entries carry their files' times: fixed (SOURCE_DATE_EPOCH, else 2000-01-01), the same
            # export gives the same bytes (a farm's checksums saw every re-export as a change)
            try:
                stamp = max(float(os.environ.get("SOURCE_DATE_EPOCH", "")), 315532800.0)  # zip times start in 1980
            except ValueError:
                stamp = 946684800.0
            # only while packaging: a published layer stamped 2000 never looked changed to a live session's
            # reload (usdview, Houdini and Omniverse go by modification time), which kept showing the old water
            files = [f for f in out.rglob("*") if f.is_file()]
            for f in files:
                os.utime(f, (stamp, stamp))
            packed = UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(out / "scene.usda")), str(out / "scene.usdz"))
            for f in files:
                os.utime(f)  # now: they were written by this run
            if not packed:
                raise StageError(f"export.usd: could not package {out / 'scene.usdz'}")

    # -- layers ----------------------------------------------------------------------------------------
    @staticmethod
    def _write_surface(path: Path, surface: Artifact, frames: list[int], m: np.ndarray, metrics: dict, progress,
                       particles: Artifact | None = None, origin: np.ndarray | None = None) -> None:
        """The surface layer; with ``particles``, each vertex's velocity as the particles' near it (within 2 l0,
        weighted (1 - r^2 / 4 l0^2)^3 over the 8 nearest; the nearest one's beyond), in units per second."""
        from pxr import UsdGeom

        stage = ul.new_stage(path, **metrics)
        UsdGeom.Scope.Define(stage, "/World/Fluid/Looks")
        material = ul.water_material(stage, "/World/Fluid/Looks/Water")
        UsdGeom.Xform.Define(stage, "/World/Fluid")
        mesh = ul.define_mesh(stage, "/World/Fluid/Surface")
        shift = local_frame(mesh, origin)
        flip = np.linalg.det(m[:3, :3]) < 0  # a mirroring placement reverses the winding
        for f in frames:
            folder = surface.frame(f)
            try:
                s = load_surface(folder, f)
            except FileNotFoundError:
                raise StageError(f"export.usd: {folder} has no surface for frame {f}") from None
            faces = s.faces[:, ::-1] if flip else s.faces
            velocities = None
            if particles is not None and particles.path is not None:
                velocities = ul.apply_linear(m, surface_velocities(s.vertices, particles.path, f))
            points = ul.apply(m, s.vertices)
            ul.set_mesh(mesh, points if origin is None else points - shift, faces,
                        ul.apply_normals(m, s.normals) if len(s.normals) else s.normals, f, velocities)
            progress.advance()
        ul.bind(mesh.GetPrim(), material)
        stage.GetRootLayer().Save()

    @staticmethod
    def _write_particles(out: Path, particles: Artifact, frames: list[int], whole: bool, m: np.ndarray,
                         metrics: dict, progress, origin: np.ndarray | None = None) -> str:
        folder = particles.path
        if folder is None:
            raise StageError("export.usd: the 'particles' artifact must be a whole-run folder")
        ready = Path(folder) / "particles.usdc"
        if ready.is_file() and ul.is_identity(m) and whole:
            # simulate's own layer, already in this frame; it holds every frame, so not for a --frames run
            # (its particles moved through the whole shot beside a surface held outside the selection)
            shutil.copyfile(ready, out / "particles.usdc")
            progress.advance(len(frames))
            return "./particles.usdc"
        try:
            meta = ParticleMeta.load(folder)
        except FileNotFoundError:
            raise StageError(f"export.usd: {folder} has no meta.json (not a particles artifact)") from None
        stage = ul.new_stage(out / "particles.usdc", **metrics)
        width = meta.spacing * ul.uniform_scale(m)

        def samples():
            for f in frames:
                try:
                    p = load_particle_frame(folder, f)
                except FileNotFoundError:
                    raise StageError(f"export.usd: {folder} has no particle frame {f}") from None
                yield f, {"x": ul.apply(m, p.x), "v": ul.apply_linear(m, p.v), "width": width, "id": p.id,
                          "rho": p.rho, "p": p.p}
                progress.advance()

        ul.write_points(stage, "/World/Particles", samples(), origin)
        stage.GetRootLayer().Save()
        return "./particles.usdc"

    @staticmethod
    def _write_walls(path: Path, walls: WallMesh, skip: set[int], m: np.ndarray, metrics: dict,
                     frames: list[int], origin: np.ndarray | None = None) -> bool:
        """The walls not from a USD asset; a moving wall as its rest mesh under a transform time-sampled
        at every exported frame (code f: the pose at f / fps) and at its keyframes between them. A wall from an
        animated USD asset carries its own animation in the asset (its time codes scaled to ours by their
        timeCodesPerSecond)."""
        from pxr import UsdGeom

        motions = dict(walls.motions())
        to_source = np.linalg.inv(m)

        keep = [i for i in range(len(walls.walls)) if i not in skip and np.any(walls.wall_id == i)]
        if not keep:
            return False
        stage = ul.new_stage(path, **metrics)
        UsdGeom.Scope.Define(stage, "/World/Walls")
        used: set[str] = set()
        for i in keep:
            faces = walls.faces[walls.wall_id == i]
            idx, inverse = np.unique(faces.ravel(), return_inverse=True)
            mesh = ul.define_mesh(stage, f"/World/Walls/{_safe_name(walls.walls[i].get('name', 'wall'), used)}")
            local = inverse.reshape(-1, 3)
            if np.linalg.det(m[:3, :3]) < 0:
                local = local[:, ::-1]
            shift = local_frame(mesh, origin) if i not in motions else np.zeros(3)  # a moving wall: its own ops
            ul.set_mesh(mesh, ul.apply(m, walls.vertices[idx]) - shift, local, None)
            if i in motions:  # the rest pose above, moved by the wall's motion seen in the written frame
                # at every frame and at the motion's own keys between them: USD interpolates between samples, and
                # across a key inside a frame it cut the corner (0.43 l0 off the path the water saw at a half frame)
                fps = metrics["fps"]
                keys = [float(t) * fps for t in motions[i].times if frames[0] < float(t) * fps < frames[-1]]
                codes = sorted(set(map(float, frames)) | set(keys))
                ul.animate_rigidly(mesh, [(c, m @ motions[i].matrix(c / fps) @ to_source) for c in codes],
                                   ul.apply(m, np.asarray(motions[i].pivot, float)[None])[0])
                # the extent bounds the points as authored (the rest pose): USD applies the transform to it
            source = str(walls.walls[i].get("source", ""))
            mesh.GetPrim().SetCustomDataByKey("source", source)
            if source.startswith("builtin:"):  # a collider made for the simulation, not a set piece: drawn only
                mesh.CreatePurposeAttr(UsdGeom.Tokens.guide)  # where guides are asked for (it hid the water)
        stage.GetRootLayer().Save()
        return True

    @staticmethod
    def _copy_asset(asset: Path, dest: Path, log=None) -> str:
        """Copy an asset and every local file it depends on, keeping their relative layout from the folder
        they all share: a set in sets/ that references ../geo/ keeps that reference (copied from the asset's
        own folder only, the geometry was left behind and the set came in empty)."""
        from pxr import Sdf, UsdUtils

        layers, files, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(asset)))
        paths = {asset.resolve()} | {Path(layer.realPath).resolve() for layer in layers if layer.realPath}
        paths |= {Path(f).resolve() for f in files}
        base = Path(os.path.commonpath([str(p.parent) for p in paths]))
        for p in paths:
            target = dest / p.relative_to(base)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(p, target)
        if unresolved and log is not None:
            log.warning("export.usd: %s refers to %d file(s) that cannot be found (first: %s); the copy refers to "
                        "them too", asset.name, len(unresolved), unresolved[0])
        return f"assets/{asset.resolve().relative_to(base)}"
