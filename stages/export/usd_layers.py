"""Small helpers that author the export's per-department USD layers (walls, particles, fluid surface,
camera, water material) and the frame conversions between a scene and a studio asset.

Frames: a 4x4 matrix ``M`` maps column vectors, p' = M @ [p, 1]. USD stores matrices for row vectors,
so an xformOp gets ``M.T``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from stages.common import usd_stage
from stages.common.meshes import bounds
from stages.common.usd_points import empty_extent

# Y-up -> Z-up is +90 degrees about X: (x, y, z) -> (x, -z, y); its inverse takes Z-up to Y-up
_Y_TO_Z = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)


def axis_change(src_up: str, dst_up: str) -> np.ndarray:
    """3x3 rotation taking coordinates in a ``src_up`` frame to a ``dst_up`` frame."""
    if src_up == dst_up:
        return np.eye(3)
    return _Y_TO_Z if (src_up, dst_up) == ("Y", "Z") else _Y_TO_Z.T


def affine(linear: np.ndarray, translate: Iterable[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = list(translate)
    return m


def is_identity(m: np.ndarray) -> bool:
    """The scene is already in the layer's units and up axis (the common case): nothing to transform. A
    60-frame surface of 145k vertices spent 1.8 s of a 3-9 s export transforming by the identity."""
    return np.array_equal(m, np.eye(4))


def apply(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    if is_identity(m):
        return np.asarray(points)
    return np.asarray(points, float) @ m[:3, :3].T + m[:3, 3]


def apply_linear(m: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    if is_identity(m):
        return np.asarray(vectors)
    return np.asarray(vectors, float) @ m[:3, :3].T


def apply_normals(m: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unit normals after the placement ``m`` (the surface stages write them unit already)."""
    if is_identity(m):
        return np.asarray(normals)
    n = np.asarray(normals, float) @ np.linalg.inv(m[:3, :3])  # inverse transpose for normals
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def uniform_scale(m: np.ndarray) -> float:
    return float(abs(np.linalg.det(m[:3, :3])) ** (1.0 / 3.0))


def to_gf_matrix(m: np.ndarray) -> Gf.Matrix4d:
    return Gf.Matrix4d(*[float(v) for v in np.asarray(m, float).T.ravel()])


# -- layers ------------------------------------------------------------------------------------


def new_stage(path: Path, *, up_axis: str, meters_per_unit: float, fps: float, frames: list[int]) -> Usd.Stage:
    """A layer with our stage metrics whose time range is the exported frames, first..last selected
    (a --frames 1:4 run said 0..5, so a viewer played frames no layer had)."""
    stage = usd_stage.new_stage(path, up_axis=up_axis, meters_per_unit=meters_per_unit, fps=fps, count=1)
    if frames:
        stage.SetStartTimeCode(min(frames))
        stage.SetEndTimeCode(max(frames))
    return stage


def extent_of(points: np.ndarray) -> Vt.Vec3fArray:
    if len(points) == 0:
        return empty_extent()
    return Vt.Vec3fArray.FromNumpy(np.stack(bounds(points)).astype(np.float32))


def vec3f(a: np.ndarray) -> Vt.Vec3fArray:
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, np.float32).reshape(-1, 3))


def define_mesh(stage: Usd.Stage, path: str) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # polygons as they are, not a limit surface
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    return mesh


def set_mesh(mesh: UsdGeom.Mesh, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None,
             time=Usd.TimeCode.Default(), velocities: np.ndarray | None = None) -> None:
    """Author one sample of a triangle mesh (topology may differ between samples), with its points'
    velocities (units per second) when given."""
    faces = np.ascontiguousarray(faces, np.int32).reshape(-1, 3)
    mesh.GetPointsAttr().Set(vec3f(vertices), time)
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)), time)
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(faces.ravel()), time)
    if normals is not None:
        mesh.GetNormalsAttr().Set(vec3f(normals), time)
    if velocities is not None:
        mesh.GetVelocitiesAttr().Set(vec3f(velocities), time)
    mesh.GetExtentAttr().Set(extent_of(np.asarray(vertices, np.float32)), time)


def water_material(stage: Usd.Stage, path: str) -> UsdShade.Material:
    """A UsdPreviewSurface water: light blue, glossy, partly transparent, ior 1.33."""
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.45, 0.70, 0.95))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.05)
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.6)
    shader.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.33)
    shader.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def bind(prim: Usd.Prim, material: UsdShade.Material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def define_camera(stage: Usd.Stage, path: str, eye: np.ndarray, target: np.ndarray, up: np.ndarray,
                  view_angle: float, aspect: float, meters_per_unit: float) -> UsdGeom.Camera:
    """A camera at ``eye`` looking at ``target`` with a vertical field of view ``view_angle`` (degrees).

    UsdGeomCamera measures lens and filmback in tenths of a scene unit (millimetres only on a
    centimetre stage), so the 36 mm film back is authored as 0.036 m / (0.1 ``meters_per_unit`` m)."""
    camera = UsdGeom.Camera.Define(stage, path)
    view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*map(float, eye)), Gf.Vec3d(*map(float, target)),
                                   Gf.Vec3d(*map(float, up)))
    camera.AddTransformOp().Set(view.GetInverse())
    horizontal = 0.36 / meters_per_unit  # a 35 mm still frame (36 mm wide) in tenths of a scene unit
    vertical = horizontal / aspect
    camera.CreateHorizontalApertureAttr(horizontal)
    camera.CreateVerticalApertureAttr(vertical)
    camera.CreateFocalLengthAttr(vertical / (2 * math.tan(math.radians(view_angle) / 2)))
    distance = float(np.linalg.norm(np.asarray(eye) - np.asarray(target)))
    distance = distance or 1.0  # eye on its target (a config's mistake): any positive range
    # relative to the distance, so the same in any units (an absolute floor would be metres in one scene
    # and millimetres in another)
    camera.CreateClippingRangeAttr(Gf.Vec2f(0.01 * distance, 100.0 * distance))
    camera.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    return camera


def fit_clipping(camera: UsdGeom.Camera, eyes: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """Near and far planes around the scene's box [lo, hi] (padded by half its diagonal: splashes leave the
    walls' box) as seen from every eye of the shot: a range relative to the eye's distance to its target
    clipped the water in front of a camera aimed past it (71 % of a surface in a user's sweep)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pad = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    lo, hi = lo - pad, hi + pad
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    eyes = np.atleast_2d(np.asarray(eyes, float))
    nearest = min(float(np.linalg.norm(np.maximum(np.maximum(lo - e, e - hi), 0.0))) for e in eyes)
    farthest = max(float(np.linalg.norm(corners - e, axis=1).max()) for e in eyes)
    camera.GetClippingRangeAttr().Set(Gf.Vec2f(max(0.5 * nearest, 1e-4 * farthest), 2.0 * farthest))


def animate_rigidly(prim: UsdGeom.Xformable, poses: Iterable[tuple[float, np.ndarray]], pivot) -> None:
    """Time samples of rigid poses (time code, 4x4 column-vector matrix) as translate, pivot and orient ops
    about the motion's ``pivot``: USD interpolates them rigidly between samples, the wall turning about its
    pivot (a matrix op is interpolated entry by entry: a wall turning 13 degrees a frame shrank 1.2 % at
    mid-frame; a translate about the origin swung the wall 0.05 l0 off its path)."""
    pivot = np.asarray(pivot, float)
    translate = prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
    at_pivot = prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble, "pivot")
    orient = prim.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
    prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble, "pivot", isInverseOp=True)
    at_pivot.Set(Gf.Vec3d(*map(float, pivot)))
    last = None
    for code, matrix in poses:
        matrix = np.asarray(matrix, float)
        q = Gf.Matrix4d(matrix.T.tolist()).ExtractRotationQuat()
        if last is not None and Gf.Dot(q, last) < 0:  # the same turn, on the short arc from the last sample
            q = -q
        last = q
        moved = matrix[:3, :3] @ pivot + matrix[:3, 3]  # where the pivot is at this sample
        translate.Set(Gf.Vec3d(*map(float, moved - pivot)), code)
        orient.Set(q, code)


def model_hierarchy(root: Usd.Stage, *, surface: bool, particles: bool, assets: int) -> None:
    """Kinds for the model hierarchy (what outliners and 'pick models' walk): /World an assembly, the fluid and
    the particles components, the referenced assets' holders groups; the particles drawn as a guide beside a
    surface (a render would show them inside the water)."""
    from pxr import Kind

    Usd.ModelAPI(root.OverridePrim("/World")).SetKind(Kind.Tokens.assembly)
    if surface:
        Usd.ModelAPI(root.OverridePrim("/World/Fluid")).SetKind(Kind.Tokens.component)
    if particles:
        prim = root.OverridePrim("/World/Particles")
        Usd.ModelAPI(prim).SetKind(Kind.Tokens.component)
        if surface:
            UsdGeom.Imageable(prim).CreatePurposeAttr(UsdGeom.Tokens.guide)
    for k in range(assets):
        Usd.ModelAPI(root.GetPrimAtPath(f"/World/Asset_{k}")).SetKind(Kind.Tokens.group)


def animate_camera(camera: UsdGeom.Camera, poses: Iterable[tuple[float, np.ndarray, np.ndarray, np.ndarray, float]]) -> None:
    """Time samples of a camera ``define_camera`` made: (time code, eye, target, up, vertical view angle) each; the
    film back stays, the focal length follows the view angle."""
    op = camera.GetOrderedXformOps()[0]
    vertical = camera.GetVerticalApertureAttr().Get()
    for code, eye, target, up, view_angle in poses:
        view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*map(float, eye)), Gf.Vec3d(*map(float, target)),
                                       Gf.Vec3d(*map(float, up)))
        op.Set(view.GetInverse(), Usd.TimeCode(code))
        camera.GetFocalLengthAttr().Set(vertical / (2 * math.tan(math.radians(view_angle) / 2)), Usd.TimeCode(code))


def write_points(stage: Usd.Stage, path: str, frames: Iterable[tuple[int, dict]],
                 origin: np.ndarray | None = None) -> UsdGeom.Points:
    """Time-sampled points: positions, velocities (units/s), widths (diameters), ids, density and
    pressure primvars, extent per sample. ``frames`` yields (time code, {x, v, width, id, rho, p}).
    ``origin``: the points relative to it, under a double-precision translate (usd_points.local_frame)."""
    from stages.common.usd_points import local_frame

    points = UsdGeom.Points.Define(stage, path)
    shift = local_frame(points, origin)
    pv = UsdGeom.PrimvarsAPI(points)
    rho = pv.CreatePrimvar("density", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    pressure = pv.CreatePrimvar("pressure", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    for t, f in frames:
        x = np.asarray(np.asarray(f["x"], np.float64) - shift, np.float32)
        points.GetPointsAttr().Set(vec3f(x), t)
        points.GetVelocitiesAttr().Set(vec3f(f["v"]), t)
        points.GetWidthsAttr().Set(Vt.FloatArray.FromNumpy(np.full(len(x), f["width"], np.float32)), t)
        points.GetIdsAttr().Set(Vt.Int64Array.FromNumpy(np.asarray(f["id"], np.int64)), t)
        rho.Set(Vt.FloatArray.FromNumpy(np.asarray(f["rho"], np.float32)), t)
        pressure.Set(Vt.FloatArray.FromNumpy(np.asarray(f["p"], np.float32)), t)
        extent = np.asarray(extent_of(x), np.float32)
        pad = 0.5 * f["width"]
        points.GetExtentAttr().Set(vec3f(extent + np.array([[-pad], [pad]], np.float32)), t)
    return points


def compliance_problems(path: Path) -> tuple[list[str], list[str]]:
    """(errors, warnings) of usd-core's checks on the layer at ``path``: UsdUtils.ComplianceChecker
    where usd-core still ships it (< 25.x), else every registered UsdValidation validator (its
    successor, what ``usdchecker`` runs)."""
    from pxr import UsdUtils

    if hasattr(UsdUtils, "ComplianceChecker"):
        checker = UsdUtils.ComplianceChecker(arkit=False, skipARKitRootLayerCheck=False, rootPackageOnly=False,
                                             skipVariants=False, verbose=False)
        checker.CheckCompliance(str(path))
        return list(checker.GetErrors()) + list(checker.GetFailedChecks()), list(checker.GetWarnings())
    from pxr import UsdValidation

    registry = UsdValidation.ValidationRegistry()
    validators = registry.GetOrLoadValidatorsByName([m.name for m in registry.GetAllValidatorMetadata()])
    stage = Usd.Stage.Open(str(path))
    errors, warnings = [], []
    for e in UsdValidation.ValidationContext(validators).Validate(stage):
        line = f"{e.GetIdentifier()}: {e.GetMessage()}"
        (errors if e.GetType() == UsdValidation.ValidationErrorType.Error else warnings).append(line)
    return errors, warnings
