"""Validation metrics computed from a simulate stage's output, for `pipeline study` (``function:``
metrics) and the benchmarks: the simulation against experiment, not against itself.

Lengths (``column_width``, ``length``, ...) are numbers in the run's scene units, or text with a unit ("0.146 m",
"14.6 cm"), which every variant of a study sweeping the units reads alike (one number was 100 x off in the
centimetre variant). ``g`` defaults to the gravity the run recorded (a study sweeping gravity was judged at 9.81)."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

AXES = {"x": 0, "y": 1, "z": 2}
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "km": 1000.0, "in": 0.0254, "ft": 0.3048}


def scene_length(value: float | str, meta: dict) -> float:
    """A metric's length in the run's scene units: a number as it is, "<number> <unit>" converted."""
    if not isinstance(value, str):
        return float(value)
    number, _, unit = value.strip().partition(" ")
    if unit.strip() not in UNITS:
        raise ValueError(f"{value!r}: a length is a number in scene units or '<number> <unit>', unit one of "
                         f"{', '.join(UNITS)}")
    return float(number) * UNITS[unit.strip()] / float(meta.get("meters_per_unit", 1.0))


def gravity(g: float | None, meta: dict) -> float:
    """The metric's g: given, else the run's (meta.json), else 9.81."""
    if g is not None:
        return float(g)
    recorded = meta.get("gravity")
    return float(recorded) if recorded else 9.81




def read_reference(path: Path, series: str | None = None) -> np.ndarray:
    """(T, Z) rows of a reference CSV with '#' comment lines and columns T, Z_over_a (or Z_over_L)."""
    lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    rows = list(csv.DictReader(lines))
    zkey = next(k for k in rows[0] if k.startswith("Z_over"))
    return np.array([(float(r["T"]), float(r[zkey])) for r in rows if series is None or r.get("series") == series])


def surge_front(out_dir: Path, *, column_width: float | str, back_wall: float | str, axis: str = "x",
                g: float | None = None):
    """Dimensionless surge front of a dam break: T = t sqrt(2 g / a) and Z/a = (front - back wall) / a per
    frame, the front being the fluid's furthest extent along ``axis`` (per-frame stats of the simulate
    stage: the outermost particle centre, plus half a spacing for the particle's own extent).
    ``column_width`` a and ``back_wall`` are in scene units."""
    t, ext, meta = front_history(out_dir, axis=axis)
    column_width, back_wall = scene_length(column_width, meta), scene_length(back_wall, meta)
    a_m = column_width * float(meta.get("meters_per_unit", 1.0))
    return t * math.sqrt(2.0 * gravity(g, meta) / a_m), (ext - back_wall) / column_width


def surge_front_error(out_dir: Path, *, study_dir: Path | None = None, reference: str, column_width: float | str,
                      back_wall: float | str, axis: str = "x", series: str | None = None, t_max: float = 3.0,
                      g: float | None = None) -> float:
    """RMS relative error of the surge front against a published one (e.g. Martin & Moyce 1952, T <= t_max).
    ``reference`` is relative to ``study_dir``."""
    ref = read_reference(Path(study_dir or ".") / reference, series)
    T, Z = surge_front(out_dir, column_width=column_width, back_wall=back_wall, axis=axis, g=g)
    ref = ref[(ref[:, 0] <= min(t_max, T[-1]))]
    if not len(ref):
        raise ValueError(f"{out_dir}: the simulation ends at T = {T[-1]:.2f}, before the first reference point")
    z = np.interp(ref[:, 0], T, Z)
    return float(np.sqrt(np.mean(((z - ref[:, 1]) / ref[:, 1]) ** 2)))


# --- Metrics the solvers converge to (issue 20): analytic references and the finest run of a study ----------


def front_history(out_dir: Path, *, axis: str = "x") -> tuple[np.ndarray, np.ndarray, dict]:
    """Per frame: time (s) and the fluid's furthest extent along ``axis`` (scene units: the outermost
    particle centre plus half a spacing), and the particle meta."""
    meta = json.loads((Path(out_dir) / "particles" / "meta.json").read_text())
    ext = np.asarray(meta["stats"]["extent_max"], float)[:, AXES[axis]] + 0.5 * float(meta["spacing"])
    return np.arange(len(ext)) / float(meta["fps"]), ext, meta


def front_speed(t: np.ndarray, front: np.ndarray, t_min: float, t_max: float) -> float:
    """Least-squares slope of the front position over t_min <= t <= t_max (at least two frames)."""
    sel = (t >= t_min - 1e-9) & (t <= t_max + 1e-9)
    if sel.sum() < 2:
        raise ValueError(f"front speed: fewer than two frames in {t_min} <= t <= {t_max} s")
    return float(np.polyfit(t[sel], front[sel], 1)[0])


def front_speed_error(out_dir: Path, *, study_dir: Path | None = None, column_height: float | str, axis: str = "x",
                      t_min: float = 0.1, t_max: float = 0.2, g: float | None = None) -> float:
    """|u / (2 sqrt(g H)) - 1|: the dam-break front speed u fitted over [t_min, t_max] s against Ritter's
    shallow-water front speed for a column H high (``column_height``, scene units). Ritter's is the inviscid
    shallow-water limit: the Euler (and a real) front approaches it from below, so this error falls with
    resolution towards a floor of some ten per cent, not to zero (README "Convergence")."""
    t, front, meta = front_history(out_dir, axis=axis)
    mpu = float(meta.get("meters_per_unit", 1.0))
    u = front_speed(t, front, t_min, t_max) * mpu
    return abs(u / (2.0 * math.sqrt(gravity(g, meta) * scene_length(column_height, meta) * mpu)) - 1.0)


def hydrostatic_pressure_error(out_dir: Path, *, study_dir: Path | None = None, frames: int = 5,
                               min_depth: float = 2.0, max_depth: float = 8.0, wall_margin: float = 2.0,
                               g: float | None = None) -> float:
    """|sum p / sum rho0 g d - 1| over the last ``frames`` frames, for the particles between ``min_depth`` and
    ``max_depth`` spacings below the free surface (the mean height of the top layer plus half a spacing) and at
    least ``wall_margin`` spacings inside the fluid's horizontal extent: the settled pressure against rho0 g d."""
    from stages.common.formats import load_particle_frame
    folder = Path(out_dir) / "particles"
    meta = json.loads((folder / "meta.json").read_text())
    l0, mpu, rho0 = float(meta["spacing"]), float(meta.get("meters_per_unit", 1.0)), float(meta["density"])
    up = AXES[str(meta.get("up_axis", "Z")).lower()]
    g = gravity(g, meta)
    side = [a for a in range(3) if a != up]
    n = int(meta["frame_count"])
    num = den = 0.0
    for k in range(max(0, n - frames), n):
        f = load_particle_frame(folder, k)
        x = np.asarray(f.x, float)
        z = x[:, up]
        top = z[z > z.max() - 0.5 * l0].mean() + 0.5 * l0
        depth = top - z
        sel = (depth > min_depth * l0) & (depth < max_depth * l0)
        for a in side:
            sel &= (x[:, a] > x[:, a].min() + wall_margin * l0) & (x[:, a] < x[:, a].max() - wall_margin * l0)
        num += float(np.asarray(f.p, float)[sel].sum())
        den += float((rho0 * g * depth[sel] * mpu).sum())
    if den <= 0:
        raise ValueError(f"{out_dir}: no particles between {min_depth} and {max_depth} spacings deep")
    return abs(num / den - 1.0)


def damped_frequency(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(f, delta): the free decay y ~ A exp(-delta t) cos(2 pi f t + phase) + c0 + c1 t fitted by least squares
    (linear in A cos, A sin, c0, c1 for given f and delta: those two by a grid, then a finer grid around the
    best); delta in 1/s, negative for a growing oscillation. Zero crossings about the mean are biased by a
    decay this strong (delta ~ 2 / s) and by the slow settling of the surface; the fit is not."""
    t = np.asarray(t, float) - float(t[0])
    y = np.asarray(y, float)

    def residual(f, delta):
        e = np.exp(-delta * t)
        a = np.stack([e * np.cos(2 * np.pi * f * t), e * np.sin(2 * np.pi * f * t), np.ones_like(t), t], axis=1)
        return float(np.linalg.lstsq(a, y, rcond=None)[1].sum())

    crossings = np.flatnonzero(np.diff(np.signbit(y - y.mean())))
    if len(crossings) < 3:
        raise ValueError("damped frequency: fewer than three crossings of the mean (no oscillation to fit)")
    f0 = 1.0 / (2.0 * np.median(np.diff(t[crossings])))  # a first guess
    # delta < 0: a growing oscillation, which a solver that creates energy shows (fitted, not clamped at 0)
    fs, ds = np.linspace(0.7 * f0, 1.3 * f0, 61), np.linspace(-2.0, 6.0, 41)
    for _ in range(3):
        r = np.array([[residual(f, d) for d in ds] for f in fs])
        i, j = np.unravel_index(np.argmin(r), r.shape)
        f, d = fs[i], ds[j]
        fs = np.linspace(f - 2 * (fs[1] - fs[0]), f + 2 * (fs[1] - fs[0]), 41)
        ds = np.linspace(d - 2 * (ds[1] - ds[0]), d + 2 * (ds[1] - ds[0]), 21)
    return float(f), float(d)


def sloshing_f1(length: float, depth: float, g: float = 9.81) -> float:
    """Linear theory's first sloshing frequency of a rectangular tank (Hz; SI lengths):
    f1 = sqrt(g k tanh(k H)) / 2 pi, k = pi / L."""
    k = math.pi / length
    return math.sqrt(g * k * math.tanh(k * depth)) / (2.0 * math.pi)


def sloshing_history(out_dir: Path, *, length: float | str, width: float | str, axis: str = "x",
                     wall: float | str = 0.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per frame: time (s) and the first mode's surface elevation at the wall x = ``wall`` (scene units),
    eta1 = (2 / L) sum_i V_i cos(k (x_i - wall)) / width, k = pi / L, V_i = l0^3 each particle's volume. The
    first mode's amplitude: the cos-weighted volume of the water per unit width, blind to the other modes
    (orthogonal to them) and smooth in the positions, unlike the top particle at the wall."""
    from stages.common.formats import load_particle_frame
    folder = Path(out_dir) / "particles"
    meta = json.loads((folder / "meta.json").read_text())
    l0 = float(meta["spacing"])
    length, width, wall = (scene_length(v, meta) for v in (length, width, wall))
    k = math.pi / length
    a = AXES[axis]
    eta = []
    for f in range(int(meta["frame_count"])):
        x = np.asarray(load_particle_frame(folder, f).x, float)[:, a]
        eta.append(2.0 / length * l0 ** 3 * float(np.cos(k * (x - wall)).sum()) / width)
    return np.arange(len(eta)) / float(meta["fps"]), np.asarray(eta), meta


def _sloshing_fit(out_dir: Path, length, width, axis: str, wall, t_min: float):
    """The first mode's (frequency, decay rate) and the run's meta."""
    t, eta, meta = sloshing_history(out_dir, length=length, width=width, axis=axis, wall=wall)
    sel = t >= t_min - 1e-9
    if sel.sum() < 8:
        raise ValueError(f"{out_dir}: fewer than 8 frames after t = {t_min} s to fit the sloshing mode")
    return damped_frequency(t[sel], eta[sel]), meta


def _si(meta: dict, *lengths) -> list[float]:
    mpu = float(meta.get("meters_per_unit", 1.0))
    return [scene_length(v, meta) * mpu for v in lengths]


def sloshing_frequency_error(out_dir: Path, *, study_dir: Path | None = None, length: float | str,
                             depth: float | str, width: float | str, axis: str = "x", wall: float | str = 0.0,
                             t_min: float = 0.0, g: float | None = None) -> float:
    """|f / f1 - 1|: the first sloshing mode's frequency f, a damped sinusoid fitted to its elevation at the
    wall (sloshing_history) from ``t_min`` s on, against linear theory's f1 for a tank ``length`` long with
    water ``depth`` deep (scene units). Linear theory is the limit the solvers converge to for small
    amplitudes (k A << 1: the weakly nonlinear shift is O((k A)^2))."""
    (f, _), meta = _sloshing_fit(out_dir, length, width, axis, wall, t_min)
    return abs(f / sloshing_f1(*_si(meta, length, depth), gravity(g, meta)) - 1.0)


def sloshing_damping(out_dir: Path, *, study_dir: Path | None = None, length: float | str, width: float | str,
                     axis: str = "x", wall: float | str = 0.0, t_min: float = 0.0) -> float:
    """The first sloshing mode's damping ratio zeta = delta / (2 pi f) from the same fit (negative: the
    oscillation grows)."""
    (f, delta), _ = _sloshing_fit(out_dir, length, width, axis, wall, t_min)
    return delta / (2.0 * math.pi * f)


def sloshing_kinetic_energy_ratio(out_dir: Path, *, study_dir: Path | None = None, **_) -> float:
    """The fluid's mean kinetic energy over the run's second half against its kinetic energy at t = 0. The
    sloshing starts from a flat surface with a velocity, so all its energy is kinetic then, and at most that
    can be kinetic later: a ratio above 1 is motion the method made, which the first mode's fit does not see
    (DFSPH's tank fitted within 0.8 % of f1 while its kinetic energy rose 6 x: a churn, issue 17)."""
    from stages.common.formats import load_particle_frame
    folder = Path(out_dir) / "particles"
    meta = json.loads((folder / "meta.json").read_text())
    mpu = float(meta.get("meters_per_unit", 1.0))
    ke = []
    for f in range(int(meta["frame_count"])):
        v = np.asarray(load_particle_frame(folder, f).v, float) * mpu
        ke.append(0.5 * float(meta["mass"]) * float(np.einsum("ij,ij->", v, v)))
    if len(ke) < 4 or ke[0] <= 0.0:
        raise ValueError(f"{out_dir}: the kinetic energy ratio needs a moving start and at least 4 frames")
    return float(np.mean(ke[len(ke) // 2:]) / ke[0])


def sloshing_damping_error(out_dir: Path, *, study_dir: Path | None = None, length: float | str,
                           depth: float | str, width: float | str, axis: str = "x", wall: float | str = 0.0,
                           t_min: float = 0.0, nu: float = 1.0e-6, g: float | None = None) -> float:
    """|zeta - zeta_water|: the first mode's damping ratio against the one water's viscosity gives through
    the walls' boundary layers (sloshing_viscous_damping: 0.006 in configs/sloshing.yaml's tank). The rest
    is the method's numerical dissipation (or, negative, energy it creates), which a convergent solver loses
    with resolution."""
    (f, delta), meta = _sloshing_fit(out_dir, length, width, axis, wall, t_min)
    water = sloshing_viscous_damping(*_si(meta, length, width, depth), nu, gravity(g, meta))
    return abs(delta / (2.0 * math.pi * f) - water)


def sloshing_viscous_damping(length: float, width: float, depth: float, nu: float = 1.0e-6,
                             g: float = 9.81) -> float:
    """Damping ratio of the first mode from the laminar Stokes layers on the floor and the four walls of a
    clean rectangular tank (SI): the mean dissipation (rho / 2) sqrt(nu w / 2) |U_t|^2 per unit wall area
    over twice the mode's energy (rho / 2) int |U|^2 dV, U = grad(cos kx cosh kz), divided by w."""
    k = math.pi / length
    w = 2.0 * math.pi * sloshing_f1(length, depth, g)
    s = math.sinh(2.0 * k * depth)
    volume = width * length * k * s / 4.0  # int |U|^2 dV
    floor = length * width / 2.0  # the walls' int |U_t|^2 dA, each over k^2
    ends = 2.0 * width * (s / (4.0 * k) - depth / 2.0)
    sides = 2.0 * (length / 2.0) * s / (2.0 * k)
    gamma = math.sqrt(nu * w / 2.0) * k * k * (floor + ends + sides) / (2.0 * volume)
    return gamma / w


def finest_variant(out_dir: Path, finest: dict, variants=None) -> Path:
    """The study variant to compare ``out_dir`` with: the one whose swept values are this one's with those of
    ``finest`` (an override path or its last part -> value, e.g. {spacing: 0.015625}) in their place.
    ``variants``: (overrides, output folder) of each of the study's variants, by default those of the study
    measuring now (pipeline.study.study_variants): matched by key and value, never by folder names or by what
    else lies beside them (a folder an earlier config of the study left). Outside a study, by folder name
    ("key-value" joined by "_"). ValueError "no finest run" when no variant matches."""
    out_dir = Path(out_dir)
    if variants is None:
        from pipeline.study import study_variants
        variants = study_variants()
    if variants is None:
        return _finest_by_name(out_dir, finest)
    mine = next((o for o, p in variants if Path(p).resolve() == out_dir.resolve()), None)
    if mine is None:
        raise ValueError(f"no finest run: {out_dir} is not one of the study's variants")
    want = dict(mine)
    for key, value in finest.items():
        keys = [k for k in mine if k == key] or [k for k in mine if k.split(".")[-1] == key]
        if len(keys) != 1:
            raise ValueError(f"no finest run: finest: {key!r} is {'none' if not keys else 'more than one'} of the "
                             f"swept keys ({', '.join(mine)})")
        want[keys[0]] = value
    for overrides, path in variants:
        if all(_same(overrides.get(k), v) for k, v in want.items()):
            return Path(path)
    raise ValueError(f"no finest run: no variant of the study has {', '.join(f'{k}={v}' for k, v in want.items())}"
                     f" (is {finest} one of the sweep's values?)")


def _same(a, b) -> bool:
    """Swept values equal: numbers by value (0.04 and 4e-2), the rest as given."""
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b))
    return float(a) == float(b) if numbers else a == b


def _finest_by_name(out_dir: Path, finest: dict) -> Path:
    parts = out_dir.name.split("_")
    for key, value in finest.items():
        key = str(key).split(".")[-1]
        if not any(p.startswith(f"{key}-") for p in parts):  # (a key with '_' in it): not this one in disguise
            raise ValueError(f"no finest run: {out_dir.name} has no value of {key}")
        parts = [f"{key}-{value}" if p.startswith(f"{key}-") else p for p in parts]
    return out_dir.parent / "_".join(parts)


def distance_to_finest(out_dir: Path, *, study_dir: Path | None = None, finest: dict, column_width: float | str,
                       axis: str = "x") -> float:
    """RMS over frames of the surge-front position's distance to the same solver's finest run of the study,
    over the column width a: the self-convergence error (0 for the finest run itself). The study measures
    once every variant has run, so the finest run is this study's (finest_variant)."""
    try:
        ref = finest_variant(out_dir, finest)
    except ValueError as e:
        raise ValueError(f"distance_to_finest: {e}") from None
    if not (ref / "particles" / "meta.json").is_file():
        raise ValueError(f"distance_to_finest: no finest run {ref}: is {finest} one of the study's sweep values "
                         "(and did it run)?")
    t0, f0, m0 = front_history(out_dir, axis=axis)
    t1, f1, m1 = front_history(ref, axis=axis)
    if len(f0) != len(f1) or not np.allclose(t0, t1):
        raise ValueError(f"distance_to_finest: the finest run {ref.name} has {len(f1)} frames, this one {len(f0)}: "
                         "compare runs of the same shot")
    (a,) = _si(m0, column_width)  # in metres: the finest run may be in other units
    f0, f1 = f0 * float(m0.get("meters_per_unit", 1.0)), f1 * float(m1.get("meters_per_unit", 1.0))
    return float(np.sqrt(np.mean((f0 - f1) ** 2)) / a)


def observed_order(spacings, errors) -> float:
    """Observed order of convergence p of error ~ C spacing^p: least-squares slope in log-log (positive
    errors only; at least two)."""
    h, e = np.asarray(spacings, float), np.asarray(errors, float)
    ok = e > 0
    if ok.sum() < 2:
        raise ValueError("observed order: needs at least two positive errors")
    return float(np.polyfit(np.log(h[ok]), np.log(e[ok]), 1)[0])


def cost_per_halving(seconds, errors) -> float:
    """The factor the wall time grows by for each halving of the error, from a least-squares fit
    error ~ C seconds^-s: 2^(1/s)."""
    t, e = np.asarray(seconds, float), np.asarray(errors, float)
    ok = (e > 0) & (t > 0)
    if ok.sum() < 2:
        raise ValueError("cost per halving: needs at least two positive (time, error) points")
    s = -float(np.polyfit(np.log(t[ok]), np.log(e[ok]), 1)[0])
    return float(2.0 ** (1.0 / s)) if s > 0 else math.inf
