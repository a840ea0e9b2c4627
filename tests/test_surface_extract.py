"""surface_extract.marching_cubes: closed surfaces of the right size and volume from particles."""
from __future__ import annotations

import numpy as np

from pipeline.testing import run_stage
from stages.common.formats import ParticleFrame, ParticleMeta, load_surface, save_particle_frame
from stages.common.meshes import boundary_edge_count, signed_volume
from stages.simulate.emitters import lattice
from stages.simulate.kernels import lattice_mass
from stages.surface_extract.marching_cubes import MarchingCubes

L0 = 0.02
SCENE = {"scene": {"name": "t", "frames": {"fps": 10, "count": 2}}}


def particles(folder, frames: list[np.ndarray], mpu: float = 1.0):
    """Particle frames ``frames`` in scene units of ``mpu`` metres (spacing L0 metres; mass kg)."""
    m = lattice_mass(1000.0, L0, 2 * L0)
    ParticleMeta(spacing=L0 / mpu, mass=m, density=1000.0, support=2 * L0 / mpu, fps=10, frame_count=len(frames),
                 up_axis="Z", meters_per_unit=mpu, solver="test").save(folder)
    for i, x in enumerate(frames):
        n = len(x)
        save_particle_frame(folder, i, ParticleFrame(x=x, v=np.zeros((n, 3)), rho=np.full(n, 1000.0),
                                                     p=np.zeros(n), id=np.arange(n)))
    return folder


def test_sphere_of_particles_gives_closed_sphere_and_right_volume(tmp_path):
    x = lattice([-0.2, -0.2, -0.2], [0.2, 0.2, 0.2], L0)
    x = x[np.linalg.norm(x, axis=1) < 0.15]
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x, np.zeros((0, 3))])
    out = run_stage(MarchingCubes, tmp_path / "s", scene=SCENE, inputs={"particles": src}, frames=(0, 1))
    mesh = load_surface(out, 0)
    v = mesh.vertices.astype(np.float64)
    assert len(mesh.faces) > 1000 and boundary_edge_count(mesh.faces) == 0
    r = np.linalg.norm(v, axis=1)
    # the lattice points reach radius 0.15 - l0/2 on average: the surface sits within half a spacing of 0.15
    assert abs(r.mean() - 0.15) < 0.5 * L0 and r.std() < 0.25 * L0
    vol = signed_volume(v, mesh.faces)
    assert vol > 0  # outward orientation
    assert abs(vol / (len(x) * L0 ** 3) - 1) < 0.05
    # normals point outwards
    assert (np.einsum("ij,ij->i", mesh.normals, v / r[:, None]) > 0.9).mean() > 0.99
    # an empty frame gives an empty mesh, not an error
    empty = load_surface(out, 1)
    assert len(empty.vertices) == 0 and len(empty.faces) == 0


def test_centimetre_and_millimetre_scenes_enclose_the_metre_scenes_volume(tmp_path):
    """Particle volumes m / rho are m^3; the stage must use them in scene units^3 (issue 16: a cm scene
    had Phi ~ 1e-6 everywhere and an empty surface)."""
    x = lattice([-0.2, -0.2, -0.2], [0.2, 0.2, 0.2], L0)
    x = x[np.linalg.norm(x, axis=1) < 0.15]
    volumes = {}
    for mpu in (1.0, 0.01, 0.001):
        (tmp_path / f"p{mpu}").mkdir()
        src = particles(tmp_path / f"p{mpu}", [x / mpu], mpu)
        mesh = load_surface(run_stage(MarchingCubes, tmp_path / f"s{mpu}", scene=SCENE, inputs={"particles": src},
                                      frames=(0,)), 0)
        assert len(mesh.faces) > 1000
        volumes[mpu] = signed_volume(mesh.vertices.astype(np.float64), mesh.faces) * mpu ** 3  # m^3
    assert abs(volumes[1.0] / (len(x) * L0 ** 3) - 1) < 0.05
    assert abs(volumes[0.01] / volumes[1.0] - 1) < 0.01 and abs(volumes[0.001] / volumes[1.0] - 1) < 0.01


def test_wall_term_puts_the_raw_surface_on_the_walls(tmp_path):
    """With the SDF upstream, the fluid's contact with the walls lies on them already (mirror particles
    carry the wall's share of Phi, and the fluid is cut at d = 0); without it the surface crosses the walls
    (the summed volumes of the outer layer put it about l0/2 out, give or take) and rounds the tank's edges."""
    from stages.common.sdf import box_interior_sdf, grid_from_function

    lo, hi = np.zeros(3), np.array([0.2, 0.2, 0.2])
    x = lattice(lo, [0.2, 0.2, 0.1], L0)  # fills the tank's floor, half its height
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    exact = box_interior_sdf(lo, hi)
    (tmp_path / "sdf").mkdir()
    grid_from_function(exact, lo, hi, L0 / 2, band=4 * L0).save(tmp_path / "sdf")
    with_wall = run_stage(MarchingCubes, tmp_path / "w", scene=SCENE, frames=(0,),
                          inputs={"particles": src, "sdf": tmp_path / "sdf"})
    without = run_stage(MarchingCubes, tmp_path / "n", scene=SCENE, frames=(0,), inputs={"particles": src})
    results = {}
    for name, out in (("wall", with_wall), ("none", without)):
        mesh = load_surface(out, 0)
        v = mesh.vertices.astype(np.float64)
        assert boundary_edge_count(mesh.faces) == 0
        d = exact(v)
        contact_line = (v[:, 2] > 4 * L0) & (d < 1.5 * L0)  # where the free surface (z = 5 l0) meets a side wall
        results[name] = (float(d[contact_line].min()), signed_volume(v, mesh.faces) / (len(x) * L0**3), float(d.min()))
    # measured: contact line 0 vs -0.06 l0 (in the wall); volume 0.973 vs 0.945 of N l0^3 (the flat top
    # 0.07 l0 low on this exact lattice, 1.3 % of 5 layers)
    assert abs(results["wall"][0]) < 0.01 * L0 and results["none"][0] < -0.02 * L0
    assert abs(results["wall"][1] - 1.0) < 0.03 and results["none"][1] < results["wall"][1] - 0.01
    assert results["wall"][2] > -1e-3 * L0  # the cut keeps the surface out of the walls


def test_a_kept_grid_buffer_leaves_nothing_of_the_last_frame():
    """The grid buffer is kept across frames (marching_cubes.grid_buffer) and not cleared between them: a small
    frame after a large one, in the same buffer filled with leftovers, is the same surface as with a fresh
    buffer (isotropic and anisotropic), and the number of threads (numba's and VTK's) does not change it."""
    import numba as nb

    from stages.surface_extract import marching_cubes as mc

    rng = np.random.default_rng(4)
    big = rng.uniform(0.0, 1.0, (4000, 3))  # a cloud: a large grid full of values
    small = lattice([0.0, 0.0, 0.0], [0.2, 0.16, 0.12], L0) + rng.uniform(-0.1, 0.1, (480, 3)) * L0
    vol = np.full(len(small), L0 ** 3)
    for anisotropic in (False, True):
        params = mc.MarchingCubesParams(cell=0.25, anisotropic=anisotropic)
        mc._kept.phi = None
        fresh = mc.extract(small, vol, L0, params)
        mc.extract(big, np.full(len(big), L0 ** 3), L0, params)
        assert mc._kept.phi.size > 100 * len(small)  # the big grid's buffer is the one reused
        mc._kept.phi[:] = 7.0  # whatever a last frame left anywhere in it
        threads = nb.get_num_threads()
        nb.set_num_threads(1)
        try:
            again = mc.extract(small, vol, L0, params)
        finally:
            nb.set_num_threads(threads)
        assert np.array_equal(again.faces, fresh.faces)
        assert np.array_equal(again.vertices, fresh.vertices)


def test_no_water_appears_behind_a_wall_thinner_than_the_kernel(tmp_path):
    """Water resting on a plate 1 l0 thick (an open box's side, a shell is 0.6 l0): the wall term's mirror
    images lay past the plate, and a slab of water 100 l0^3 big appeared under it (a user's sweep: 1.19 x
    the particles' volume; under the shipped open bowl, 0.38 x). Nothing is under the plate now, and a
    plate 4 l0 thick keeps its mirror images (the raw surface on the plate)."""
    from stages.common.sdf import grid_from_function

    x = lattice([0.0, 0.0, 0.1], [0.2, 0.2, 0.16], L0)  # 3 layers on the plate's top (z = 0.1)
    (tmp_path / "p").mkdir()
    src = particles(tmp_path / "p", [x])
    found = {}
    for thick in (1.0, 4.0):
        def plate(p, t=thick * L0):  # a slab z in [0.1 - t, 0.1], unbounded across: exact distance
            return np.abs(p[:, 2] - (0.1 - t / 2)) - t / 2

        sdf = tmp_path / f"sdf{thick}"
        sdf.mkdir()
        grid_from_function(plate, [-0.1, -0.1, -0.1], [0.3, 0.3, 0.3], L0 / 2, band=4 * L0).save(sdf)
        out = run_stage(MarchingCubes, tmp_path / f"s{thick}", scene=SCENE, frames=(0,),
                        inputs={"particles": src, "sdf": sdf})
        mesh = load_surface(out, 0)
        v = mesh.vertices.astype(np.float64)
        found[thick] = (float(v[:, 2].min()), signed_volume(v, mesh.faces) / (len(x) * L0 ** 3),
                        boundary_edge_count(mesh.faces))
    bottom, ratio, open_edges = found[1.0]
    assert bottom > 0.1 - 0.01 * L0 and open_edges == 0  # nothing under the plate, closed
    assert 0.85 < ratio < 1.05
    bottom, ratio, _ = found[4.0]
    assert abs(bottom - 0.1) < 0.01 * L0 and 0.95 < ratio < 1.05  # mirror images put it on the plate
