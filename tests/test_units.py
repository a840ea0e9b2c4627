"""Scene units: a scene authored in centimetres simulates the same physics as the same scene in metres
(the solvers work in SI; lengths are converted on the way in and out)."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.testing import run_stage
from stages.common.formats import ParticleMeta, load_particle_frame
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHSimulate
from stages.simulate.mps import MPSSimulate
from stages.simulate.sph import SPHSimulate

from test_units_pipeline import y_to_z, z_to_y

L0 = 0.02  # metres


def scene(mpu: float, effects=None) -> dict:
    s = 1.0 / mpu  # metres -> scene units
    return {"scene": {"name": "t", "frames": {"fps": 50, "count": 6}, "units": {"up_axis": "Z", "meters_per_unit": mpu}},
            "fluid": {"spacing": L0 * s, "emitters": [{"box": {"min": [0, 0, 0], "max": [0.12 * s, 0.2 * s, 0.2 * s]}}]},
            "effects": {"gravity": {}, "viscosity": {"mu": 0.001}, **(effects or {})}}


def run(tmp_path, mpu: float, solver=SPHSimulate, params=None, effects=None):
    s = 1.0 / mpu
    hi = np.array([0.3, 0.2, 0.4]) * s
    (tmp_path / f"sdf{mpu}").mkdir()
    grid_from_function(box_interior_sdf([0, 0, 0], hi), [0, 0, 0], hi, L0 * s / 2).save(tmp_path / f"sdf{mpu}")
    return run_stage(solver, tmp_path / f"out{mpu}", scene=scene(mpu, effects), params={"threads": 1, **(params or {})},
                     inputs={"sdf": tmp_path / f"sdf{mpu}"})


@pytest.mark.parametrize("solver, params, mpu, effects", [
    (SPHSimulate, {}, 0.01, None),
    (SPHSimulate, {}, 0.001, None),
    (SPHSimulate, {"kernel": "poly6_spiky"}, 0.01, None),
    (DFSPHSimulate, {}, 0.01, None),
    (MPSSimulate, {}, 0.01, None),
], ids=["sph-cm", "sph-mm", "sph_poly6-cm", "dfsph-cm", "mps-cm"])
def test_centimetre_scene_moves_like_the_metre_scene(tmp_path, solver, params, mpu, effects):
    metres, other = run(tmp_path, 1.0, solver, params, effects), run(tmp_path, mpu, solver, params, effects)
    k = 1.0 / mpu  # metres -> scene units
    assert ParticleMeta.load(other).spacing == pytest.approx(ParticleMeta.load(metres).spacing * k, rel=1e-12)
    a, b = load_particle_frame(metres, 5), load_particle_frame(other, 5)
    order_a, order_b = np.argsort(a.id), np.argsort(b.id)
    fall = np.abs(a.x[:, 2] - load_particle_frame(metres, 0).x[:, 2]).max()
    assert fall > 0.5 * L0  # the column has started to collapse: the comparison means something
    np.testing.assert_allclose(b.x[order_b] / k, a.x[order_a], atol=1e-3 * L0)
    np.testing.assert_allclose(b.v[order_b] / k, a.v[order_a], atol=1e-3)
    np.testing.assert_allclose(b.rho[order_b], a.rho[order_a], rtol=1e-4)  # kg/m^3 either way


@pytest.mark.parametrize("solver, mpu", [(SPHSimulate, 0.01), (DFSPHSimulate, 0.001)], ids=["sph-cm", "dfsph-mm"])
def test_surface_tension_moves_alike_in_every_unit(tmp_path, solver, mpu):
    """Akinci's curvature term -K_ij (n_i - n_j) has no distance weight: it steps at r = h, and h = 2 l0 is
    where the start lattice's second neighbours sit. Rounding of x * meters_per_unit put each such pair in or
    out: the first step's acceleration differed by 0.13 m/s^2 on half the particles, and the metre and
    centimetre runs of one scene parted by 0.02 l0 at 0.1 s and 5 l0 at 0.3 s. (A 1 cm block thrown at
    0.3 m/s in a 30 x 16 x 20 cm tank, water's tension and adhesion.)"""
    l0 = 0.01

    def one(mpu):
        s = 1.0 / mpu
        lo, hi = np.array([-0.15, -0.08, 0.0]) * s, np.array([0.15, 0.08, 0.2]) * s
        (tmp_path / f"sdf{mpu}").mkdir()
        grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 * s / 2).save(tmp_path / f"sdf{mpu}")
        sc = {"scene": {"name": "t", "frames": {"fps": 50, "count": 6}, "units": {"up_axis": "Z", "meters_per_unit": mpu}},
              "fluid": {"spacing": l0 * s, "emitters": [{"box": {"min": [-0.1 * s, -0.05 * s, 0], "max": [0, 0.05 * s, 0.1 * s]},
                                                        "velocity": [0.3 * s, 0, 0]}]},
              "effects": {"gravity": {}, "viscosity": {"mu": 0.001}, "surface_tension": {"gamma": 0.0728},
                          "wall_adhesion": {"beta": 1.0}}}
        return run_stage(solver, tmp_path / f"out{mpu}", scene=sc, params={"threads": 1}, inputs={"sdf": tmp_path / f"sdf{mpu}"})

    metres, other = one(1.0), one(mpu)
    a, b = load_particle_frame(metres, 5), load_particle_frame(other, 5)
    order_a, order_b = np.argsort(a.id), np.argsort(b.id)
    assert np.abs(a.x[order_a] - load_particle_frame(metres, 0).x[np.argsort(load_particle_frame(metres, 0).id)]).max() > 2 * l0
    np.testing.assert_allclose(b.x[order_b] * mpu, a.x[order_a], atol=1e-4 * l0)


def test_a_box_far_from_the_origin_gets_the_same_lattice():
    """The emitter lattice's count tolerance grows with the coordinates: a 0.2 m box 1e7 m off the origin
    lost a row (7 columns instead of 8), as (hi - lo) there is off by about 1e-9 m."""
    from stages.simulate.emitters import lattice

    near = lattice([-0.1, 0.0, 0.0], [0.1, 0.2, 0.2], 0.025)
    for offset in (1e3, 1e5, 1e7, -1e7):
        far = lattice([offset - 0.1, 0.0, 0.0], [offset + 0.1, 0.2, 0.2], 0.025)
        assert len(far) == len(near) == 512
        np.testing.assert_allclose(far - [offset, 0, 0], near, atol=1e-8)


def test_a_box_typed_in_feet_to_six_digits_keeps_every_layer():
    """The metre scene's box (8 x 10 x 8 spacings of 2 cm) converted to feet and typed to 6-7 digits, as a
    person converting it would: 7.999994 spacings long; it lost a layer (490 particles instead of 640)."""
    from stages.simulate.emitters import lattice

    metres = lattice([-0.2, -0.1, 0.0], [-0.04, 0.1, 0.16], 0.02)
    feet = lattice([-0.656168, -0.328084, 0.0], [-0.131234, 0.328084, 0.524934], 0.0656168)
    assert len(metres) == len(feet) == 640
    np.testing.assert_allclose(feet * 0.3048, metres, atol=1e-5 * 0.02)


@pytest.mark.parametrize("flip", [False, True])
def test_an_open_or_inside_out_mesh_emitter_fills_to_its_rim(tmp_path, caplog, flip):
    """Mesh emitters fill by the generalized winding number: an open box (no lid) fills up to its rim
    (open3d's three-ray vote filled it in an irregular pattern of layers, silently), inside-out faces fill
    the same, and an open mesh is named in a warning."""
    import logging

    import trimesh

    from pipeline.scene import Fluid
    from stages.simulate.emitters import emit

    box = trimesh.creation.box(bounds=[[0, 0, 0], [0.1, 0.06, 0.08]])
    open_box = trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.5])  # the lid removed
    if flip:
        open_box.invert()
    open_box.export(tmp_path / "open.obj")
    fluid = Fluid.model_validate({"spacing": L0, "emitters": [{"mesh": "open.obj"}]})
    with caplog.at_level(logging.WARNING):
        x, _ = emit(fluid.emitters, L0, lambda p: tmp_path / p, meters_per_unit=1.0)
    assert len(x) == 5 * 3 * 4  # every lattice point of the box, all four layers
    assert "open.obj is not closed" in caplog.text


@pytest.mark.parametrize("scene_up", ["Z", "Y"])
def test_a_usd_emitter_in_centimetres_y_up_fills_the_same_block(tmp_path, scene_up):
    """A fluid volume handed over as USD (centimetres, Y up, its mesh under a translated parent, quads) fills
    the block a box emitter fills in a metre scene: the file's metersPerUnit, upAxis and transforms apply."""
    from pxr import Gf, Usd, UsdGeom

    from pipeline.scene import Fluid
    from stages.simulate.emitters import emit

    stage = Usd.Stage.CreateNew(str(tmp_path / "water.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.Xform.Define(stage, "/Set").AddTranslateOp().Set(Gf.Vec3d(0, 0, -6))
    cube = UsdGeom.Mesh.Define(stage, "/Set/Water")
    corners = [(x, y, z) for x in (0, 10) for y in (0, 8) for z in (0, 6)]  # cm, Y-up: 10 x 6 x 8 in metres Z-up
    cube.GetPointsAttr().Set([Gf.Vec3f(*c) for c in corners])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    cube.GetFaceVertexCountsAttr().Set([4] * 6)
    cube.GetFaceVertexIndicesAttr().Set([i for q in quads for i in q])
    stage.GetRootLayer().Save()
    fluid = Fluid.model_validate({"spacing": L0, "emitters": [{"mesh": "water.usda", "prims": ["/Set/Water"]}]})
    box = Fluid.model_validate({"spacing": L0, "emitters": [{"box": {"min": [0, 0, 0], "max": [0.1, 0.06, 0.08]}}]})
    x, _ = emit(fluid.emitters, L0, lambda p: tmp_path / p, meters_per_unit=1.0, up_axis=scene_up)
    y, _ = emit(box.emitters, L0, lambda p: tmp_path / p, meters_per_unit=1.0)
    if scene_up == "Y":  # the metre block, turned into the Y-up scene: (x, y, z) -> (x, z, -y)
        y = np.c_[y[:, 0], y[:, 2], -y[:, 1]]
    assert len(x) == 5 * 3 * 4
    np.testing.assert_allclose(np.sort(x, axis=0), np.sort(y, axis=0), atol=1e-9)


def test_a_usd_emitter_with_meters_per_unit_is_a_config_error():
    from pydantic import ValidationError

    from pipeline.scene import Fluid

    with pytest.raises(ValidationError, match="a USD file states its own"):
        Fluid.model_validate({"spacing": L0, "emitters": [{"mesh": "water.usdc", "meters_per_unit": 0.01}]})


def test_mesh_emitter_file_in_other_units_is_converted(tmp_path):
    """A mesh emitter's file in centimetres (meters_per_unit: 0.01) fills the same region of a metre
    scene as a box emitter does, like a wall file in other units."""
    import trimesh

    from pipeline.scene import Fluid
    from stages.simulate.emitters import emit

    trimesh.creation.box(bounds=[[0, 0, 0], [10, 6, 8]]).export(tmp_path / "block_cm.stl")
    fluid = Fluid.model_validate({"spacing": L0, "emitters": [{"mesh": "block_cm.stl", "meters_per_unit": 0.01}]})
    box = Fluid.model_validate({"spacing": L0, "emitters": [{"box": {"min": [0, 0, 0], "max": [0.1, 0.06, 0.08]}}]})
    x, _ = emit(fluid.emitters, L0, lambda p: tmp_path / p, meters_per_unit=1.0)
    y, _ = emit(box.emitters, L0, lambda p: tmp_path / p, meters_per_unit=1.0)
    assert len(y) == 5 * 3 * 4
    np.testing.assert_allclose(np.sort(x, axis=0), np.sort(y, axis=0), atol=1e-9)


@pytest.mark.parametrize("solver", ["mps", "dfsph"])
def test_a_y_up_dam_break_steps_like_the_z_up_one_to_rounding(solver):
    """The solvers take the scene's axes as they are (gravity along its up axis), so a Y-up scene is the Z-up
    one turned by 90 degrees: its first steps must agree with the Z-up ones to float64 rounding. The flow is
    chaotic (a difference grows about 1e8 x in a 0.3 s dam break), so anything bigger from the start ends up
    particle spacings apart: MPS summed its wall maps in float32 in stencil order, which differs with the axes, and
    was 5e-8 l0 off after these six steps (3 l0 after 0.3 s in a 2250-particle dam break); with the maps summed in
    float64 it is 2e-15 l0 (2e-8 l0 after 0.3 s)."""
    import numba as nb

    from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
    from stages.simulate.emitters import lattice
    from stages.simulate.mps import MPSParams, MPSSolver

    l0, g = 0.02, 9.81
    lo, hi = np.array([-0.2, -0.06, 0.0]), np.array([0.2, 0.06, 0.24])  # the tank, symmetric about y = 0
    x = lattice([-0.2, -0.06, 0.0], [-0.08, 0.06, 0.16], l0)  # the water column at its -x end
    cls, params = (MPSSolver, MPSParams()) if solver == "mps" else (DFSPHSolver, DFSPHParams())
    out = {}
    before = nb.get_num_threads()
    nb.set_num_threads(1)
    try:
        for up in ("Z", "Y"):
            turn = z_to_y if up == "Y" else np.asarray
            a, b = turn(lo), turn(hi)
            a, b = np.minimum(a, b), np.maximum(a, b)
            # padded like a baked SDF: the wall maps' staggered lattice ends dq / 2 past the grid on the high side
            # only, so a wall within the stencil's reach of the grid's border is summed differently per side
            sdf = grid_from_function(box_interior_sdf(a, b), a - 3 * l0, b + 3 * l0, l0 / 2)
            gravity = turn(np.array([0.0, 0.0, -g]))
            s = cls(turn(x), np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=params,
                    gravity=gravity, mu=1e-3, wall_viscosity=True)
            for _ in range(6):
                s.step(1.0)
            back = y_to_z if up == "Y" else np.asarray
            order = np.argsort(s.id)
            out[up] = (back(s.x[order]), back(s.v[order]), s.t)
    finally:
        nb.set_num_threads(before)
    (xz, vz, tz), (xy, vy, ty) = out["Z"], out["Y"]
    assert ty == tz
    assert np.abs(vz).max() > 0.1  # the column has started to fall
    assert np.abs(xy - xz).max() < 1e-10 * l0
    assert np.abs(vy - vz).max() < 1e-10 * np.abs(vz).max()
