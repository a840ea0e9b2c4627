"""A new USD layer with the stage metrics every layer of ours carries (STYLE.md pattern 13)."""
from __future__ import annotations

from pathlib import Path

from pxr import Usd, UsdGeom


def shot_start(stage: Usd.Stage) -> float:
    """The time code a file's shot starts at: its startTimeCode (studios use 1001), 0 when it has none."""
    return stage.GetStartTimeCode() if stage.HasAuthoredMetadata("startTimeCode") else 0.0


def new_stage(path: Path, *, up_axis: str, meters_per_unit: float, fps: float, count: int,
              root: str = "World") -> Usd.Stage:
    """A new layer with the stage metrics every layer of ours carries, and its default prim."""
    path = Path(path)
    if path.exists():
        path.unlink()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(max(int(count) - 1, 0))
    world = UsdGeom.Xform.Define(stage, f"/{root}")
    stage.SetDefaultPrim(world.GetPrim())
    return stage
