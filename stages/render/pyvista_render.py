"""Offscreen frames with PyVista/VTK: the walls and the snapped fluid surface (or the particles).

Headless: with no X display we ask VTK for its EGL window (Mesa's llvmpipe software renderer through
libEGL, no GPU and no X server needed; Debian packages libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1),
falling back to OSMesa (libosmesa6) when Mesa's EGL is not installed. Both pass the render tests; EGL
starts faster. Left to itself VTK first tries X and spends seconds timing out on the missing display;
a VTK_DEFAULT_OPENGL_WINDOW set by the user wins.

Containers (fluid "inside", mesh_import's open box, and shells) are seen from outside, so the faces
between the camera and the container's centre are drawn faint: the water inside shows. Walls are drawn
two-sided (no back-face culling, two-sided lighting): an open or single-sided mesh (a shell) shows its
back faces lit like its front. A moving wall is drawn at its pose at the frame's time (frame / fps).
"""
from __future__ import annotations

import atexit
import ctypes.util
import functools
import math
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Annotated, Literal, Mapping

import numpy as np
from pydantic import field_validator, Field, model_validator

from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.camera import camera_files, fluid_bounds, shot_camera
from stages.common.formats import (WALLS_FILE, WALLS_INFO, ParticleMeta, SurfaceMesh, WallMesh, load_particle_frame,
                                   load_surface, skipped_frame_marker, surface_file)

Vec3 = tuple[float, float, float]

WATER_RGB = (0.45, 0.70, 0.95)
WALL_RGB = (0.62, 0.62, 0.60)


def choose_offscreen_backend() -> str | None:
    """Pick VTK's headless window class before pyvista is imported; respects a user's choice."""
    if os.environ.get("DISPLAY") or os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return os.environ.get("VTK_DEFAULT_OPENGL_WINDOW")
    # libEGL (glvnd) alone has no driver; Mesa's EGL vendor library is what renders without a GPU
    egl = ctypes.util.find_library("EGL") and ctypes.util.find_library("EGL_mesa")
    backend = "vtkEGLRenderWindow" if egl else "vtkOSOpenGLRenderWindow"
    os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = backend
    return backend


DEFAULT_RESOLUTION = (1280, 720)


class RenderParams(Params):
    # 16-8192 a side: VTK's offscreen buffer gave black 300 x 22028 frames for [-5, 100] and a bad_alloc for
    # [100000, 100000] (no test of the plan's memory estimate sees a frame buffer)
    resolution: tuple[Annotated[int, Field(ge=16, le=8192)], Annotated[int, Field(ge=16, le=8192)]] | None = Field(
        None, description="image width and height, pixels (16 to 8192 each); default: camera.resolution, the "
        "shot's (which the USD camera follows too), else 1280 x 720")
    show: Literal["surface", "particles"] = Field("surface", description="the fluid as its surface or as particles")
    color_by: Literal["speed", "pressure"] = Field("speed", description="particle colour (show: particles)")
    color_range: tuple[float, float] | None = Field(
        None, description="colour map range (units/s or Pa); default: 0 to the 99.5th percentile of all frames' "
        "values, so colours mean the same in every frame; faster ones are drawn pink, the bar's 'above' swatch")
    # at most 100 px of 720 lines: 1e6 drew every particle as a disc over the whole frame, in silence
    point_size: float = Field(6.0, gt=0, le=100, description="particle sphere size on screen, pixels of a 720-line "
                              "frame (at most 100), scaled with the resolution (show: particles)")
    every: int = Field(1, ge=1, description="render every n-th frame; the others are marked skipped and the "
                       "movie holds each rendered frame until the next")
    background: str = Field("#20242c", description="background colour (name or #rrggbb)")
    wall_opacity: float = Field(1.0, ge=0, le=1, description="opacity of the walls (a container's far side)")
    near_wall_opacity: float = Field(0.12, ge=0, le=1, description="opacity of a container's near side, "
                                     "between the camera and the fluid (0 hides it)")
    label: bool = Field(True, description="write the simulated time into the lower left corner")
    water_opacity: float = Field(0.85, ge=0, le=1, description="opacity of the fluid surface")

    @field_validator("background")
    @classmethod
    def _a_colour(cls, v: str) -> str:
        """Checked when the config loads (a bad colour failed at the first frame, after the simulation)."""
        from pyvista.plotting.colors import Color
        try:
            Color(v)
        except ValueError:
            hint = " (in YAML, quote it: '#20242c'; # starts a comment)" if v.startswith("#") else ""
            raise ValueError(f"{v!r} is not a colour: a name (white, black, ...) or #rrggbb{hint}") from None
        return v

    @model_validator(mode="after")
    def _ordered_range(self) -> "RenderParams":
        if self.color_range is not None and not self.color_range[0] < self.color_range[1]:
            raise ValueError(f"color_range {list(self.color_range)}: the first value must be below the second")
        if self.show == "surface" and self.color_by == "pressure":  # it was ignored without a word
            raise ValueError("color_by: pressure colours particles; set show: particles with it")
        return self


def near_faces(vertices: np.ndarray, faces: np.ndarray, eye: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Faces whose plane separates the eye from the container's centre: the near side of a tank (its
    front wall, lid, near side walls; both skins of a thick wall), whatever way the faces are wound
    and whether or not the container has a lid."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return np.einsum("ij,ij->i", n, eye - a) * np.einsum("ij,ij->i", n, centre - a) < 0


def length_unit(meters_per_unit: float) -> str:
    """The scene's length unit as a label says it: m, cm, mm, km, in, ft, yd, else "x <metres it holds> m"
    (a speed in those units times that is m/s)."""
    names = {1.0: "m", 0.01: "cm", 0.001: "mm", 1000.0: "km", 0.0254: "in", 0.3048: "ft", 0.9144: "yd"}
    return next((n for v, n in names.items() if math.isclose(meters_per_unit, v, rel_tol=1e-6)),
                f"x {meters_per_unit:g} m")


def text_colour(params: RenderParams) -> str:
    """White labels on a dark background, black on a light one (white text vanished on white)."""
    from pyvista.plotting.colors import Color
    r, g, b = Color(params.background).float_rgb
    return "black" if 0.2126 * r + 0.7152 * g + 0.0722 * b > 0.5 else "white"


ABOVE_RGB = (1.0, 0.35, 0.75)  # values above the colour range (outside viridis): pink, said under the bar


def point_pixels(params: RenderParams) -> float:
    """point_size is in pixels of a 720-line frame, scaled with the frame's smaller side, so the particles cover
    the same share of the picture at any resolution (fixed pixels covered 8.9 % at 320 x 180, 0.17 % at 4K)."""
    return max(1.0, params.point_size * min(params.resolution) / 720.0)


def color_bar(params: RenderParams, meters_per_unit: float, top: float) -> dict:
    """The particle colour bar (pyvista scalar_bar_args): titled with its unit (speeds are in scene units per
    second), 3 significant digits, fonts sized from the image's smaller side, and placed so its labels stay
    inside the frame (VTK sized them to the bar and cut 9.06e+03 to 9.06e+ below 1280 px); ``top`` is the
    colour range's upper end: up to a million the labels are whole numbers (9060, not 9.06e+03)."""
    fmt = "%.0f" if 100 <= top < 1e6 else "%.3g"
    w, h = params.resolution
    font = max(9, round(min(w, h) / 24))
    title = f"speed ({length_unit(meters_per_unit)}/s)" if params.color_by == "speed" else "pressure (Pa)"
    bar_px = max(8, round(0.03 * min(w, h)))
    labels_px = 7 * 0.6 * font  # 3 significant digits ('0.757', '9060', '1.2e+06') are at most 7 characters
    right = max(bar_px + labels_px, 0.5 * (bar_px + 0.6 * font * len(title))) + 0.02 * w  # the title is centred
    return {"title": title, "color": text_colour(params), "vertical": True, "fmt": fmt, "n_labels": 5,
            "above_label": "",  # (pyvista's swatch label sat on the title: said under the bar instead)
            "title_font_size": font, "label_font_size": font, "unconstrained_font_size": True,
            "position_x": max(0.0, 1.0 - right / w), "width": bar_px / w, "position_y": 0.08, "height": 0.66,
            "render": False}


def particle_values(p, color_by: str) -> np.ndarray:
    return np.linalg.norm(p.v, axis=1) if color_by == "speed" else np.asarray(p.p, np.float64)


TOP_SHARE = 0.005  # the colour range's top leaves out this share of the shot's values (drawn "above")


# run_max's histogram: log10 bins over 1e-9-1e9 (speeds in m/s, pressures in Pa), each 0.12 % wide
LOG_RANGE, LOG_BINS = (-9.0, 9.0), 36_000


@functools.lru_cache(maxsize=8)
def run_max(folder: Path, color_by: str) -> float:
    """The colour range's top: the 99.5th percentile of the speeds / pressures of every particle in every frame
    together (once per worker process), so a few splash outliers do not wash the colours out; the values above
    it are drawn in the bar's "above" colour. (The largest per-frame percentile let one frame's start-up
    pressure in the corners set the range of the whole shot: later frames all dark.) Counted in a log histogram,
    one pass and fixed memory, to within its bin (0.12 %), from above: keeping each frame's own top 0.5 % lost
    the values of the fast frames (a shot starting at rest ranged to 0.93 m/s while its 99.5th percentile was 3.8;
    81 % of a mid-shot frame was drawn "above")."""
    meta = ParticleMeta.load(folder)
    lo, hi = LOG_RANGE
    counts = np.zeros(LOG_BINS + 1, np.int64)  # [0]: values at or below 10**lo (rest, zero or negative pressure)
    for f in range(meta.frame_count):
        try:
            values = particle_values(load_particle_frame(folder, f), color_by)
        except FileNotFoundError:
            continue
        positive = values[values > 10.0 ** lo]
        bins = ((np.log10(positive) - lo) * (LOG_BINS / (hi - lo))).astype(np.int64)
        counts += np.bincount(np.clip(bins, 0, LOG_BINS - 1) + 1, minlength=LOG_BINS + 1)
        counts[0] += len(values) - len(positive)
    total = int(counts.sum())
    if total == 0:
        return 0.0
    k = max(1, int(math.ceil(TOP_SHARE * total)))
    b = LOG_BINS - int(np.searchsorted(np.cumsum(counts[::-1]), k))  # the bin holding the k-th largest value
    return 0.0 if b == 0 else float(10.0 ** (lo + b * (hi - lo) / LOG_BINS))  # its upper edge


def polydata(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None):
    import pyvista as pv

    # offsets + connectivity handed to VTK as they are: ~20x faster than the legacy [3, a, b, c, ...] cell list
    mesh = pv.PolyData.from_regular_faces(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    if normals is not None and len(normals) == len(vertices):
        mesh.point_data["Normals"] = np.asarray(normals, np.float32)
        mesh.point_data.active_normals_name = "Normals"
    return mesh


def surface_folder(inputs: Mapping[str, Artifact], frame: int) -> Path:
    if "surface" not in inputs:
        raise StageError("render.pyvista: show: surface needs the 'surface' artifact (wall_snap stage)")
    return inputs["surface"].frame(frame)


def read_surface(folder: Path, frame: int) -> SurfaceMesh:
    try:
        return load_surface(folder, frame)
    except FileNotFoundError:
        raise StageError(f"render.pyvista: {folder} has no surface for frame {frame}") from None


def file_state(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


def walls_identity(folder: Path) -> tuple:
    """The walls artifact's files as they are on disk (path, mtime, size): what a kept plotter's walls came from."""
    return tuple((str(f), st.st_mtime_ns, st.st_size) for f in (folder / WALLS_FILE, folder / WALLS_INFO)
                 for st in (f.stat(),))


@functools.lru_cache(maxsize=2)
def _walls_as_on_disk(folder: Path, identity: tuple) -> WallMesh:
    return WallMesh.load(folder)


def load_walls(folder: Path) -> WallMesh:
    """The walls, read once per process while their files stay the same (a large imported mesh is not
    read again every frame)."""
    return _walls_as_on_disk(folder, walls_identity(folder))


class PyvistaRender(Stage):
    kind = "render"
    name = "pyvista"
    version = "7"
    Params = RenderParams
    inputs = ("walls",)
    optional_inputs = ("surface", "particles")
    outputs = ("frames",)
    reads = ("scene.units", "scene.frames.fps", "camera")
    per_frame = True
    default = True
    description = "offscreen PNG frames of the walls and fluid surface (or particles) with PyVista/VTK"

    def input_names(self, params: RenderParams) -> tuple[str, ...]:
        if params.show == "surface":
            return ("walls", "surface", "particles")
        return ("walls", "particles")

    def external_files(self, ctx: Context, params: RenderParams) -> list[Path]:
        return camera_files(ctx)  # the layers a camera.usd composes

    def check(self, ctx: Context, params: RenderParams) -> None:
        """Said once before the run (said from run_frame, once per process, each pool worker said it again and a
        second run in the same process not at all)."""
        shot = ctx.scene["camera"].resolution or DEFAULT_RESOLUTION
        if params.resolution and abs(params.resolution[0] / params.resolution[1] / (shot[0] / shot[1]) - 1) > 0.01:
            ctx.log.warning(f"render.resolution {params.resolution[0]}x{params.resolution[1]} is not the shot "
                            f"camera's aspect ({shot[0]}x{shot[1]}"
                            f"{'' if ctx.scene['camera'].resolution else ', the default'}): the frames are framed "
                            "for it, a USD export's camera (if one is written) is not; set camera.resolution to it so "
                            "both agree")

    def run_frame(self, ctx: Context, inputs: Mapping[str, Artifact], params: RenderParams, frame: int) -> None:
        if frame % params.every:
            # a marker, not a missing file: the movie tells a skipped frame from a lost one
            skipped_frame_marker(ctx.out_dir, frame).write_text("")
            return
        choose_offscreen_backend()
        # the frame size: the stage's own, else the shot camera's (export's USD camera follows that one)
        size = params.resolution or ctx.scene["camera"].resolution or DEFAULT_RESOLUTION
        params = params.model_copy(update={"resolution": tuple(size)})
        scene = ctx.scene["scene"]
        walls = load_walls(Path(inputs["walls"].path))
        eye, centre, up, view_angle = shot_camera(walls, scene.units, ctx.scene["camera"], ctx.resolve,
                                                  "render.pyvista", frame / scene.frames.fps,
                                                  params.resolution[0] / params.resolution[1],
                                                  fluid_bounds(getattr(inputs.get("particles"), "path", None)))
        # everything the plotter and its static walls depend on
        key = (tuple(params.resolution), params.background, params.wall_opacity, params.near_wall_opacity,
               walls_identity(Path(inputs["walls"].path)), tuple(eye), tuple(centre), tuple(up), view_angle)
        with _LOCK:
            view = view_for(key, walls, eye, params)
            try:
                image = view.draw(ctx, inputs, params, frame, walls, (eye, centre, up, view_angle))
            except BaseException:
                close_view()  # never reuse a plotter a failed frame left half changed
                raise
        # zlib level 1: a few times faster than PIL's default 6 for ~1.3x the bytes; the pixels are the same
        from PIL import Image

        Image.fromarray(image).save(Path(ctx.out_dir) / f"frame_{frame:05d}.png", compress_level=1)

    # -- pieces of the picture -------------------------------------------------------------------
    @staticmethod
    def _add_walls(plotter, walls: WallMesh, eye: np.ndarray, params: RenderParams, moving: bool) -> None:
        """The walls that move (``moving``) or the ones that stay."""
        style = dict(color=WALL_RGB, ambient=0.25, diffuse=0.75, specular=0.0, smooth_shading=False, culling=False)
        plotter.renderer.SetTwoSidedLighting(True)  # VTK's default, made explicit: back faces of shells lit
        for index, info in enumerate(walls.walls):
            faces = walls.faces[walls.wall_id == index]
            if len(faces) == 0 or (info.get("motion") is not None) != moving:
                continue
            near = np.zeros(len(faces), bool)
            # mesh_import builds an open box as a thick solid the fluid is "outside" of; it holds fluid all the
            # same; a shell (fluid "both": an open bowl, a trough) may hold it too
            if info.get("fluid", "outside") in ("inside", "both") or info.get("source") == "builtin:open_box":
                # a container is seen from outside: its near side would hide the fluid
                used = walls.vertices[np.unique(faces)]
                near = near_faces(walls.vertices, faces, eye, 0.5 * (used.min(axis=0) + used.max(axis=0)))
            if (~near).any() and params.wall_opacity > 0:
                plotter.add_mesh(polydata(walls.vertices, faces[~near]), opacity=params.wall_opacity, render=False,
                                 **style)
            if near.any() and params.near_wall_opacity > 0:
                plotter.add_mesh(polydata(walls.vertices, faces[near]), opacity=params.near_wall_opacity,
                                 render=False, **style)

    @staticmethod
    def _add_surface(plotter, mesh: SurfaceMesh, params: RenderParams) -> None:
        if len(mesh.faces) == 0:
            return
        plotter.add_mesh(polydata(mesh.vertices, mesh.faces, mesh.normals), color=WATER_RGB,
                         opacity=params.water_opacity, smooth_shading=True, ambient=0.15, diffuse=0.7,
                         specular=0.7, specular_power=60.0, render=False)

    @staticmethod
    def _add_particles(plotter, inputs: Mapping[str, Artifact], frame: int, params: RenderParams,
                       meters_per_unit: float) -> None:
        import pyvista as pv

        folder = inputs["particles"].path
        if folder is None:
            raise StageError("render.pyvista: the 'particles' artifact must be a whole-run folder")
        p = load_particle_frame(folder, frame)
        if len(p) == 0:
            return
        cloud = pv.PolyData(np.asarray(p.x, np.float64))
        cloud[params.color_by] = particle_values(p, params.color_by)
        clim = params.color_range or (0.0, max(run_max(folder, params.color_by), 1e-9))
        bar = color_bar(params, meters_per_unit, clim[1])
        plotter.add_mesh(cloud, render_points_as_spheres=True, point_size=point_pixels(params), cmap="viridis",
                         clim=clim, above_color=ABOVE_RGB, render=False, scalar_bar_args=bar)
        # the title clear of the top label (VTK sets it right on the bar's end)
        plotter.scalar_bars[bar["title"]].SetVerticalTitleSeparation(round(0.6 * bar["title_font_size"]))
        if params.color_range is None or (cloud[params.color_by] > clim[1]).any():  # what pink means, under the bar
            w, h = params.resolution
            size = max(6, round(0.5 * bar["label_font_size"]))
            plotter.add_text("pink: above", position=(w - 0.02 * w - 13 * size, 0.012 * h), color=ABOVE_RGB,
                             font_size=size, render=False)


def time_label(frame: int, fps: float) -> str:
    """"t = 0.03 s", with as many decimals as tell consecutive frames apart (at 600 fps six frames read
    t = 0.01 s with two)."""
    decimals = max(2, math.ceil(math.log10(fps) - 1e-9))
    return f"t = {frame / fps:.{decimals}f} s"


# -- one plotter kept across the frames of a process ------------------------------------------------
class View:
    """An offscreen plotter kept from frame to frame: a new plotter per frame (a new EGL/OSMesa context,
    every shader compiled again by llvmpipe) cost more than drawing the frame. Static walls are added
    once; each frame replaces the moving walls, the fluid and the time label, added in that order after
    the static walls (translucent layers are blended order-independently, VTK's default, so the picture
    is the one a fresh plotter draws).
    The GL context is released after every frame: the next frame may come from another thread."""

    def __init__(self, key: tuple, walls: WallMesh, eye: np.ndarray, params: RenderParams) -> None:
        import pyvista as pv

        self.key = key
        w, h = params.resolution
        self.plotter = pv.Plotter(off_screen=True, window_size=(int(w), int(h)), lighting="three lights")
        self.moving = bool(walls.motions())  # walls that move are added anew every frame
        self.frame_actors: list[str] = []  # names of the actors the last frame added
        self.rendered = False  # the GL context exists once the first frame is rendered
        self.ahead: tuple[Path, int, tuple | None, Future] | None = None  # the next frame's surface, being read
        try:
            self.plotter.set_background(params.background)
            PyvistaRender._add_walls(self.plotter, walls, eye, params, moving=False)
        except BaseException:
            self.plotter.close()
            raise

    def draw(self, ctx: Context, inputs: Mapping[str, Artifact], params: RenderParams, frame: int,
             walls: WallMesh, camera) -> np.ndarray:
        """The frame's RGB image (h, w, 3) uint8."""
        plotter = self.plotter
        eye, centre, up, view_angle = camera
        fps = ctx.scene["scene"].frames.fps
        if self.rendered:
            plotter.render_window.MakeCurrent()  # removing an actor frees its GL buffers: in this context
        try:
            for name in self.frame_actors:
                plotter.remove_actor(name, reset_camera=False, render=False)
            for title in list(plotter.scalar_bars.keys()):  # pyvista keeps a removed bar's title and would not
                plotter.remove_scalar_bar(title, render=False)  # draw it again: only a process's first frame had it
            before = set(plotter.renderer.actors)
            if self.moving:  # the camera frames the walls at rest; moving walls drawn at the frame's time
                PyvistaRender._add_walls(plotter, walls.posed(frame / fps), eye, params, moving=True)
            if params.show == "surface":
                PyvistaRender._add_surface(plotter, self.surface(surface_folder(inputs, frame), frame), params)
                self.read_ahead(inputs, frame + params.every)
            else:
                PyvistaRender._add_particles(plotter, inputs, frame, params,
                                             ctx.scene["scene"].units.meters_per_unit)
            if params.label:
                plotter.add_text(time_label(frame, fps), position="lower_left",
                                 font_size=max(9, round(params.resolution[1] / 40)), color=text_colour(params),
                                 render=False)
            self.frame_actors = [name for name in plotter.renderer.actors if name not in before]
            plotter.camera_position = [tuple(eye), tuple(centre), tuple(up)]
            plotter.camera.view_angle = view_angle
            plotter.reset_camera_clipping_range()
            plotter.render()  # pyvista renders a plotter's first frame in screenshot, this does the others
            image = np.asarray(plotter.screenshot(None, return_img=True))[..., :3]
            self.rendered = True
            return image
        finally:
            if self.rendered:
                plotter.render_window.ReleaseCurrent()

    def surface(self, folder: Path, frame: int) -> SurfaceMesh:
        """The frame's surface: the one read ahead if it is that frame's file as it is now."""
        ahead, self.ahead = self.ahead, None
        path = folder / surface_file(frame)
        if ahead is not None and ahead[:3] == (folder, frame, file_state(path)):
            return ahead[3].result()
        return read_surface(folder, frame)

    def read_ahead(self, inputs: Mapping[str, Artifact], frame: int) -> None:
        """Start reading ``frame``'s surface on a thread: VTK lets go of the GIL while it renders this frame."""
        art = inputs["surface"]
        folder = art.path if art.path is not None else art.frames.get(frame)
        state = None if folder is None else file_state(folder / surface_file(frame))
        if state is not None:
            self.ahead = (folder, frame, state, _reader().submit(read_surface, folder, frame))

    def close(self) -> None:
        if self.rendered:
            self.plotter.render_window.MakeCurrent()  # released after the last frame, maybe by another thread
        self.plotter.close()


_LOCK = threading.Lock()  # VTK is not thread safe: one frame at a time per process
_view: View | None = None


@functools.cache
def _reader() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="render-read-ahead")


def view_for(key: tuple, walls: WallMesh, eye: np.ndarray, params: RenderParams) -> View:
    """The kept plotter if it was built for ``key``, else a new one (the old one closed)."""
    global _view
    if _view is None or _view.key != key:
        close_view()
        _view = View(key, walls, eye, params)
    return _view


@atexit.register
def close_view() -> None:
    global _view
    view, _view = _view, None
    if view is not None:
        view.close()
