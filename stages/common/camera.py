"""The shot's camera (the scene's ``camera`` section), shared by render and export so the frames and
the USD camera prim show the same view: a UsdGeom.Camera from a file, or automatic framing on the
walls, with position / focal_point / up from the config taking precedence."""
from __future__ import annotations

import functools

import math
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.stage import StageError

from .formats import WallMesh


def auto_camera(lo: np.ndarray, hi: np.ndarray, up_axis: str, view_angle: float,
                aspect: float = 16 / 9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 3/4 view from the front-right and somewhat above that fits the box [lo, hi] in a frame ``aspect``
    wide per unit of height: ``view_angle`` is the vertical angle, so a portrait frame (aspect below 1)
    fits the box in its narrower horizontal angle (fitted vertically, a 480 x 640 frame cut the tank's
    sides off)."""
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    if up_axis == "Z":
        direction, up = np.array([0.55, -1.0, 0.6]), np.array([0.0, 0.0, 1.0])
    else:  # Y-up: the same view with (x, y, z)_Z-up -> (x, z, -y)
        direction, up = np.array([0.55, 0.6, 1.0]), np.array([0.0, 1.0, 0.0])
    direction /= np.linalg.norm(direction)
    half = math.radians(view_angle) / 2
    if aspect < 1.0:
        half = math.atan(aspect * math.tan(half))  # the horizontal half-angle
    distance = 1.05 * radius / math.sin(half)
    return centre + distance * direction, centre, up


def _camera_prim(path: Path, prim: str | None, who: str):
    from pxr import Usd, UsdGeom

    if not path.is_file():
        raise StageError(f"{who}: camera.usd: {path} not found")
    from .usd_stage import open_stage

    stage = open_stage(path, f"{who}: camera.usd: ")
    if prim:
        cam_prim = stage.GetPrimAtPath(prim)
        if not cam_prim or not cam_prim.IsA(UsdGeom.Camera):
            raise StageError(f"{who}: camera.prim: {prim} is not a UsdGeom.Camera in {path}")
    else:
        cam_prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)), None)
        if cam_prim is None:
            raise StageError(f"{who}: camera.usd: {path} has no UsdGeom.Camera prim")
    return stage, cam_prim


def _time_code(stage, seconds: float):
    """The file's time code at ``seconds`` into the shot: the shot starts at the file's startTimeCode (0 when it
    has none) and runs at its timeCodesPerSecond."""
    from pxr import Usd

    from .usd_stage import shot_start

    return Usd.TimeCode(shot_start(stage) + seconds * stage.GetTimeCodesPerSecond())


def usd_camera_moves(path: Path, prim: str | None, who: str = "camera") -> bool:
    """Whether the camera's transform or lens is animated (time samples on it or on an ancestor's xform)."""
    from pxr import UsdGeom

    _, cam_prim = _camera_prim(path, prim, who)
    p = cam_prim
    while p and not p.IsPseudoRoot():
        if p.IsA(UsdGeom.Xformable) and UsdGeom.Xformable(p).TransformMightBeTimeVarying():
            return True
        p = p.GetParent()
    return any(a.ValueMightBeTimeVarying() for a in cam_prim.GetAttributes())


def usd_camera(path: Path, prim: str | None, up_axis: str, meters_per_unit: float, who: str = "camera",
               seconds: float = 0.0):
    """(eye, focal point, up, vertical view angle) of a UsdGeom.Camera at ``seconds`` into the shot, in the
    scene's units and up axis. An animated camera is read at that time (read at the default time, a camera
    with only time samples sat at the origin)."""
    from pxr import UsdGeom

    from .usd_stage import stage_units

    stage, cam_prim = _camera_prim(path, prim, who)
    cam = UsdGeom.Camera(cam_prim).GetCamera(_time_code(stage, seconds))
    frustum = cam.frustum
    eye = np.array(frustum.GetPosition())
    look = np.array(frustum.ComputeViewDirection())
    up = np.array(frustum.ComputeUpVector())
    view_angle = float(cam.GetFieldOfView(cam.FOVVertical))
    # the file's units and up axis -> the scene's (Y-up -> Z-up is +90 degrees about X)
    file_mpu, file_up = stage_units(stage, f"{who}: camera.usd: {path}")
    scale = file_mpu / meters_per_unit
    rot = np.eye(3)
    if file_up != up_axis:
        rot = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)
        rot = rot if (file_up, up_axis) == ("Y", "Z") else rot.T
    eye = rot @ eye * scale
    return eye, eye + rot @ look, rot @ up, view_angle


def camera_files(ctx) -> list[Path]:
    """The layers a ``camera.usd`` composes (the file itself the engine finds): render's and export's
    ``external_files``, so an edit to a sublayer that moves the camera is a new key."""
    from stages.mesh_import.usd_import import usd_dependencies

    cam = ctx.scene["camera"]
    return usd_dependencies(ctx.resolve(cam.usd)) if cam.usd is not None else []


@functools.lru_cache(maxsize=8)
def fluid_bounds(particles: Path | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The box of the fluid at the shot's start (frame 0 of a particle run, half a spacing around the
    particles), for the automatic camera; None without one."""
    from stages.common.formats import ParticleMeta, load_particle_frame

    if particles is None:
        return None
    try:
        meta, x = ParticleMeta.load(particles), load_particle_frame(particles, 0).x
    except (FileNotFoundError, OSError):
        return None
    if len(x) == 0:
        return None
    return x.min(axis=0) - 0.5 * meta.spacing, x.max(axis=0) + 0.5 * meta.spacing


def shot_camera(walls: WallMesh, units, cam, resolve: Callable[[str], Path], who: str, seconds: float = 0.0,
                aspect: float = 16 / 9, fluid: tuple[np.ndarray, np.ndarray] | None = None):
    """(eye, focal point, up, vertical view angle) in scene units for the scene's ``cam``
    (pipeline.scene.Camera) at ``seconds`` into the shot (a USD camera may be animated), for an image
    ``aspect`` wide per unit of height; ``who`` names the stage in errors. The automatic camera frames the
    walls and ``fluid`` (fluid_bounds: a column standing above a floor plate was cut off at the frame's top)."""
    view_angle = cam.view_angle
    if cam.usd is not None:
        eye, centre, up, view_angle = usd_camera(resolve(cam.usd), cam.prim, units.up_axis, units.meters_per_unit, who,
                                                 seconds)
    else:
        if len(walls.vertices):
            lo, hi = walls.vertices.min(axis=0), walls.vertices.max(axis=0)
            if fluid is not None:
                lo, hi = np.minimum(lo, fluid[0]), np.maximum(hi, fluid[1])
        elif fluid is not None:
            lo, hi = np.asarray(fluid[0], float), np.asarray(fluid[1], float)
        else:
            lo, hi = np.full(3, -1.0 / units.meters_per_unit), np.full(3, 1.0 / units.meters_per_unit)  # +-1 m
        eye, centre, up = auto_camera(lo, hi, units.up_axis, view_angle, aspect)
    if cam.focal_point is not None:
        centre = np.asarray(cam.focal_point, float)
    if cam.position is not None:
        eye = np.asarray(cam.position, float)
    if cam.up is not None:
        up = np.asarray(cam.up, float)
    eye, centre, up = np.asarray(eye, float), np.asarray(centre, float), np.asarray(up, float)
    view = centre - eye
    if not np.linalg.norm(view) > 0:
        raise StageError(f"{who}: camera.position {tuple(eye.tolist())} is the focal point: the camera looks nowhere; "
                         "move camera.position or camera.focal_point")
    if np.linalg.norm(np.cross(view, up)) <= 1e-6 * np.linalg.norm(view) * np.linalg.norm(up):
        if cam.up is not None:
            raise StageError(f"{who}: camera.up is along the view direction (camera.position -> focal point): give an "
                             "up across it")
        up = across(units.up_axis)  # looking straight down (or up) the up axis: the default roll is undefined
    return eye, centre, up, view_angle


def across(up_axis: str) -> np.ndarray:
    """An up for a camera looking along the scene's up axis: the horizontal axis that points away from the
    viewer in the automatic framing (+Y for Z-up, -Z for Y-up), so a plan view keeps the other views' layout."""
    return np.array([0.0, 1.0, 0.0]) if up_axis == "Z" else np.array([0.0, 0.0, -1.0])
