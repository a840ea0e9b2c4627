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


def write_run(folder, *, front, spacing, fps=60.0, mpu=1.0, axis=0, up_axis="Z", frames=None, density=1000.0,
              gravity=None):
    """A simulate stage's output folder: meta.json with per-frame extent_max (front - spacing / 2 along
    ``axis``) and optionally particle frames."""
    ext = np.zeros((len(front), 3))
    ext[:, axis] = np.asarray(front) - 0.5 * spacing
    meta = {"spacing": spacing, "fps": fps, "meters_per_unit": mpu, "up_axis": up_axis, "density": density,
            "frame_count": len(frames) if frames else len(front), "stats": {"extent_max": ext.tolist()},
            **({"gravity": gravity} if gravity is not None else {})}
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


def test_a_studys_metric_reads_lengths_with_units_and_the_runs_own_gravity(tmp_path):
    """A study sweeping the units gives every variant one set of metric arguments: a column height as a number
    was in each run's scene units, so the centimetre variant's front speed error read 1.34 against 0.77 (a
    tester's units study). "0.5 m" reads alike in every run; g defaults to the gravity the run recorded (a
    gravity sweep's g = 2.45 run was judged at 9.81)."""
    def run(name, mpu, g):
        u = 0.9 * 2.0 * math.sqrt(g * 0.5)  # m/s: 10 % behind Ritter's front at this run's gravity
        t = np.arange(25) / 60.0
        return write_run(tmp_path / name, front=(0.25 + u * t) / mpu, spacing=0.0125 / mpu, mpu=mpu, gravity=g)

    for name, mpu in (("m", 1.0), ("cm", 0.01), ("mm", 0.001)):
        r = run(name, mpu, G)
        for height in ("0.5 m", "50 cm", "500 mm"):
            assert val.front_speed_error(r, column_height=height) == pytest.approx(0.1, abs=1e-9), (name, height)
        assert val.front_speed_error(r, column_height=0.5 / mpu) == pytest.approx(0.1, abs=1e-9)
    moon = run("moon", 1.0, 1.62)
    assert val.front_speed_error(moon, column_height="0.5 m") == pytest.approx(0.1, abs=1e-9)
    assert val.front_speed_error(moon, column_height="0.5 m", g=G) == pytest.approx(1 - 0.9 * math.sqrt(1.62 / G))
    with pytest.raises(ValueError, match="'0.5 furlong': a length is a number in scene units or '<number> <unit>'"):
        val.front_speed_error(moon, column_height="0.5 furlong")


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
    with pytest.raises(ValueError, match="no finest run"):
        val.distance_to_finest(other, finest={"spacing": 0.0125}, column_width=a)
    # a finest run of another shot (other frames) is no reference: it was compared over the shorter one
    short = write_run(tmp_path / "variants" / "spacing-0.025_use-dfsph", front=0.25 + 3.0 * t[:10], spacing=0.025)
    write_run(tmp_path / "variants" / "spacing-0.0125_use-dfsph", front=0.25 + 3.0 * t, spacing=0.0125)
    with pytest.raises(ValueError, match="has 20 frames, this one 10"):
        val.distance_to_finest(short, finest={"spacing": 0.0125}, column_width=a)


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


def sloshing_run(folder, *, f, delta, mpu=1.0, axis=0, L=0.2, W=0.04, H=0.1, l0=0.01, fps=60.0, frames=90):
    """A lattice of water L x W x H (metres) whose particles are displaced along ``axis`` by
    eps(t) sin(k x), eps = 1e-4 L exp(-delta t) cos(2 pi f t): the first mode's elevation at the wall is then
    -eps k H to first order, so it rings at f and decays at delta. Stored in scene
    units of ``mpu`` metres."""
    k = math.pi / L
    nx, ny, nz = round(L / l0), round(W / l0), round(H / l0)
    g = np.meshgrid((np.arange(nx) + 0.5) * l0, (np.arange(ny) + 0.5) * l0, (np.arange(nz) + 0.5) * l0, indexing="ij")
    base = np.stack([a.ravel() for a in g], 1)
    if axis == 1:  # the tank's length along y (and its width along x)
        base = base[:, [1, 0, 2]]
    out = []
    for n in range(frames):
        t = n / fps
        eps = 1e-4 * L * math.exp(-delta * t) * math.cos(2 * math.pi * f * t)
        x = base.copy()
        x[:, axis] += eps * np.sin(k * base[:, axis])
        x /= mpu
        out.append(ParticleFrame(x=x, v=np.zeros_like(x), rho=np.full(len(x), 1000.0), p=np.zeros(len(x)),
                                 id=np.arange(len(x))))
    return write_run(folder, front=[0.0] * frames, spacing=l0 / mpu, fps=fps, mpu=mpu, frames=out)


@pytest.mark.parametrize("mpu,axis", [(1.0, 0), (0.01, 0), (0.001, 1)])
@pytest.mark.parametrize("factor,zeta", [(1.0, 0.02), (1.05, 0.006), (0.97, -0.004)])
def test_sloshing_metrics_recover_a_known_mode(tmp_path, mpu, axis, factor, zeta):
    """A mode ringing at factor x f1 with damping ratio zeta (negative: growing) is measured as such, in
    metres, centimetres and millimetres, along x or y."""
    f1 = val.sloshing_f1(0.2, 0.1)
    f = factor * f1
    run = sloshing_run(tmp_path / "r", f=f, delta=zeta * 2 * math.pi * f, mpu=mpu, axis=axis)
    kw = dict(length=0.2 / mpu, width=0.04 / mpu, axis="xyz"[axis])
    assert val.sloshing_frequency_error(run, depth=0.1 / mpu, **kw) == pytest.approx(abs(factor - 1.0), abs=1e-3)
    assert val.sloshing_damping(run, **kw) == pytest.approx(zeta, abs=1e-3)
    water = val.sloshing_viscous_damping(0.2, 0.04, 0.1)
    assert val.sloshing_damping_error(run, depth=0.1 / mpu, **kw) == pytest.approx(abs(zeta - water), abs=1e-3)
    t, eta, _ = val.sloshing_history(run, **kw)
    assert eta[0] == pytest.approx(-1e-4 * 0.2 * math.pi / 0.2 * 0.1 / mpu, rel=1e-3)  # -eps k H


def test_sloshing_f1_and_the_walls_damping_against_quadrature():
    """f1 from linear theory (f1 = 1.892 Hz for 0.1 m of water in a 0.2 m tank), and the Stokes-layer damping
    ratio against a direct quadrature of the mode's |grad phi|^2 over the volume and the wetted walls."""
    L, W, H, nu = 0.2, 0.04, 0.1, 1e-6
    assert val.sloshing_f1(L, H) == pytest.approx(1.8921, abs=1e-4)
    k = math.pi / L
    w = 2 * math.pi * val.sloshing_f1(L, H)
    n = 400
    x = (np.arange(n) + 0.5) / n * L
    z = (np.arange(n) + 0.5) / n * H
    X, Z = np.meshgrid(x, z, indexing="ij")
    u2 = (k * np.sin(k * X) * np.cosh(k * Z)) ** 2  # phi = cos(kx) cosh(kz)
    w2 = (k * np.cos(k * X) * np.sinh(k * Z)) ** 2
    dx, dz = L / n, H / n
    energy = (u2 + w2).sum() * dx * dz * W
    walls = ((k * np.sin(k * x)) ** 2).sum() * dx * W  # the floor: u only
    walls += 2 * ((k * np.sinh(k * z)) ** 2).sum() * dz * W  # the end walls x = 0, L: w only
    walls += 2 * (u2 + w2).sum() * dx * dz  # the side walls: both
    zeta = math.sqrt(nu * w / 2) * walls / (2 * energy) / w
    assert val.sloshing_viscous_damping(L, W, H, nu) == pytest.approx(zeta, rel=1e-4)
    assert 0.005 < zeta < 0.007
