"""A new USD layer with the stage metrics every layer of ours carries (STYLE.md pattern 13)."""
from __future__ import annotations

import re
from pathlib import Path

from pxr import Usd, UsdGeom


def usd_error(e: Exception) -> str:
    """The first cause in a pxr error, on one line without C++ namespaces: "bad.usda:4:1: parse error
    matching TupleValueClose at '}' in </M.points>" rather than the last of its stacked messages."""
    for chunk in str(e).split("Error in "):
        m = re.search(r" : '(.*)'\s*$", chunk, re.S)
        if m:
            text = re.sub(r"pxrInternal_v\w+?__pxrReserved__::|Sdf_TextFileFormatParser::", "", m.group(1))
            return " ".join(text.split())[:300]
    return " ".join(str(e).split())[:300] or type(e).__name__


def open_stage(path: Path, who: str = "", diagnostics: list[str] | None = None) -> Usd.Stage:
    """The USD stage at ``path``, or a StageError naming the file and the parser's first complaint. With
    ``diagnostics``, USD's warnings while composing go there (one line each) instead of to stderr."""
    from pipeline.stage import StageError
    from pxr import UsdUtils

    # while a delegate exists Tf prints nothing: the caller says what matters in one line
    delegate = UsdUtils.CoalescingDiagnosticDelegate() if diagnostics is not None else None
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as e:  # pxr raises Tf.ErrorException with stacked C++ messages
        raise StageError(f"{who}{path}: cannot open as USD ({usd_error(e)})") from None
    finally:
        if delegate is not None:
            diagnostics += [re.sub(r" \(instantiating stage on stage .*\)$", "", " ".join(d.commentary.split()))
                            for d in delegate.TakeUncoalescedDiagnostics()]
            del delegate
    if stage is None:
        raise StageError(f"{who}{path}: cannot open as USD")
    return stage


_ARC = re.compile(r"@([^@]*)@ for (reference|payload) introduced by @([^@]*)@<([^>]*)>")
_SUBLAYER = re.compile(r"sublayer @([^@]*)@ of layer @([^@]*)@")


def unresolved_assets(stage: Usd.Stage) -> list[tuple[str, str]]:
    """(prim path, '' for a sublayer; one line: the layer, the arc and the asset) of every reference, payload or
    sublayer the stage could not open: USD composes on without it and only warns (a wall left out)."""
    from pxr import Pcp

    out = []
    for e in stage.GetCompositionErrors():
        if not isinstance(e, (Pcp.ErrorInvalidAssetPath, Pcp.ErrorInvalidSublayerPath)):
            continue
        text = " ".join(str(e).split())
        m, sub = _ARC.search(text), _SUBLAYER.search(text)
        if m:
            asset, arc, layer, prim = m.groups()
            out.append((prim, f"layer {layer}: the {arc} of <{prim}>, {asset}, cannot be opened (missing file?)"))
        elif sub:
            out.append(("", f"layer {sub.group(2)}: sublayer {sub.group(1)} cannot be opened (missing file?)"))
        else:
            out.append((str(getattr(e.rootSite, "path", "") or ""), text[:300]))
    return out


def stage_units(stage: Usd.Stage, where: str) -> tuple[float, str]:
    """The stage's (metersPerUnit, upAxis), or a StageError naming ``where``: USD allows only Y or Z up
    (X was turned as if Z up were Y) and a unit must be a positive length."""
    import math

    from pipeline.stage import StageError

    mpu, up = float(UsdGeom.GetStageMetersPerUnit(stage)), str(UsdGeom.GetStageUpAxis(stage))
    if up not in ("Y", "Z"):
        raise StageError(f"{where}: upAxis {up!r} is not Y or Z, the two USD allows")
    if not (math.isfinite(mpu) and mpu > 0):
        raise StageError(f"{where}: metersPerUnit {mpu} must be a positive number")
    return mpu, up


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
