"""Adaptive time step (PHYSICS.md "Time step limits"), shared by SPH and MPS."""
from __future__ import annotations

import functools
import math

# Defaults tuned at this spacing (m) are Froude-scaled above it (lengths x k, times x sqrt(k)), so a scene
# 10,000 x larger runs as the same scene scaled: DFSPH's largest step, MPS's compressibility term.
REFERENCE_SPACING = 0.02


def stable_dt(*, l0: float, h: float, v_max: float, a_max: float, cfl: float, sound_speed: float | None,
              dt_viscous: float, dt_max: float) -> float:
    """min of the advective (cfl l0 / v_max), acoustic (0.4 h / (c + v_max)), viscous (``dt_viscous``: the
    solver's viscous_dt) and force (0.25 sqrt(h / a_max)) limits, and ``dt_max`` (the frame interval)."""
    dt = min(dt_max, dt_viscous)
    if v_max > 0:
        dt = min(dt, cfl * l0 / v_max)
    if sound_speed:
        dt = min(dt, 0.4 * l0 / (sound_speed + v_max))
    if a_max > 0:
        dt = min(dt, 0.25 * math.sqrt(h / a_max))
    return dt


VISCOUS_MARGIN = 0.8  # of the viscosity sum's stability limit on the rest lattice (walls and a free surface move it)


@functools.lru_cache(maxsize=None)
def viscous_coefficient(support: float, samples: int = 24) -> float:
    """C in the viscous step limit dt <= C l0^2 / nu (nu the fluid's kinematic viscosity) of the eq. 9 sum
    normalised on the rest lattice (kernels.visc_lattice_factor), at a support of ``support`` l0: VISCOUS_MARGIN
    x 2 / the largest eigenvalue of the sum on the lattice. An explicit step of nu sum_j w_j (v_j - v_i) is
    stable while dt nu sum_j w_j (1 - cos k . x_j) <= 2 for every Fourier mode k (the fastest alternates layer by
    layer); the limit is 0.50 l0^2 / nu at 2 l0, 0.59 at 2.25 l0, 0.81 at 2.5 l0. The former 0.125 h^2 / nu (nu
    over the lattice factor) was 0.98 / 0.94 of it at 2 / 2.25 l0: walls and the free surface tipped it over (a
    dam break's block at mu 1e4 Pa s threw particles at 4 m/s with WCSPH, DFSPH blew up at 3e4; at 0.86 of it
    both ran calm up to 1e5)."""
    from .kernels import lattice_modes, visc_lap_np
    import numpy as np
    offsets, r, waves = lattice_modes(support, samples)
    w = visc_lap_np(r, support)
    w = w / (0.5 * (w * offsets[:, 2] ** 2).sum())  # the sum's Laplacian of z^2 / 2 made 1, as the solvers do
    largest = float(((1.0 - np.cos(waves @ offsets.T)) * w).sum(axis=1).max())
    return VISCOUS_MARGIN * 2.0 / largest


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
