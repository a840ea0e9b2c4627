"""wall_snap.distance: a fluid box in a box tank ends flat on the walls (exact distance, not the grid)."""
from __future__ import annotations

import numpy as np

from pipeline.testing import run_stage
from stages.common.formats import WallMesh, load_surface
from stages.common.meshes import face_normals
from stages.common.sdf import SDFGrid, box_interior_sdf, grid_from_function
from stages.simulate.emitters import lattice
from stages.surface_extract.marching_cubes import MarchingCubes
from stages.wall_snap.distance import DistanceSnap, DistanceSnapParams, snap_mesh

from test_surface_extract import L0, SCENE, particles

LO, HI = np.zeros(3), np.array([0.2, 0.2, 0.2])


def tank_walls(folder):
    """The tank as a wall mesh (the exact geometry the SDF was made from)."""
    import trimesh

    box = trimesh.creation.box(bounds=[LO, HI])
    box.invert()  # a container: normals into the fluid
    folder.mkdir()
    WallMesh(np.asarray(box.vertices), np.asarray(box.faces, np.int32), np.zeros(len(box.faces), np.int32),
             [{"name": "tank", "fluid": "inside"}]).save(folder)
    return folder


def test_box_in_tank_snaps_flat_onto_the_walls(tmp_path):
    x = lattice([0, 0, 0], [0.2, 0.2, 0.1], L0)  # fills the tank's floor, half its height
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    exact = box_interior_sdf(LO, HI)
    sdf = grid_from_function(exact, LO, HI, L0 / 2, band=4 * L0)
    (tmp_path / "sdf").mkdir()
    sdf.save(tmp_path / "sdf")
    raw_dir = run_stage(MarchingCubes, tmp_path / "raw", scene=SCENE, inputs={"particles": src}, frames=(0,))
    snap_dir = run_stage(DistanceSnap, tmp_path / "snap", scene=SCENE, frames=(0,),
                         inputs={"raw_surface": raw_dir, "sdf": tmp_path / "sdf", "particles": src})
    raw, snapped = load_surface(raw_dir, 0), load_surface(snap_dir, 0)
    v0, v1 = raw.vertices.astype(np.float64), snapped.vertices.astype(np.float64)
    d0, d1 = exact(v0), exact(v1)
    band = d0 < 0.9 * L0  # strictly inside the snap band (1 l0): its edge is a tie
    assert band.sum() > 500 and (np.abs(d0[band]) > 0.05 * L0).any()  # the raw surface floats off the wall
    # away from the tank's edges every snapped vertex lies on the wall to 1e-3 l0 from the SDF alone;
    # in the concave edges the flip guard may hold a few back
    walls_near = (np.minimum(v1 - LO, HI - v1) < L0).sum(axis=1)
    flat = band & (walls_near == 1)
    assert flat.sum() > 200
    assert np.abs(d1[flat]).max() < 1e-3 * L0
    assert np.abs(d1[band]).max() < 0.5 * L0
    assert d1.min() > -1e-3 * L0  # nothing inside the wall
    # with the wall mesh, every vertex of the band (edges too) ends on the exact wall, except the few
    # the flip guard held back (at the contact line in the tank's corners)
    walls = WallMesh.load(tank_walls(tmp_path / "walls"))
    on_mesh, report = snap_mesh(raw, SDFGrid.load(tmp_path / "sdf"), L0, DistanceSnapParams(), walls)
    v2 = on_mesh.vertices.astype(np.float64)
    d2 = exact(v2)
    off = band & (np.abs(d2) > 1e-3 * L0)
    assert off.sum() <= report["damped"] and off.sum() < 0.01 * band.sum()
    assert d2.min() > -1e-3 * L0
    assert (np.einsum("ij,ij->i", face_normals(v0, raw.faces), face_normals(v2, raw.faces)) >= 0).all()
    # the floor is flat: every floor-band vertex at z = 0
    floor = band & (v0[:, 2] < L0)
    assert np.abs(v1[floor & (walls_near == 1), 2]).max() < 1e-3 * L0
    # no triangle flipped
    f = snapped.faces
    assert (np.einsum("ij,ij->i", face_normals(v0, f), face_normals(v1, f)) >= 0).all()
    # vertices away from the walls did not move
    far = d0 > 1.5 * L0
    assert np.allclose(v0[far], v1[far])
