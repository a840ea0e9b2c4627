"""Validation metrics computed from a simulate stage's output, for `pipeline study` (``function:``
metrics) and the benchmarks: the simulation against experiment, not against itself."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

AXES = {"x": 0, "y": 1, "z": 2}


def read_reference(path: Path, series: str | None = None) -> np.ndarray:
    """(T, Z) rows of a reference CSV with '#' comment lines and columns T, Z_over_a (or Z_over_L)."""
    lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    rows = list(csv.DictReader(lines))
    zkey = next(k for k in rows[0] if k.startswith("Z_over"))
    return np.array([(float(r["T"]), float(r[zkey])) for r in rows if series is None or r.get("series") == series])


def surge_front(out_dir: Path, *, column_width: float, back_wall: float, axis: str = "x", g: float = 9.81):
    """Dimensionless surge front of a dam break: T = t sqrt(2 g / a) and Z/a = (front - back wall) / a per
    frame, the front being the fluid's furthest extent along ``axis`` (per-frame stats of the simulate
    stage: the outermost particle centre, plus half a spacing for the particle's own extent).
    ``column_width`` a and ``back_wall`` are in scene units."""
    meta = json.loads((Path(out_dir) / "particles" / "meta.json").read_text())
    ext = np.asarray(meta["stats"]["extent_max"], float)[:, AXES[axis]] + 0.5 * float(meta["spacing"])
    t = np.arange(len(ext)) / float(meta["fps"])
    a_m = column_width * float(meta.get("meters_per_unit", 1.0))
    return t * math.sqrt(2.0 * g / a_m), (ext - back_wall) / column_width


def surge_front_error(out_dir: Path, *, study_dir: Path | None = None, reference: str, column_width: float,
                      back_wall: float, axis: str = "x", series: str | None = None, t_max: float = 3.0,
                      g: float = 9.81) -> float:
    """RMS relative error of the surge front against a published one (e.g. Martin & Moyce 1952, T <= t_max).
    ``reference`` is relative to ``study_dir``."""
    ref = read_reference(Path(study_dir or ".") / reference, series)
    T, Z = surge_front(out_dir, column_width=column_width, back_wall=back_wall, axis=axis, g=g)
    ref = ref[(ref[:, 0] <= min(t_max, T[-1]))]
    if not len(ref):
        raise ValueError(f"{out_dir}: the simulation ends at T = {T[-1]:.2f}, before the first reference point")
    z = np.interp(ref[:, 0], T, Z)
    return float(np.sqrt(np.mean(((z - ref[:, 1]) / ref[:, 1]) ** 2)))
