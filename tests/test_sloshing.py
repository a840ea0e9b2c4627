"""Free sloshing through the pipeline (configs/sloshing.yaml, issue 20's analytic axis): DFSPH with water's
viscosity rings at linear theory's first frequency, and the same tank in centimetres with Y up rings alike.
(WCSPH and MPS sloshing: tests/test_moving_walls.py, tests/test_moving_walls_mps.py.)"""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

import pipeline
from pipeline import Registry
from stages.simulate import validation as val

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "sloshing.yaml"
L, W, H = 0.2, 0.04, 0.1  # the config's tank length, width and water depth, m
SPACING_FACTOR = 4.0 / 3.0  # 15 particles of depth (the config: 20)


def in_units(raw: dict, scale: float, up: str) -> dict:
    """The config with every length in units of 1 / scale metres and the given up axis (Y: y and z swapped)."""
    raw = copy.deepcopy(raw)
    swap = (lambda v: [v[0], v[2], v[1]]) if up == "Y" else (lambda v: list(v))
    raw["scene"]["units"] = {"meters_per_unit": 1.0 / scale, "up_axis": up}
    tank = raw["walls"][0]
    tank["size"] = swap([scale * v for v in tank["size"]])
    tank["center"] = swap([scale * v for v in tank["center"]])
    em = raw["fluid"]["emitters"][0]
    em["box"] = {k: swap([scale * v for v in em["box"][k]]) for k in ("min", "max")}
    em["velocity"] = swap([scale * v for v in em["velocity"]])
    raw["fluid"]["spacing"] = scale * raw["fluid"]["spacing"]
    return raw


def run(raw: dict, folder: Path) -> Path:
    config = folder / "sloshing.yaml"
    folder.mkdir(parents=True)
    config.write_text(yaml.safe_dump(raw))
    report = pipeline.run(config, registry=Registry.from_entry_points(), overrides=("simulate.use=dfsph",
                          f"fluid.spacing={raw['fluid']['spacing'] * SPACING_FACTOR}"), cache_dir=folder / "cache",
                          out_dir=folder / "out")
    return Path(report.outputs["particles"]).parent


def test_dfsph_rings_at_the_first_sloshing_frequency_in_any_units(tmp_path):
    """At 15 particles of depth DFSPH's first mode rings within 2 % of f1 = 1.892 Hz and damps at a ratio below
    0.05 (water's is 0.006), in metres with Z up and in centimetres with Y up. Measured in m, m Y-up, cm, mm:
    0.08-0.43 % and 0.017-0.030; the runs differ by rounding, which the particles' motion amplifies, so the two
    are compared within that spread (1 % of f1, 0.02 of damping ratio), not bitwise. (The spread depends on the
    numba cache too: a fresh clone's cold cache gave 0.0174 in m against 0.0342 in cm in session 38, outside the
    0.015 this compared within before; the same clone's warm reruns pass, and a warm run in m gave 0.0074. A units
    error is far larger: water's viscosity taken 100 x too high damps at 0.085, its frequency 2.3 % off f1.)"""
    results = []
    for scale, up in [(1.0, "Z"), (100.0, "Y")]:
        raw = in_units(yaml.safe_load(CONFIG.read_text()), scale, up)
        out = run(raw, tmp_path / f"{scale:g}{up}")
        kw = dict(length=L * scale, width=W * scale)
        results.append((val.sloshing_frequency_error(out, depth=H * scale, **kw), val.sloshing_damping(out, **kw)))
    for err, zeta in results:
        assert err < 0.02, results
        assert 0.0 < zeta < 0.05, results
    (e_m, z_m), (e_cm, z_cm) = results
    assert abs(e_m - e_cm) < 0.01 and abs(z_m - z_cm) < 0.02, results


def test_the_kinetic_energy_ratio_sees_motion_the_method_made(tmp_path):
    """The first mode's fit is blind to motion that is not the first mode: DFSPH's tank fitted within 0.8 % of
    f1 while its kinetic energy rose 6 x (a tester's run; issue 17). The study also reports the mean kinetic
    energy over the second half against the start's, all of the sloshing's energy (a flat surface, moving):
    above 1 is motion the method made. Checked on frames of a known energy, in centimetres."""
    import numpy as np

    from stages.common.formats import ParticleFrame, ParticleMeta, save_particle_frame

    for growth in (0.5, 2.0):
        folder = tmp_path / f"g{growth}" / "particles"
        folder.mkdir(parents=True)
        ParticleMeta(spacing=1.0, mass=0.001, density=1000.0, support=2.0, fps=10, frame_count=8, up_axis="Z",
                     meters_per_unit=0.01, solver="synthetic").save(folder)
        for f in range(8):
            speed = 5.0 * (1.0 if f < 4 else growth)  # cm/s: the second half at `growth` x the start's speed
            v = np.tile([speed, 0.0, 0.0], (10, 1))
            save_particle_frame(folder, f, ParticleFrame(np.zeros((10, 3)), v, np.full(10, 1000.0), np.zeros(10),
                                                         np.arange(10)))
        ratio = val.sloshing_kinetic_energy_ratio(folder.parent)
        assert ratio == pytest.approx(growth ** 2), ratio
    study = yaml.safe_load((CONFIG.parent / "studies" / "sloshing.yaml").read_text())
    assert "kinetic_energy_ratio" in [m["name"] for m in study["metrics"]]
