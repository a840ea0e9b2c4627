"""simulate.sph as a stage: output format, dropped particles, resume-from-checkpoint equality."""
import logging
import shutil
from pathlib import Path

import numpy as np

from pipeline.stage import Artifact, Context
from pipeline.testing import run_stage, scene_sections, stage_context
from stages.common.formats import ParticleMeta, load_particle_frame
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.sph import SPHSimulate

L0 = 0.02


def _sdf(tmp: Path) -> Path:
    folder = tmp / "sdf"
    folder.mkdir()
    grid_from_function(box_interior_sdf([0, 0, 0], [0.3, 0.2, 0.4]), [0, 0, 0], [0.3, 0.2, 0.4], L0 / 2).save(folder)
    return folder


SCENE = {
    "scene": {"name": "t", "frames": {"fps": 50, "count": 7}, "units": {"up_axis": "Z"}},
    "fluid": {"spacing": L0, "emitters": [{"box": {"min": [-0.04, 0, 0], "max": [0.12, 0.2, 0.2]}}]},
    "effects": {"gravity": {}, "viscosity": {"mu": 0.01}},
}


def _ctx(out: Path, ckpt: Path | None) -> Context:
    sections = scene_sections(SCENE)
    return stage_context(SPHSimulate, out, scene=sections, frames=tuple(range(7)), log=logging.getLogger("t"),
                         checkpoint_dir=ckpt)


def test_stage_writes_frames_meta_usd_and_drops_particles_in_walls(tmp_path, caplog):
    sdf = _sdf(tmp_path)
    with caplog.at_level(logging.WARNING):
        out = run_stage(SPHSimulate, tmp_path / "out", scene=SCENE, params={"threads": 1}, inputs={"sdf": sdf})
    meta = ParticleMeta.load(out)
    # the box starts 0.04 behind the x = 0 wall: two lattice columns (8 x 10 x 2 per column) are dropped
    assert meta.stats["dropped_in_wall"] == 2 * 10 * 10
    assert "dropped 200" in caplog.text
    f0 = load_particle_frame(out, 0)
    f6 = load_particle_frame(out, 6)
    assert len(f0) == 6 * 10 * 10
    assert np.array_equal(np.sort(f6.id), np.arange(len(f0)))
    assert f6.x[:, 2].min() > 0.0  # nothing below the floor
    assert (out / "particles.usdc").stat().st_size > 0
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.Open(str(out / "particles.usdc"))
    pts = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    assert len(pts.GetPointsAttr().Get(6)) == len(f6)
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and stage.GetEndTimeCode() == 6


def test_resume_from_checkpoint_is_bitwise_identical(tmp_path):
    sdf = _sdf(tmp_path)
    arts = {"sdf": Artifact(name="sdf", key="t", path=sdf)}
    params = SPHSimulate.Params(threads=1, checkpoint_every=2)
    straight = tmp_path / "straight"
    straight.mkdir()
    SPHSimulate().run(_ctx(straight, tmp_path / "ck_straight"), arts, params)
    # an interrupted run: keep only what existed after frame 4's checkpoint, then run again
    ck = tmp_path / "ck"
    shutil.copytree(tmp_path / "ck_straight", ck)
    for p in ck.glob("state_*.npz"):
        if p.name != "state_00004.npz":
            p.unlink()
    for f in (5, 6):
        (ck / "frames" / f"{f:05d}.npz").unlink(missing_ok=True)
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    SPHSimulate().run(_ctx(resumed, ck), arts, params)
    for f in range(7):
        a, b = load_particle_frame(straight, f), load_particle_frame(resumed, f)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and np.array_equal(a.id, b.id)
