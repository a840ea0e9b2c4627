"""The convergence metrics of stages/simulate/validation.py (issue 20) on synthetic outputs with an analytic
answer: a front moving at a known fraction of Ritter's speed, a column with a known pressure error, two
runs whose fronts differ by a known distance, errors following a known power law. Metres and centimetres,
Z and Y up."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stages.common.formats import ParticleFrame, save_particle_frame
from stages.simulate import validation as val

G = 9.81


def write_run(folder, *, front, spacing, fps=60.0, mpu=1.0, axis=0, up_axis="Z", frames=None, density=1000.0):
    """A simulate stage's output folder: meta.json with per-frame extent_max (front - spacing / 2 along
    ``axis``) and optionally particle frames."""
    ext = np.zeros((len(front), 3))
    ext[:, axis] = np.asarray(front) - 0.5 * spacing
    meta = {"spacing": spacing, "fps": fps, "meters_per_unit": mpu, "up_axis": up_axis, "density": density,
            "frame_count": len(frames) if frames else len(front), "stats": {"extent_max": ext.tolist()}}
    (folder / "particles").mkdir(parents=True)
    (folder / "particles" / "meta.json").write_text(json.dumps(meta))
    for k, f in enumerate(frames or []):
        save_particle_frame(folder / "particles", k, f)
    return folder


@pytest.mark.parametrize("mpu", [1.0, 0.01])
@pytest.mark.parametrize("factor", [1.0, 0.8])
def test_front_speed_error_against_ritter(tmp_path, mpu, factor):
    H_m = 0.5
    u = factor * 2.0 * math.sqrt(G * H_m)  # m/s
    t = np.arange(25) / 60.0
    # accelerating for 0.05 s (outside the fit window), then at u: the window sees only the speed
    x_m = 0.25 + np.where(t < 0.05, 0.5 * u / 0.05 * t ** 2, u * (t - 0.025))
    run = write_run(tmp_path / "r", front=x_m / mpu, spacing=0.0125 / mpu, mpu=mpu)
    err = val.front_speed_error(run, column_height=H_m / mpu, t_min=0.1, t_max=0.2)
    assert err == pytest.approx(abs(factor - 1.0), abs=1e-9)


def test_front_speed_needs_frames_in_the_window():
    with pytest.raises(ValueError, match="fewer than two frames"):
        val.front_speed(np.array([0.0, 0.5]), np.array([0.0, 1.0]), 0.1, 0.2)


def column(l0, n_side, layers, up, mpu, p_factor, rho0=1000.0):
    """A lattice column (scene units) with pressure p_factor rho0 g d (d below the free surface, metres)."""
    g = (np.arange(n_side) + 0.5) * l0
    k = (np.arange(layers) + 0.5) * l0
    a, b, c = np.meshgrid(g, g, k, indexing="ij")
    x = np.stack([a.ravel(), b.ravel(), c.ravel()], 1)
    if up == "Y":
        x = x[:, [0, 2, 1]]
    height = x[:, 1 if up == "Y" else 2]
    depth_m = (layers * l0 - height) * mpu
    p = p_factor * rho0 * G * depth_m
    n = len(x)
    return ParticleFrame(x=x, v=np.zeros_like(x), rho=np.full(n, rho0), p=p, id=np.arange(n))


@pytest.mark.parametrize("up,mpu", [("Z", 1.0), ("Y", 0.01), ("Z", 0.001)])
@pytest.mark.parametrize("p_factor", [1.0, 1.07, 0.9])
def test_hydrostatic_pressure_error(tmp_path, up, mpu, p_factor):
    l0 = 0.01 / mpu
    frames = [column(l0, 12, 20, up, mpu, p_factor) for _ in range(3)]
    run = write_run(tmp_path / "r", front=[0.0] * 3, spacing=l0, mpu=mpu, up_axis=up, frames=frames)
    assert val.hydrostatic_pressure_error(run, frames=2) == pytest.approx(abs(p_factor - 1.0), abs=1e-5)


def test_hydrostatic_pressure_error_needs_a_deep_enough_column(tmp_path):
    frames = [column(0.01, 12, 2, "Z", 1.0, 1.0)]
    run = write_run(tmp_path / "r", front=[0.0], spacing=0.01, frames=frames)
    with pytest.raises(ValueError, match="no particles"):
        val.hydrostatic_pressure_error(run)


def test_distance_to_finest(tmp_path):
    t = np.arange(20) / 60.0
    a = 0.25
    fine = write_run(tmp_path / "variants" / "spacing-0.0125_use-sph", front=0.25 + 3.0 * t, spacing=0.0125)
    coarse = write_run(tmp_path / "variants" / "spacing-0.025_use-sph", front=0.25 + 3.0 * t + 0.02, spacing=0.025)
    assert val.finest_variant(coarse, {"spacing": 0.0125}) == fine
    assert val.distance_to_finest(coarse, finest={"spacing": 0.0125}, column_width=a) == pytest.approx(0.02 / a)
    assert val.distance_to_finest(fine, finest={"spacing": 0.0125}, column_width=a) == 0.0
    other = write_run(tmp_path / "variants" / "spacing-0.025_use-mps", front=0.25 + 3.0 * t, spacing=0.025)
    with pytest.raises(ValueError, match="list the finest value first"):
        val.distance_to_finest(other, finest={"spacing": 0.0125}, column_width=a)


def test_observed_order_and_cost_per_halving():
    h = np.array([0.04, 0.02, 0.01])
    assert val.observed_order(h, 3.0 * h ** 2) == pytest.approx(2.0)
    assert val.observed_order(h, 0.5 * h) == pytest.approx(1.0)
    # error ~ t^-1/2: halving the error costs 4x the time; ~ t^-1: 2x
    t = np.array([1.0, 8.0, 64.0])
    assert val.cost_per_halving(t, 0.1 * t ** -0.5) == pytest.approx(4.0)
    assert val.cost_per_halving(t, 0.1 / t) == pytest.approx(2.0)
    assert val.cost_per_halving(t, 0.1 * t) == math.inf  # error rising with cost: no halving at any price
    with pytest.raises(ValueError):
        val.observed_order([0.01, 0.02], [0.0, 0.1])
