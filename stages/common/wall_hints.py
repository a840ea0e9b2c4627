"""Advice for the refusals a wall's size or side explains: the walls' boxes (sdf_bake writes them beside the
field, WALL_BOXES_FILE) against the emitters' for "no particles in the fluid region", and against the fluid
spacing for "would need about 1 PB" (a model in millimetres in a metre scene)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

WALL_BOXES_FILE = "wall_boxes.json"
# walls this many times larger (or smaller) than the emitters, or this many spacings across when the size
# is refused: likely a model in other units than the scene's
UNITS_RATIO = 100.0
SPACINGS_ACROSS = 2000.0
_UNITS = ("if the model is in other units than the scene's, set meters_per_unit on its walls[] entry (the metres "
          "in one of its units: 0.001 for millimetres, 0.01 for centimetres, 1 for metres)")


def write_wall_boxes(folder: Path, walls: list[dict], vertices: np.ndarray, wall_id: np.ndarray,
                     faces: np.ndarray) -> None:
    """Each wall's name, source, fluid side and box (scene units), for simulate's messages."""
    out = []
    for i, w in enumerate(walls):
        used = np.unique(faces[wall_id == i])
        if not len(used):
            continue
        v = vertices[used]
        out.append({"index": i, "source": w.get("source", w["name"]), "fluid": w["fluid"],
                    "min": v.min(axis=0).tolist(), "max": v.max(axis=0).tolist()})
    (Path(folder) / WALL_BOXES_FILE).write_text(json.dumps(out, indent=1))


def read_wall_boxes(folder: Path) -> list[dict] | None:
    """What write_wall_boxes wrote, or None (a field cached before it was written)."""
    try:
        return json.loads((Path(folder) / WALL_BOXES_FILE).read_text())
    except (OSError, ValueError):
        return None


def _dims(lo, hi) -> str:
    return " x ".join(f"{float(h - l):.3g}" for l, h in zip(lo, hi))


def spacing_hint(walls_lo, walls_hi, spacing: float) -> str:
    """"; the walls: 400 x 400 x 300 scene units, 20,000 spacings across: ..." when the walls are more than
    SPACINGS_ACROSS fluid spacings across (a memory refusal: sdf_bake is not keyed on the emitters), else ""."""
    w = float(np.max(np.asarray(walls_hi, float) - np.asarray(walls_lo, float)))
    if not spacing > 0 or w / spacing <= SPACINGS_ACROSS:
        return ""
    return f"; the walls: {_dims(walls_lo, walls_hi)} scene units, {w / spacing:,.0f} spacings across: {_UNITS}"


def units_hint(walls_lo, walls_hi, emit_lo, emit_hi, who_walls: str = "the walls") -> str:
    """"; the walls: 400 x 400 x 300 scene units, 2000 times the emitters' 0.2 x 0.2 x 0.1: ..." when one is
    UNITS_RATIO times the other's size, else ""."""
    w = float(np.max(np.asarray(walls_hi, float) - np.asarray(walls_lo, float)))
    e = float(np.max(np.asarray(emit_hi, float) - np.asarray(emit_lo, float)))
    if w <= 0 or e <= 0 or 1.0 / UNITS_RATIO < w / e < UNITS_RATIO:
        return ""
    ratio = w / e
    how = f"{ratio:.3g} times" if ratio > 1 else f"1/{1 / ratio:.3g} of"
    return f"; {who_walls}: {_dims(walls_lo, walls_hi)} scene units, {how} the emitters' {_dims(emit_lo, emit_hi)}: {_UNITS}"


def no_fluid_hint(boxes: list[dict] | None, points: np.ndarray) -> str:
    """Why emitted ``points`` (scene units) all lie in walls: the walls whose solid holds them (an obstacle's
    box around them, or a container's box beside them) and what to change; plus units_hint. The old advice
    ("a closed wall mesh is a solid ... unless ... fluid: inside") when the boxes are not known."""
    generic = ("; a closed wall mesh is a solid with the fluid outside unless its walls[] entry says fluid: inside")
    if not boxes or not len(points):
        return generic
    lo, hi = points.min(axis=0), points.max(axis=0)
    parts = []
    for b in boxes:
        blo, bhi = np.asarray(b["min"], float), np.asarray(b["max"], float)
        inside = np.all((points >= blo) & (points <= bhi), axis=1).mean()
        name = f"wall {b['index']} ({Path(str(b['source'])).name}, fluid: {b['fluid']})"
        if b["fluid"] == "inside" and inside < 0.5:
            parts.append(f"{name} is a container and the emitters lie outside its box ({box_text(blo, bhi)}): "
                         "move them into it")
        elif b["fluid"] == "inside" and not str(b["source"]).startswith("builtin:"):
            # the emitters in its box and still all in walls: the mesh's closed volume is its material, as a
            # thick-walled tank's is (the old advice told such a wall to say fluid: inside, which it did)
            parts.append(f"{name} holds the fluid inside its closed mesh, and the emitters in its box are not in "
                         "that volume: if it is a thick-walled tank (the water in a cavity outside its material), "
                         "remove fluid: inside from its walls[] entry")
        elif b["fluid"] == "outside" and inside >= 0.5:
            parts.append(f"{name} is a solid around the emitters: set fluid: inside on its walls[] entry if it is "
                         "a container, or move the emitters out of it")
        elif b["fluid"] == "both" and inside >= 0.5:
            parts.append(f"{name} is a shell through the emitters")
    walls_lo = np.min([b["min"] for b in boxes], axis=0)
    walls_hi = np.max([b["max"] for b in boxes], axis=0)
    units = units_hint(walls_lo, walls_hi, lo, hi)
    if not parts and not units:
        return generic
    return ("; " + "; ".join(parts) if parts else "") + units


def box_text(lo, hi) -> str:
    """"x -0.2..0.2, y -0.2..0.2, z -0.12..0.52": a box for a message, in the caller's units."""
    return ", ".join(f"{a} {float(l):.4g}..{float(h):.4g}" for a, l, h in zip("xyz", lo, hi))


def stray_text(stray: dict) -> str:
    """A stray part for a message: "a stray part of 1 triangle (under 0.01 % of the area) at x 50..50, ... 49.5
    scene units from the rest (x -0.5..0.5, ...), widening the wall's box 50.5x along x"."""
    n = stray["triangles"]
    pieces = f" in {stray['pieces']} pieces" if stray["pieces"] > 1 else ""
    share = "under 0.01 %" if stray["area_share"] < 1e-4 else f"{100 * stray['area_share']:.2g} %"
    return (f"a stray part of {n} triangle{'s' if n != 1 else ''}{pieces} ({share} of the area) at "
            f"{box_text(stray['min'], stray['max'])}, {stray['distance']:.4g} scene units from the rest "
            f"({box_text(stray['rest_min'], stray['rest_max'])}), widening the wall's box {stray['widens']:.4g}x "
            f"along {stray['axis']}")
