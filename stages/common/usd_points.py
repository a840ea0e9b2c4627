"""Write particle frames as a time-sampled UsdGeom.Points layer (positions, velocities per second,
widths = particle spacing, ids, density and pressure primvars, extent per sample)."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from .usd_stage import new_stage


def write_points_layer(path: Path, frames: Iterable[tuple[int, object]], *, spacing: float, up_axis: str,
                       meters_per_unit: float, fps: float, count: int, prim: str = "/World/Particles",
                       origin: np.ndarray | None = None) -> Path:
    """``frames`` yields (time code, ParticleFrame). Stage metadata: upAxis, metersPerUnit,
    timeCodesPerSecond, start/end time codes, defaultPrim /World. ``origin`` (formats.local_origin, far from
    the world's origin): the points relative to it, under a double-precision translate by it."""
    path = Path(path)
    stage = new_stage(path, up_axis=up_axis, meters_per_unit=meters_per_unit, fps=fps, count=count)
    pts = UsdGeom.Points.Define(stage, prim)
    shift = local_frame(pts, origin)
    api = UsdGeom.PrimvarsAPI(pts)
    rho_pv = api.CreatePrimvar("density", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    p_pv = api.CreatePrimvar("pressure", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    for t, f in frames:
        x = np.ascontiguousarray(np.asarray(f.x, np.float64).reshape(-1, 3) - shift, np.float32)
        tc = Usd.TimeCode(float(t))
        pts.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(x), tc)
        pts.GetVelocitiesAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(f.v, np.float32).reshape(-1, 3)), tc)
        pts.GetWidthsAttr().Set(Vt.FloatArray.FromNumpy(np.full(len(x), spacing, np.float32)), tc)
        pts.GetIdsAttr().Set(Vt.Int64Array.FromNumpy(np.asarray(f.id, np.int64)), tc)
        rho_pv.Set(Vt.FloatArray.FromNumpy(np.asarray(f.rho, np.float32)), tc)
        p_pv.Set(Vt.FloatArray.FromNumpy(np.asarray(f.p, np.float32)), tc)
        if len(x):
            lo = x.min(axis=0) - 0.5 * spacing
            hi = x.max(axis=0) + 0.5 * spacing
            pts.GetExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), tc)
        else:
            pts.GetExtentAttr().Set(empty_extent(), tc)
    stage.GetRootLayer().Save()
    return path


def local_frame(prim, origin) -> np.ndarray:
    """Put ``prim`` (Xformable) at ``origin`` with a double-precision translate op and return what its points
    subtract (zeros when ``origin`` is None: no op, points as they are)."""
    if origin is None:
        return np.zeros(3)
    origin = np.asarray(origin, np.float64)
    UsdGeom.Xformable(prim).AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, origin)))
    return origin


def empty_extent():
    """USD's extent of no points: the empty range (+max, -max), which bounding-box caches skip; a zero box at the
    origin (as written before) pulled a drained frame's bounds to the origin."""
    from pxr import UsdGeom, Vt

    return UsdGeom.PointBased.ComputeExtent(Vt.Vec3fArray())
