"""render.pyvista and movie.ffmpeg on synthetic walls, surfaces and particles (no upstream stages)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from PIL import Image

from pipeline.stage import StageError
from pipeline.testing import run_stage
from stages.common.formats import (ParticleFrame, ParticleMeta, SurfaceMesh, WallMesh, save_particle_frame,
                                   save_surface)
from stages.movie.ffmpeg_movie import FfmpegMovie
from stages.render.pyvista_render import PyvistaRender

FRAMES = 3
SCENE = {"scene": {"name": "t", "frames": {"fps": 10, "count": FRAMES}}}
SPHERE_CENTRE = np.array([-0.6, 0.0, 0.5])
SPHERE_RADIUS = 0.3


def make_walls(folder):
    """A closed 2 x 1 x 1 tank (fluid inside), floor at z = 0."""
    box = trimesh.creation.box(extents=(2.0, 1.0, 1.0))
    box.apply_translation((0, 0, 0.5))
    WallMesh(box.vertices, box.faces, np.zeros(len(box.faces), np.int32),
             [{"name": "tank", "fluid": "inside", "source": "builtin:box_tank"}]).save(folder)
    return folder


def make_surfaces(folder, frames=FRAMES):
    ball = trimesh.creation.icosphere(subdivisions=3, radius=SPHERE_RADIUS)
    ball.apply_translation(SPHERE_CENTRE)
    for f in range(frames):
        save_surface(folder, f, SurfaceMesh(ball.vertices, ball.faces, ball.vertex_normals))
    return folder


def make_particles(folder, frames=FRAMES):
    rng = np.random.default_rng(1)
    ParticleMeta(spacing=0.05, mass=0.125, density=1000.0, support=0.1, fps=10, frame_count=frames,
                 up_axis="Z", meters_per_unit=1.0, solver="synthetic").save(folder)
    for f in range(frames):
        n = 500 + 10 * f  # the count may change between frames
        x = SPHERE_CENTRE + rng.uniform(-0.25, 0.25, (n, 3))
        save_particle_frame(folder, f, ParticleFrame(x, rng.normal(size=(n, 3)), np.full(n, 1000.0),
                                                     rng.uniform(0, 5000, n), np.arange(n)))
    return folder


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("render_inputs")
    walls, surf, parts = (root / n for n in ("walls", "surface", "particles"))
    for d in (walls, surf, parts):
        d.mkdir()
    return {"walls": make_walls(walls), "surface": make_surfaces(surf), "particles": make_particles(parts)}


def water_mask(img: np.ndarray) -> np.ndarray:
    """Pixels of the light-blue water material (walls are grey, the background dark grey)."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (b - r > 40) & (b > 110)


def test_input_names_follow_show():
    assert PyvistaRender().input_names(PyvistaRender.Params(show="surface")) == ("walls", "surface", "particles")
    assert PyvistaRender().input_names(PyvistaRender.Params(show="particles")) == ("walls", "particles")


EYE = np.array([0.0, -5.0, 0.5])


def assert_sphere_seen_from_eye(img, fov=30.0, eye=EYE):
    """Water pixels where the perspective projection of the sphere seen from ``eye`` (looking +y) falls."""
    h, w = img.shape[:2]
    assert img.shape == (h, w, 3)
    mask = water_mask(img)
    # where the sphere should be: perspective projection of its centre and radius
    focal = (h / 2) / math.tan(math.radians(fov) / 2)
    depth = SPHERE_CENTRE[1] - eye[1]
    u = w / 2 + focal * SPHERE_CENTRE[0] / depth
    v = h / 2 - focal * (SPHERE_CENTRE[2] - eye[2]) / depth
    r_px = focal * SPHERE_RADIUS / math.sqrt(depth**2 - SPHERE_RADIUS**2)
    ys, xs = np.nonzero(mask)
    assert len(xs) > 0.6 * math.pi * r_px**2, "too few water pixels: the fluid inside the tank is hidden"
    assert len(xs) < 1.3 * math.pi * r_px**2
    assert abs(xs.mean() - u) < 0.15 * r_px and abs(ys.mean() - v) < 0.15 * r_px
    # the far wall of the tank is drawn (grey, brighter than the background) around the sphere
    grey = (np.abs(img[..., 0].astype(int) - img[..., 2]) < 12) & (img[..., 0] > 70)
    assert grey.mean() > 0.2


def test_surface_frame_shows_water_where_the_sphere_is(tmp_path, inputs):
    import imageio.v3 as iio

    scene = {**SCENE, "camera": {"position": EYE.tolist(), "focal_point": [0, 0, 0.5], "up": [0, 0, 1],
                                 "view_angle": 30.0}}
    out = run_stage(PyvistaRender, tmp_path, scene=scene, params={"resolution": [320, 240]}, inputs=inputs,
                    frames=(1,))
    img = iio.imread(out / "frame_00001.png")[..., :3]
    assert img.shape == (240, 320, 3)
    assert_sphere_seen_from_eye(img)


def test_camera_from_a_y_up_centimetre_usd_file(tmp_path, inputs):
    """The same view as above, authored as a studio camera prim: Y-up, centimetres."""
    import imageio.v3 as iio
    from pxr import Gf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "shot_cam.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    cam = UsdGeom.Camera.Define(stage, "/Shot/Cam")
    # scene (x, y, z) Z-up metres -> (x, z, -y) Y-up centimetres
    view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(0, 50, 500), Gf.Vec3d(0, 50, 0), Gf.Vec3d(0, 1, 0))
    cam.AddTransformOp().Set(view.GetInverse())
    cam.CreateVerticalApertureAttr(20.25)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateFocalLengthAttr(20.25 / (2 * math.tan(math.radians(15))))
    stage.GetRootLayer().Save()
    scene = {**SCENE, "camera": {"usd": "shot_cam.usda", "prim": "/Shot/Cam"}}
    out = run_stage(PyvistaRender, tmp_path / "out", scene=scene, params={"resolution": [320, 240]}, inputs=inputs,
                    frames=(0,), config_dir=tmp_path)
    assert_sphere_seen_from_eye(iio.imread(out / "frame_00000.png")[..., :3])
    with pytest.raises(StageError, match="/Shot/Nope"):
        run_stage(PyvistaRender, tmp_path / "bad", scene={**SCENE, "camera": {"usd": "shot_cam.usda", "prim": "/Shot/Nope"}},
                  inputs=inputs, frames=(0,), config_dir=tmp_path, params={"resolution": [64, 48]})


def test_an_animated_usd_camera_is_read_at_each_frames_time(tmp_path, inputs):
    """A studio camera animated by time samples only (no default value; startTimeCode 10 at 24 codes a second):
    each frame is drawn from the pose at its own time, as the shot's time maps to the file's codes (the camera
    was read at the default time: the origin, inside the water, with no word)."""
    import imageio.v3 as iio
    from pxr import Gf, Usd, UsdGeom

    from stages.common.camera import usd_camera, usd_camera_moves

    stage = Usd.Stage.CreateNew(str(tmp_path / "anim_cam.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(24)
    stage.SetStartTimeCode(10)
    cam = UsdGeom.Camera.Define(stage, "/Shot/Cam")
    op = cam.AddTransformOp()
    good = Gf.Matrix4d().SetLookAt(Gf.Vec3d(0, 50, 500), Gf.Vec3d(0, 50, 0), Gf.Vec3d(0, 1, 0)).GetInverse()
    away = Gf.Matrix4d().SetLookAt(Gf.Vec3d(0, 50, 700), Gf.Vec3d(0, 50, 1200), Gf.Vec3d(0, 1, 0)).GetInverse()
    op.Set(good, Usd.TimeCode(10))  # t = 0: the view of the test above
    op.Set(away, Usd.TimeCode(34))  # t = 1 s: looking away from the tank
    cam.CreateVerticalApertureAttr(20.25)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateFocalLengthAttr(20.25 / (2 * math.tan(math.radians(15))))
    stage.GetRootLayer().Save()
    path = tmp_path / "anim_cam.usda"
    assert usd_camera_moves(path, "/Shot/Cam")
    eye0 = usd_camera(path, "/Shot/Cam", "Z", 1.0)[0]
    eye_half = usd_camera(path, "/Shot/Cam", "Z", 1.0, seconds=0.5)[0]
    np.testing.assert_allclose(eye0, [0.0, -5.0, 0.5], atol=1e-9)  # (x, y, z) cm Y-up -> (x, -z, y) m Z-up
    np.testing.assert_allclose(eye_half, [0.0, -6.0, 0.5], atol=1e-9)  # halfway between the two samples
    scene = {"scene": {"name": "t", "frames": {"fps": 1, "count": 2}}, "camera": {"usd": "anim_cam.usda"}}
    out = run_stage(PyvistaRender, tmp_path / "out", scene=scene, params={"resolution": [320, 240]}, inputs=inputs,
                    frames=(0, 1), config_dir=tmp_path)
    assert_sphere_seen_from_eye(iio.imread(out / "frame_00000.png")[..., :3])
    assert water_mask(iio.imread(out / "frame_00001.png")[..., :3]).sum() == 0  # at t = 1 s it looks away
    # the export carries the motion: /World/Camera at each frame's code is the pose render drew
    from stages.export.usd_export import UsdExport

    usd = run_stage(UsdExport, tmp_path / "usd", scene=scene, inputs=inputs, config_dir=tmp_path,
                    params={"particles": False})
    composed = Usd.Stage.Open(str(usd / "scene.usda"))
    exported = UsdGeom.Camera(composed.GetPrimAtPath("/World/Camera"))
    for f, seconds in ((0, 0.0), (1, 1.0)):
        eye = np.array(exported.GetCamera(Usd.TimeCode(f)).frustum.GetPosition())
        np.testing.assert_allclose(eye, usd_camera(path, "/Shot/Cam", "Z", 1.0, seconds=seconds)[0], atol=1e-6)


def test_exported_usd_camera_shows_what_the_frames_show(tmp_path, inputs):
    """Render and export share the scene's camera: rendering through the exported /World/Camera gives
    the frame the automatic camera gave."""
    import imageio.v3 as iio

    from stages.export.usd_export import UsdExport

    res = {"resolution": [320, 180]}
    auto = run_stage(PyvistaRender, tmp_path / "auto", scene=SCENE, params=res, inputs=inputs, frames=(1,))
    usd = run_stage(UsdExport, tmp_path / "usd", scene=SCENE, inputs=inputs, config_dir=tmp_path,
                    params={"particles": False, "camera_aspect": 320 / 180})
    again = run_stage(PyvistaRender, tmp_path / "again", params=res, inputs=inputs, frames=(1,), config_dir=tmp_path,
                      scene={**SCENE, "camera": {"usd": str(usd / "scene.usda"), "prim": "/World/Camera"}})
    water_a = water_mask(iio.imread(auto / "frame_00001.png")[..., :3])
    water_b = water_mask(iio.imread(again / "frame_00001.png")[..., :3])
    assert water_a.sum() > 100
    assert (water_a ^ water_b).sum() < 0.02 * water_a.sum()


def test_a_portrait_shot_set_on_the_camera_renders_and_exports_alike(tmp_path, inputs):
    """camera.resolution is the shot's size: render draws its frames at it and the exported USD camera takes
    its aspect (the USD camera was 16:9 whatever the frames were, and framed for 16:9: rendering through it
    gave another picture than the portrait frames)."""
    import imageio.v3 as iio
    from pxr import Usd, UsdGeom

    from stages.export.usd_export import UsdExport

    scene = {**SCENE, "camera": {"resolution": [180, 320]}}
    auto = run_stage(PyvistaRender, tmp_path / "auto", scene=scene, inputs=inputs, frames=(1,))
    usd = run_stage(UsdExport, tmp_path / "usd", scene=scene, inputs=inputs, config_dir=tmp_path,
                    params={"particles": False})
    stage = Usd.Stage.Open(str(usd / "scene.usda"))  # held: a prim of a dropped stage is invalid
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    aperture = cam.GetHorizontalApertureAttr().Get() / cam.GetVerticalApertureAttr().Get()
    assert aperture == pytest.approx(180 / 320)
    again = run_stage(PyvistaRender, tmp_path / "again", inputs=inputs, frames=(1,), config_dir=tmp_path,
                      scene={**SCENE, "camera": {"usd": str(usd / "scene.usda"), "prim": "/World/Camera",
                                                 "resolution": [180, 320]}})
    img_a = iio.imread(auto / "frame_00001.png")[..., :3]
    assert img_a.shape == (320, 180, 3)
    water_a, water_b = water_mask(img_a), water_mask(iio.imread(again / "frame_00001.png")[..., :3])
    assert water_a.sum() > 100
    assert (water_a ^ water_b).sum() < 0.02 * water_a.sum()


def test_auto_camera_and_particles_are_not_blank(tmp_path, inputs):
    import imageio.v3 as iio

    out = run_stage(PyvistaRender, tmp_path / "s", scene=SCENE, params={"resolution": [200, 120]},
                    inputs=inputs, frames=(0,))
    img = iio.imread(out / "frame_00000.png")[..., :3]
    assert water_mask(img).sum() > 100 and img.std() > 10
    out = run_stage(PyvistaRender, tmp_path / "p", scene=SCENE, inputs=inputs, frames=(2,),
                    params={"resolution": [200, 120], "show": "particles", "color_by": "pressure"})
    img = iio.imread(out / "frame_00002.png")[..., :3]
    assert img.std() > 10
    assert (np.abs(img.astype(int) - img[0, 0]).sum(axis=2) > 60).sum() > 200  # particles drawn


@pytest.mark.parametrize("resolution", [(240, 320), (320, 180)])
def test_a_portrait_or_small_frame_keeps_the_tank_and_the_colour_bar_inside(tmp_path, inputs, resolution):
    """The automatic camera fitted the walls in the vertical view angle only, so a portrait frame cut the
    tank's sides off; the colour bar's labels were sized to the bar and cut at the frame's right edge below
    1280 px (9.06e+03 drawn as 9.06e+). Both edges of the frame are now background, top to bottom."""
    import imageio.v3 as iio

    out = run_stage(PyvistaRender, tmp_path / "p", scene=SCENE, inputs=inputs, frames=(2,),
                    params={"resolution": list(resolution), "show": "particles", "color_by": "pressure",
                            "label": False})
    img = iio.imread(out / "frame_00002.png")[..., :3].astype(int)
    background = np.array([0x20, 0x24, 0x2C])
    for edge in (img[:, :2], img[:, -2:]):
        assert np.abs(edge - background).sum(axis=2).max() < 30
    assert (np.abs(img - background).sum(axis=2) > 60).sum() > 0.1 * img.shape[0] * img.shape[1]  # drawn


def test_the_colour_bar_names_its_unit():
    """Speeds are in scene units per second: the bar says which; pressure is in pascals."""
    from stages.render.pyvista_render import color_bar

    params = PyvistaRender.Params(show="particles", resolution=(1280, 720))
    assert [color_bar(params, mpu, 1.0)["title"] for mpu in (1.0, 0.01, 0.001, 0.0254, 0.3048, 0.5)] == [
        "speed (m/s)", "speed (cm/s)", "speed (mm/s)", "speed (in/s)", "speed (ft/s)", "speed (x 0.5 m/s)"]
    assert color_bar(PyvistaRender.Params(show="particles", color_by="pressure", resolution=(640, 360)), 0.01,
                     9056.0)["title"] == "pressure (Pa)"


def test_the_automatic_camera_fits_the_walls_in_a_portrait_frame():
    """Every corner of the walls' box projects inside the frame for 16:9, square and 3:4 images."""
    from stages.common.camera import auto_camera

    lo, hi = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 0.5, 1.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for aspect in (16 / 9, 1.0, 0.75, 0.5):
        eye, centre, up = auto_camera(lo, hi, "Z", 30.0, aspect)
        forward = (centre - eye) / np.linalg.norm(centre - eye)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        true_up = np.cross(right, forward)
        rel = corners - eye
        depth = rel @ forward
        tan_v = math.tan(math.radians(15.0))
        assert np.all(np.abs(rel @ true_up) / depth < tan_v)
        assert np.all(np.abs(rel @ right) / depth < aspect * tan_v), aspect


def test_the_automatic_camera_frames_fluid_standing_above_the_walls(tmp_path):
    """A column of water standing on a floor plate reached far above the walls' box, which alone set the
    automatic camera: the column's top was cut off in every frame. The camera now frames the fluid's start
    too (frame 0 of the particle run, half a spacing around it)."""
    from pipeline.scene import Camera, Units
    from stages.common.camera import fluid_bounds, shot_camera

    parts = tmp_path / "p"
    parts.mkdir()
    ParticleMeta(spacing=0.02, mass=0.008, density=1000.0, support=0.04, fps=10, frame_count=1, up_axis="Z",
                 meters_per_unit=1.0, solver="synthetic").save(parts)
    g = np.stack(np.meshgrid(np.arange(-0.09, 0.1, 0.02), np.arange(-0.09, 0.1, 0.02), np.arange(0.01, 0.6, 0.02),
                             indexing="ij"), axis=-1).reshape(-1, 3)
    save_particle_frame(parts, 0, ParticleFrame(g, np.zeros_like(g), np.full(len(g), 1000.0), np.zeros(len(g)),
                                                np.arange(len(g))))
    plate = trimesh.creation.box(extents=(0.6, 0.6, 0.04))
    plate.apply_translation((0, 0, -0.02))
    walls = WallMesh(plate.vertices, plate.faces.astype(np.int32), np.zeros(len(plate.faces), np.int32),
                     [{"name": "plate", "fluid": "outside"}])
    fluid = fluid_bounds(parts)
    assert np.allclose(fluid[1], [0.1, 0.1, 0.6])
    for box in (fluid, None):
        eye, centre, up, angle = shot_camera(walls, Units(up_axis="Z"), Camera(), lambda p: tmp_path / p, "render",
                                             aspect=16 / 9, fluid=box)
        forward = (centre - eye) / np.linalg.norm(centre - eye)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        true_up = np.cross(right, forward)
        top = np.array([0.0, 0.0, 0.6]) - eye
        inside = abs(top @ true_up) / (top @ forward) < math.tan(math.radians(angle / 2))
        assert inside == (box is not None)  # without the fluid's box the column's top is out of the frame


@pytest.mark.parametrize("up_axis", ["Z", "Y"])
def test_a_plan_view_without_an_up_gets_one_across_the_view(tmp_path, inputs, up_axis):
    """Looking straight down the scene's up axis with no camera.up, the default up (the up axis) lies along the
    view and VTK drew blank frames: the camera takes the horizontal axis the automatic view looks along."""
    import imageio.v3 as iio

    from pipeline.scene import Camera, Units
    from stages.common.camera import shot_camera

    eye, target = (np.array([0.0, 0.0, 3.0]), np.zeros(3)) if up_axis == "Z" else (np.array([0.0, 3.0, 0.0]), np.zeros(3))
    walls = WallMesh.load(inputs["walls"])
    cam = Camera(position=tuple(eye), focal_point=tuple(target))
    _, _, up, _ = shot_camera(walls, Units(up_axis=up_axis), cam, lambda p: tmp_path / p, "render")
    assert abs(up @ (target - eye)) < 1e-12 and np.linalg.norm(up) == 1.0
    if up_axis == "Z":  # the picture: the tank seen from above is drawn (the ball in it)
        out = run_stage(PyvistaRender, tmp_path / "plan", params={"resolution": [200, 120]}, inputs=inputs,
                        frames=(0,), scene={**SCENE, "camera": {"position": eye.tolist(), "focal_point": target.tolist()}})
        img = iio.imread(out / "frame_00000.png")[..., :3]
        assert water_mask(img).sum() > 100 and img.std() > 10


def test_an_eye_on_the_automatic_focal_point_is_a_one_line_error(tmp_path, inputs):
    """camera.position alone, on the walls' centre the automatic camera looks at: the camera looks nowhere."""
    from pipeline.scene import Camera, Units
    from stages.common.camera import shot_camera

    walls = WallMesh.load(inputs["walls"])
    centre = 0.5 * (walls.vertices.min(axis=0) + walls.vertices.max(axis=0))
    with pytest.raises(StageError, match="camera.position .* is the focal point") as err:
        shot_camera(walls, Units(), Camera(position=tuple(centre)), lambda p: tmp_path / p, "render")
    assert "\n" not in str(err.value)


def test_missing_surface_frame_is_a_stage_error(tmp_path, inputs):
    with pytest.raises(StageError, match="frame 7"):
        run_stage(PyvistaRender, tmp_path, scene={"scene": {"name": "t", "frames": {"count": 8}}},
                  params={"resolution": [64, 48]}, inputs=inputs, frames=(7,))


def test_movie_has_every_frame_and_a_contact_sheet(tmp_path):
    import imageio.v3 as iio
    import imageio_ffmpeg

    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    count = 7
    for f in range(count):  # odd size: the encoder pads to even
        img = np.zeros((61, 81, 3), np.uint8)
        img[:, : 10 * (f + 1)] = (40, 160, 250)
        iio.imwrite(frames_dir / f"frame_{f:05d}.png", img)
    scene = {"scene": {"name": "t", "frames": {"fps": 12, "count": count}}}
    out = run_stage(FfmpegMovie, tmp_path / "movie", scene=scene, params={"sheet_frames": 4},
                    inputs={"frames": frames_dir})
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))
    assert n == count
    assert secs == pytest.approx(count / 12, abs=0.1)
    sheet = iio.imread(out / "contact_sheet.png")
    assert sheet.shape[1] > 1000 and sheet.std() > 10


def test_movie_playback_rate_and_a_truncated_encode(tmp_path, monkeypatch):
    """movie.fps plays a 600 fps simulation at 30 (slow motion); an encoder that stops early (disk full, a
    file-size limit, ffmpeg killed: imageio-ffmpeg never checks its exit) is a stage error, not a cached,
    unplayable movie.mp4."""
    import imageio.v3 as iio
    import imageio_ffmpeg

    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    for f in range(6):
        iio.imwrite(frames_dir / f"frame_{f:05d}.png", np.full((48, 64, 3), 40 * f, np.uint8))
    scene = {"scene": {"name": "t", "frames": {"fps": 600, "count": 6}}}
    out = run_stage(FfmpegMovie, tmp_path / "slow", scene=scene, params={"fps": 30}, inputs={"frames": frames_dir})
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))
    assert n == 6 and secs == pytest.approx(0.2, abs=0.02)
    # an ffmpeg that encodes, then loses all but the file's first 48 bytes and exits 0 (as one killed mid-write)
    real = imageio_ffmpeg.get_ffmpeg_exe()
    fake = tmp_path / "ffmpeg"
    fake.write_text(f"#!/bin/sh\n\"{real}\" \"$@\" || exit $?\n"
                    'case "$*" in *-crf*) for last; do :; done; truncate -s 48 "$last";; esac\n')
    fake.chmod(0o755)
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(fake))
    with pytest.raises(OSError, match="the encoder did not finish movie.mp4"):  # the machine's failure: exit 1
        run_stage(FfmpegMovie, tmp_path / "cut", scene=scene, inputs={"frames": frames_dir})


def test_near_side_of_a_tank_is_the_side_facing_the_camera():
    from stages.render.pyvista_render import near_faces

    box = trimesh.creation.box(extents=(2, 2, 2))
    eye = np.array([0.0, -10.0, 0.0])
    for faces in (box.faces, box.faces[:, ::-1]):  # either winding
        near = near_faces(box.vertices, faces, eye, np.zeros(3))
        normals = trimesh.Trimesh(box.vertices, box.faces).face_normals
        np.testing.assert_array_equal(near, normals[:, 1] < -0.5)  # exactly the front wall


def test_render_every_second_frame_and_the_movie_keeps_time(tmp_path, inputs):
    import imageio_ffmpeg

    scene = {"scene": {"name": "t", "frames": {"fps": 10, "count": 4}}}
    make_surfaces(inputs["surface"], frames=4)
    frames = run_stage(PyvistaRender, tmp_path / "f", scene=scene, inputs=inputs,
                       params={"resolution": [64, 48], "every": 2})
    assert sorted(p.name for p in frames.iterdir()) == [".frame_00001.skipped", ".frame_00003.skipped",
                                                         "frame_00000.png", "frame_00002.png"]
    out = run_stage(FfmpegMovie, tmp_path / "m", scene=scene, inputs={"frames": frames})
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))
    assert n == 4 and secs == pytest.approx(0.4, abs=0.05)  # the scene's fps, each drawn frame held twice
    # 7 frames rendered every 3rd: frames 0, 3, 6 each stay on screen until the next, so frame 6 (t = 0.6 s) shows at
    # 0.6 s and the movie is the shot's 7 frames at its fps (it was 3 frames at fps / 3: 0.9 s for a 0.7 s shot;
    # before that fps x 3 / 7: 1.29 x fast); from frame 1 (--frames 1:7) it starts at the first drawn frame, 3
    for selection in (range(7), range(1, 7)):
        sevens = tmp_path / f"seven_{selection[0]}"
        sevens.mkdir()
        for f in selection:
            if f % 3:
                (sevens / f".frame_{f:05d}.skipped").write_text("")
            else:
                Image.fromarray(np.full((48, 64, 3), 30 * f, np.uint8)).save(sevens / f"frame_{f:05d}.png")
        out = run_stage(FfmpegMovie, tmp_path / f"m7_{selection[0]}", scene={"scene": {"name": "t", "frames": {
            "fps": 10, "count": 7}}}, inputs={"frames": sevens}, frames=tuple(selection))
        n, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))
        slots = 7 if selection[0] == 0 else 4
        assert n == slots and secs == pytest.approx(slots * 0.1, abs=0.02), (n, secs)
    # a selection holding no rendered frame (--frames 1:3 with every 3) says why, not only "no rendered frames"
    with pytest.raises(StageError, match=r"render skipped all 2 selected frames \(1\.\.2; render\.every"):
        run_stage(FfmpegMovie, tmp_path / "m7_none", scene={"scene": {"name": "t", "frames": {"fps": 10, "count": 7}}},
                  inputs={"frames": tmp_path / "seven_1"}, frames=(1, 2))
    (frames / ".frame_00003.skipped").unlink()  # a lost frame is an error, not a skip
    with pytest.raises(StageError, match="frame_00003.png"):
        run_stage(FfmpegMovie, tmp_path / "m2", scene=scene, inputs={"frames": frames})


def test_a_single_sided_sheet_is_drawn_the_same_from_either_side(tmp_path, inputs):
    """Issue 16: open meshes render two-sided. A single sheet of triangles (a shell) seen from above
    looks the same whichever way its faces are wound (with back-face culling the sheet wound away
    from the camera vanishes: checked, 2 of 19,200 pixels)."""
    import imageio.v3 as iio

    sheet = trimesh.creation.box(extents=(2.0, 2.0, 1e-9))
    top = sheet.faces[sheet.triangles_center[:, 2] > 0]  # two triangles, normals +z
    scene = {**SCENE, "camera": {"position": [0.0, -0.8, 3.0], "focal_point": [0, 0, 0], "up": [0, 0, 1],
                                 "view_angle": 40.0}}
    images, counts = [], []
    for name, faces in (("up", top), ("down", top[:, ::-1])):
        walls = tmp_path / f"walls_{name}"
        walls.mkdir()
        WallMesh(sheet.vertices, faces, np.zeros(len(faces), np.int32),
                 [{"name": "sheet", "fluid": "both", "shell": 0.01, "source": "sheet.obj"}]).save(walls)
        out = run_stage(PyvistaRender, tmp_path / name, scene=scene, params={"resolution": [160, 120], "label": False},
                        inputs={**inputs, "walls": walls}, frames=(0,))
        img = iio.imread(out / "frame_00000.png")[..., :3].astype(int)
        wall = (np.abs(img - img[0, 0]).sum(axis=2) > 30) & ~water_mask(img)  # neither background nor water
        images.append(img)
        counts.append(int(wall.sum()))
    assert min(counts) > 0.3 * 160 * 120, counts  # the sheet fills much of the view, seen from either side
    assert np.abs(images[0] - images[1]).max(axis=2).mean() < 2.0  # and is lit the same


def test_a_kept_plotter_draws_what_a_fresh_one_draws(tmp_path, inputs):
    """Issue 20: one plotter is kept across a process's frames (static walls added once, the fluid and
    label replaced). Its frames are pixel for pixel those of a fresh plotter, after a failed frame too
    (the half-changed plotter is dropped) and when the next frame comes from another thread (the
    engine runs each stage on a thread of its own)."""
    import threading

    import imageio.v3 as iio

    from stages.render import pyvista_render

    scene = {"scene": {"name": "t", "frames": {"fps": 10, "count": 8}}}
    params = {"resolution": [160, 90]}
    pyvista_render.close_view()
    kept = run_stage(PyvistaRender, tmp_path / "kept", scene=scene, params=params, inputs=inputs, frames=(0, 1, 2))
    assert pyvista_render._view is not None
    with pytest.raises(StageError, match="frame 7"):  # no surface for frame 7
        run_stage(PyvistaRender, tmp_path / "bad", scene=scene, params=params, inputs=inputs, frames=(7,))
    assert pyvista_render._view is None
    run_stage(PyvistaRender, tmp_path / "after", scene=scene, params=params, inputs=inputs, frames=(0, 1))
    # frame 2 on another thread with the plotter the main thread made
    results = []
    thread = threading.Thread(target=lambda: results.append(run_stage(
        PyvistaRender, tmp_path / "thread", scene=scene, params=params, inputs=inputs, frames=(2,))))
    thread.start()
    thread.join()
    assert len(results) == 1  # the thread finished its frame
    for name, frames in (("after", (1,)), ("thread", (2,))):
        for f in frames:
            pyvista_render.close_view()
            fresh = run_stage(PyvistaRender, tmp_path / f"fresh{f}", scene=scene, params=params, inputs=inputs,
                              frames=(f,))
            img = iio.imread(tmp_path / name / f"frame_{f:05d}.png")
            np.testing.assert_array_equal(img, iio.imread(fresh / f"frame_{f:05d}.png"))
            np.testing.assert_array_equal(img, iio.imread(kept / f"frame_{f:05d}.png"))
            assert water_mask(img[..., :3]).sum() > 50  # not blank


def test_every_frame_of_a_process_keeps_its_colour_bar(tmp_path, inputs):
    """The plotter is kept from frame to frame: pyvista remembered the removed bar's title and did not draw it
    again, so only the first frame a process drew had the colour bar (a user's sweep; with --workers 2, one
    frame per worker)."""
    import imageio.v3 as iio

    out = run_stage(PyvistaRender, tmp_path / "p", scene=SCENE, inputs=inputs, frames=(0, 1, 2),
                    params={"resolution": [320, 180], "show": "particles", "color_by": "pressure", "label": False})
    background = np.array([0x20, 0x24, 0x2C])
    drawn = []
    for f in (0, 1, 2):
        img = iio.imread(out / f"frame_{f:05d}.png")[..., :3].astype(int)
        right = img[:, int(0.85 * img.shape[1]):]  # the bar and its labels
        drawn.append(int((np.abs(right - background).sum(axis=2) > 60).sum()))
    assert min(drawn) > 0.5 * max(drawn) > 0, drawn


@pytest.mark.parametrize("fps", [1, 24, 29.97, 100, 120, 600, 1000])
def test_the_time_label_tells_consecutive_frames_apart(fps):
    from stages.render.pyvista_render import time_label

    labels = [time_label(f, fps) for f in range(50)]
    assert len(set(labels)) == 50 and labels[0] == "t = " + "0." + "0" * (len(labels[1]) - 8) + " s"


def test_a_render_resolution_of_another_aspect_than_the_shot_camera_is_said(tmp_path, inputs, caplog):
    """render.resolution portrait without camera.resolution: the frames were framed for portrait while the
    exported USD camera stayed 16:9 and closer (a user's sweep), without a word."""
    import logging

    from pipeline.testing import stage_context
    from stages.render.pyvista_render import RenderParams

    def check(resolution):
        PyvistaRender().check(stage_context(PyvistaRender, tmp_path, scene=SCENE), RenderParams(resolution=resolution))

    for k in range(2):  # said by every run's check (it was once per process: a second run said nothing)
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            check([90, 160])
        assert caplog.text.count("render.resolution 90x160 is not the shot camera's aspect (1280x720, the "
                                 "default)") == 1, k
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        check([320, 180])
        run_stage(PyvistaRender, tmp_path / "p", scene=SCENE, inputs=inputs, frames=(0, 1),
                  params={"resolution": [90, 160]})
    assert "shot camera's aspect" not in caplog.text  # the frames themselves say nothing


def test_the_colour_range_of_a_shot_starting_at_rest_is_its_fast_frames_percentile(tmp_path):
    """Each frame kept only its own top 0.5 % for the shot's percentile, so a shot whose speeds are in a few
    frames (a dam break starting at rest) got the top of its quiet frames: 0.93 m/s for a shot whose 99.5th
    percentile was 3.8 m/s, 81 % of a mid-shot frame drawn "above". The top is now within 0.2 % above the
    percentile of every value, whatever the frames' share."""
    from stages.render.pyvista_render import run_max

    parts = tmp_path / "p"
    parts.mkdir()
    frames, n = 12, 500
    ParticleMeta(spacing=0.05, mass=0.125, density=1000.0, support=0.1, fps=10, frame_count=frames, up_axis="Z",
                 meters_per_unit=1.0, solver="synthetic").save(parts)
    rng = np.random.default_rng(5)
    speeds = []
    for f in range(frames):
        v = np.zeros((n, 3))
        if f >= 9:  # the last three frames move, in m/s: 1/4 of the values, all the fast ones
            v[:, 0] = rng.uniform(0.0, 4.0, n) * (f - 8)
        speeds.append(np.linalg.norm(v, axis=1))
        x = SPHERE_CENTRE + rng.uniform(-0.25, 0.25, (n, 3))
        save_particle_frame(parts, f, ParticleFrame(x, v, np.full(n, 1000.0), np.zeros(n), np.arange(n)))
    every = np.sort(np.concatenate(speeds))
    want = every[-int(np.ceil(0.005 * len(every)))]  # the 30th largest of 6,000
    top = run_max(parts, "speed")
    assert want <= top < 1.002 * want, (top, want)
    assert run_max(parts, "pressure") == 0.0  # all zero: no range to give


def test_the_colour_range_is_the_shots_percentile_and_what_is_above_it_shows(tmp_path):
    """The colour bar's top was the largest per-frame 99.5th percentile while the docs said "the largest value":
    one frame's start-up spike set the range of the whole shot, and particles above it looked like the top
    colour. The top is now the 99.5th percentile of every frame's values together, particles above it are drawn
    pink with an "above" swatch on the bar; point sizes scale with the resolution."""
    import imageio.v3 as iio

    from stages.render.pyvista_render import ABOVE_RGB, point_pixels, run_max

    parts = tmp_path / "p"
    parts.mkdir()
    ParticleMeta(spacing=0.05, mass=0.125, density=1000.0, support=0.1, fps=10, frame_count=12, up_axis="Z",
                 meters_per_unit=1.0, solver="synthetic").save(parts)
    rng = np.random.default_rng(3)
    for f in range(12):
        n = 400
        x = SPHERE_CENTRE + rng.uniform(-0.25, 0.25, (n, 3))
        p = rng.uniform(0, 1000, n)
        if f == 0:
            p[:20] = 5000.0  # a start-up spike: 5 % of one frame
        save_particle_frame(parts, f, ParticleFrame(x, np.zeros((n, 3)), np.full(n, 1000.0), p, np.arange(n)))
    top = run_max(parts, "pressure")
    # the shot's 99.5th percentile: the spike, 0.42 % of all values, is not the range (with 4 frames it was 1.25 %,
    # and the range only stayed below it because each frame kept its own top 0.5 %: the percentile was wrong)
    assert 990 < top < 1002  # (run_max: its histogram's bin, 0.12 %, from above)
    walls = tmp_path / "w"
    walls.mkdir()
    out = run_stage(PyvistaRender, tmp_path / "f", scene=SCENE, frames=(0,),
                    inputs={"walls": make_walls(walls), "particles": parts},
                    params={"resolution": [960, 540], "show": "particles", "color_by": "pressure", "label": False})
    def pink(folder):
        img = iio.imread(folder / "frame_00000.png")[..., :3].astype(int)
        r, g, b = img[..., 0], img[..., 1], img[..., 2]  # shaded spheres: pink's hue, not its exact value
        return int(((r > 120) & (b > 0.5 * r) & (g < 0.6 * r)).sum())

    whole = run_stage(PyvistaRender, tmp_path / "g", scene=SCENE, frames=(0,),
                      inputs={"walls": walls, "particles": parts},
                      params={"resolution": [960, 540], "show": "particles", "color_by": "pressure", "label": False,
                              "color_range": [0.0, 6000.0]})
    assert pink(out) > pink(whole) + 30, (pink(out), pink(whole))  # the spike's particles and the bar's swatch
    assert ABOVE_RGB[0] > ABOVE_RGB[1]
    assert point_pixels(PyvistaRender.Params(resolution=(3840, 2160))) == 3 * point_pixels(PyvistaRender.Params(
        resolution=(1280, 720)))
