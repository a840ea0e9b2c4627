"""Adaptive time step (PHYSICS.md "Time step limits"), shared by SPH and MPS."""
from __future__ import annotations

import math

# Defaults tuned at this spacing (m) are Froude-scaled above it (lengths x k, times x sqrt(k)), so a scene
# 10,000 x larger runs as the same scene scaled: DFSPH's largest step, MPS's compressibility term.
REFERENCE_SPACING = 0.02


def stable_dt(*, l0: float, h: float, v_max: float, a_max: float, cfl: float, sound_speed: float | None,
              nu: float | None, dt_max: float) -> float:
    """min of the advective (cfl l0 / v_max), acoustic (0.4 h / (c + v_max)), viscous
    (0.125 h^2 / nu) and force (0.25 sqrt(h / a_max)) limits, and ``dt_max`` (the frame interval)."""
    dt = dt_max
    if v_max > 0:
        dt = min(dt, cfl * l0 / v_max)
    if sound_speed:
        dt = min(dt, 0.4 * l0 / (sound_speed + v_max))
    if nu:
        dt = min(dt, 0.125 * h * h / nu)
    if a_max > 0:
        dt = min(dt, 0.25 * math.sqrt(h / a_max))
    return dt


def step_to(t: float, t_end: float, dt: float) -> float:
    """The step to take from t towards t_end: never past it, and no sliver step at the end (the
    remainder below 1.5 dt is split in two equal steps). A remainder within rounding of dt is one step: frames
    on multiples of a fixed time step left remainders a few ulps above it, and each was split in two."""
    rest = t_end - t
    if rest <= dt * (1.0 + 1e-9):
        return rest
    if rest < 1.5 * dt:
        return 0.5 * rest
    return dt
