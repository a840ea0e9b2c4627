"""Inflows (continuous emitters) and sinks, through the simulate stages (issue 18): the emitted volume is
pi r^2 v (t1 - t0), the jet follows the ballistic parabola, a tank with a tap and an overflow drain reaches
a constant level with the drained mass equal to the inflow, a resumed run is bitwise the uninterrupted
one, and malformed inflows and sinks are one-line config errors."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import main
from pipeline.stage import Artifact, StageError
from pipeline.testing import run_stage, stage_context
from stages.common.formats import ParticleMeta, load_particle_frame
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHSimulate
from stages.simulate.inflow import Inflow
from stages.simulate.mps import MPSSimulate
from stages.simulate.sph import SPHSimulate

SOLVERS = {"sph": SPHSimulate, "dfsph": DFSPHSimulate, "mps": MPSSimulate}
G = 9.81
WATER = {"gravity": {"g": G}, "viscosity": {"mu": 0.001}}


def _tank(tmp: Path, hi, l0: float) -> Path:
    folder = tmp / "sdf"
    if not folder.exists():
        folder.mkdir(parents=True)
        grid_from_function(box_interior_sdf([0, 0, 0], hi), [0, 0, 0], hi, l0 / 2).save(folder)
    return folder


# -- the horizontal jet: volume and trajectory --------------------------------------------------------
JET_L0 = 0.01
JET = {"center": [0.03, 0.05, 0.3], "direction": [1, 0, 0], "radius": 0.02, "speed": 2.0, "start": 0.02, "end": 0.32}
JET_FPS = 25
JET_SCENE = {
    "scene": {"name": "jet", "frames": {"fps": JET_FPS, "count": 10}, "units": {"up_axis": "Z"}},
    "fluid": {"spacing": JET_L0, "inflow": [JET]},  # no initial fluid: the scene fills from the jet
    "effects": WATER,
}


@pytest.fixture(scope="module", params=list(SOLVERS))
def jet_run(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp(f"jet_{request.param}")
    sdf = _tank(tmp, [0.6, 0.1, 0.4], JET_L0)
    out = run_stage(SOLVERS[request.param], tmp / "out", scene=JET_SCENE, params={"threads": 1}, inputs={"sdf": sdf})
    return request.param, out


def test_emitted_volume_is_pi_r2_v_t(jet_run):
    _, out = jet_run
    stats = ParticleMeta.load(out).stats
    exact = math.pi * JET["radius"] ** 2 * JET["speed"] * (JET["end"] - JET["start"])
    emitted = stats["inflow_particles"] * JET_L0 ** 3
    assert abs(emitted / exact - 1.0) < 0.01, (emitted, exact)
    # the layer count is the rounded (t1 - t0) / T: never more than half a layer from the exact volume
    jet = Inflow(center=JET["center"], direction=JET["direction"], radius=JET["radius"], speed=JET["speed"],
                 start=JET["start"], end=JET["end"], l0=JET_L0)
    assert stats["inflow_layers"] == [math.ceil((JET["end"] - JET["start"]) / jet.period - 0.5)]
    assert stats["inflow_skipped_layers"] == [0] and stats["sunk"] == 0 and stats["left_domain"] == 0
    assert abs(stats["inflow_particles"] - exact / JET_L0 ** 3) <= 0.5 * len(jet.disc)
    # stable ids: fresh ones for every layer, never reused, each particle kept from frame to frame
    seen = np.zeros(0, np.int32)
    for f in range(JET_SCENE["scene"]["frames"]["count"]):
        ids = load_particle_frame(out, f).id
        assert len(np.unique(ids)) == len(ids)
        assert np.isin(seen, ids).all()
        seen = ids
    assert np.array_equal(np.sort(seen), np.arange(stats["inflow_particles"]))


def test_jet_follows_the_ballistic_parabola(jet_run):
    """Each particle of a free jet flies on z = z0 - g X^2 / (2 v^2) (X the distance from the nozzle) until it
    spreads at the floor (the jet reaches it at X ~ 0.5 m): the centroid of the jet particles in slices
    X +- l0 / 2 is there within l0 + 3 % of the drop, at t = 0.28 s (the jet is steady up to X = 0.5 m)."""
    name, out = jet_run
    f = load_particle_frame(out, 7)  # t = 0.28 s
    x0, z0 = JET["center"][0], JET["center"][2]
    for X in (0.05, 0.1, 0.2, 0.3):
        drop = G * X ** 2 / (2.0 * JET["speed"] ** 2)
        sl = np.abs(f.x[:, 0] - x0 - X) <= JET_L0 / 2
        sl &= f.x[:, 2] > 0.1  # not the puddle spreading on the floor
        assert sl.sum() >= 5, (name, X, sl.sum())
        z = float(f.x[sl, 2].mean())
        assert abs(z - (z0 - drop)) <= JET_L0 + 0.03 * drop, (name, X, z, z0 - drop)
