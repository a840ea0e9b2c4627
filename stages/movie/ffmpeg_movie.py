"""An H.264 MP4 of the rendered frames (imageio-ffmpeg's own ffmpeg binary) and a contact sheet PNG."""
from __future__ import annotations

import math
import subprocess
import tempfile
from fractions import Fraction
from pathlib import Path
from typing import Literal, Mapping

import numpy as np
from pydantic import Field, model_validator

from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import skipped_frame_marker


# players and H.264's levels stop near 240 fps ("MB rate > level limit" at 10,000); a faster shot is meant as slow
# motion, which plays at the usual 30
MAX_FPS = 240.0
SLOW_MOTION_FPS = 30.0
# a contact sheet's tiles at least 100 px wide (8 columns of a 200 px sheet were 25 px thumbnails nobody can read),
# the sheet at most 16384 px a side (a tall frame's tiles scaled to the width asked for gigapixel sheets)
MIN_TILE = 100
MAX_SHEET = 16384


class MovieParams(Params):
    crf: int = Field(18, ge=0, le=51, description="x264 constant rate factor (lower = better, bigger)")
    # veryfast at crf 18 matches medium at crf 20 (PSNR 39.98 against 39.99 dB over the dam break's 60 frames at
    # 960 x 540) in 0.5 s of encoding instead of 1.3 s, for a 16 % larger file (0.73 against 0.63 MB)
    preset: Literal["ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower",
                    "veryslow"] = Field("veryfast", description="x264 speed preset (slower = smaller at the same "
                                                                "quality)")
    fps: float | None = Field(None, gt=0, le=MAX_FPS, description="playback rate, frames per second (default: the "
                              f"scene's fps, or {SLOW_MOTION_FPS} when that is above {MAX_FPS:g}: slow motion)")
    sheet_frames: int = Field(9, ge=1, le=64, description="frames on the contact sheet, evenly spaced")
    sheet_columns: int = Field(3, ge=1, le=8, description="columns of the contact sheet")
    sheet_width: int = Field(1800, ge=200, le=MAX_SHEET, description="contact sheet width, pixels (at least "
                             f"{MIN_TILE} a column; a sheet of tall frames is narrowed to {MAX_SHEET} px high)")

    @model_validator(mode="after")
    def _readable_tiles(self) -> "MovieParams":
        if self.sheet_width // self.sheet_columns < MIN_TILE:
            raise ValueError(f"sheet_width {self.sheet_width} over {self.sheet_columns} columns gives "
                             f"{self.sheet_width // self.sheet_columns} px tiles: at least {MIN_TILE} px a tile "
                             f"(sheet_width {MIN_TILE * self.sheet_columns} or more, or fewer columns)")
        return self


def playback_fps(params: MovieParams, scene_fps: float) -> float:
    if params.fps is not None:
        return float(params.fps)
    return float(scene_fps) if scene_fps <= MAX_FPS else SLOW_MOTION_FPS


def frame_png(folder: Path, frame: int) -> Path:
    return Path(folder) / f"frame_{frame:05d}.png"


def check_movie(movie: Path, frames: int) -> None:
    """The encoder's output holds every frame sent: imageio-ffmpeg does not check ffmpeg's exit, so a full disk
    ("Error writing trailer"), a file-size limit or a killed ffmpeg left a truncated, unplayable movie.mp4 that
    the cache then served as finished. An OSError, not a StageError: the machine failed, not the input (exit 1,
    which a farm retries, and the log saved; it was exit 2, a user's mistake)."""
    import imageio_ffmpeg

    try:
        n, _ = imageio_ffmpeg.count_frames_and_secs(str(movie))
    except Exception as e:  # ffmpeg cannot read it: no moov atom, truncated
        reason = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise OSError(f"the encoder did not finish {movie.name} (disk full or ffmpeg stopped?): {reason}") from None
    if n != frames:
        raise OSError(f"{movie.name} holds {n} of the {frames} frames sent (disk full or ffmpeg stopped?)")


def encode(movie: Path, size: tuple[int, int], fps: float, params: MovieParams, images) -> list[str]:
    """H.264 of ``images`` (RGB uint8, ``size`` = (W, H)) into ``movie``; returns what ffmpeg wrote to stderr,
    which is captured: imageio-ffmpeg let it through to the terminal (a raw x264 line beside the run's own)."""
    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "warning", "-f", "rawvideo", "-vcodec", "rawvideo",
           "-s", f"{size[0]}x{size[1]}", "-pix_fmt", "rgb24", "-r", str(Fraction(fps).limit_denominator()),
           "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-crf", str(params.crf),
           "-preset", params.preset, "-movflags", "+faststart", str(movie)]
    with tempfile.TemporaryFile() as err:
        # its own session: a Ctrl-C reaches the run, which stops ffmpeg, not ffmpeg mid-write
        p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True)
        try:
            for img in images:
                try:
                    p.stdin.write(img.tobytes())
                except BrokenPipeError:  # ffmpeg stopped: check_movie says so, with its last line
                    break
            try:
                p.stdin.close()
            except BrokenPipeError:
                pass
            p.wait()
        except BaseException:
            p.kill()
            p.wait()
            raise
        err.seek(0)
        return [line.strip() for line in err.read().decode("utf-8", "replace").splitlines() if line.strip()]


def evenly_spaced(items: list[int], count: int) -> list[int]:
    if len(items) <= count:
        return list(items)
    picks = np.linspace(0, len(items) - 1, count).round().astype(int)
    return [items[i] for i in sorted(set(picks.tolist()))]


class FfmpegMovie(Stage):
    kind = "movie"
    name = "ffmpeg"
    version = "4"
    Params = MovieParams
    inputs = ("frames",)
    outputs = ("movie",)
    reads = ("scene.frames.fps", "frames")
    default = True
    description = "movie.mp4 at the scene's fps (or fps: a playback rate), skipped frames held, and contact_sheet.png"

    def check(self, ctx: Context, params: MovieParams) -> None:
        scene_fps = ctx.scene["scene"].frames.fps
        if params.fps is None and scene_fps > MAX_FPS:
            ctx.log.warning("movie.ffmpeg: scene.frames.fps %g is above a movie's %g; the movie plays at %g fps "
                            "(%.3g x slow motion): set stages.movie.fps to choose", scene_fps, MAX_FPS,
                            SLOW_MOTION_FPS, scene_fps / SLOW_MOTION_FPS)

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: MovieParams) -> None:
        import imageio.v3 as iio

        every = sorted(ctx.frames)
        frames = []
        for f in every:
            folder = inputs["frames"].frame(f)
            if frame_png(folder, f).is_file():
                frames.append(f)
            elif not skipped_frame_marker(folder, f).is_file():  # render's every: n
                raise StageError(f"movie.ffmpeg: rendered frame missing: {frame_png(folder, f)}")
        if not frames:
            raise StageError(f"movie.ffmpeg: no rendered frames: render skipped all {len(every)} selected frames "
                             f"({every[0]}..{every[-1]}; render.every: n draws frames 0, n, 2n, ...): select frames "
                             "holding one (--frames) or lower render.every")
        # the movie runs at the playback rate (default the scene's fps) through every frame from the first
        # rendered one to the last selected one; where render skipped frames (render.every: n, or a --frames
        # selection with gaps) the last rendered frame stays on screen, so the movie keeps the shot's time and
        # frame rate (a rate of fps / n made 7 frames every 2 play 0.27 s instead of 0.23, at 15 fps)
        slots = [max(f for f in frames if f <= k) for k in range(frames[0], every[-1] + 1)]
        fps = playback_fps(params, ctx.scene["scene"].frames.fps)
        paths = {f: frame_png(inputs["frames"].frame(f), f) for f in frames}
        first = iio.imread(paths[frames[0]])[..., :3]
        h, w = first.shape[:2]
        # yuv420p needs even sizes: pad by one pixel rather than rescale
        H, W = h + h % 2, w + w % 2
        movie = Path(ctx.out_dir) / "movie.mp4"
        progress = ctx.progress("encoding movie", len(slots))

        def images():
            shown, img = None, None
            for f in slots:
                if f != shown:
                    img = iio.imread(paths[f])[..., :3]
                    if img.shape[:2] != (h, w):
                        raise StageError(f"movie.ffmpeg: {paths[f]} is {img.shape[1]}x{img.shape[0]}, expected {w}x{h}")
                    if (H, W) != (h, w):
                        img = np.pad(img, ((0, H - h), (0, W - w), (0, 0)), mode="edge")
                    img, shown = np.ascontiguousarray(img, np.uint8), f
                yield img
                progress.advance()

        said = encode(movie, (W, H), fps, params, images())
        if said:  # kept out of the terminal (the run's one-line promise), in the log for whoever looks
            ctx.log.debug("ffmpeg said: %s", " | ".join(said))
        try:
            check_movie(movie, len(slots))
        except StageError as e:
            raise StageError(f"{e}; ffmpeg: {said[-1]}" if said else str(e)) from None
        self._contact_sheet(ctx, inputs, params, frames)

    @staticmethod
    def _contact_sheet(ctx: Context, inputs: Mapping[str, Artifact], params: MovieParams, frames: list[int]) -> None:
        from PIL import Image

        picks = evenly_spaced(frames, params.sheet_frames)
        cols = min(params.sheet_columns, len(picks))
        rows = math.ceil(len(picks) / cols)
        tiles = [Image.open(frame_png(inputs["frames"].frame(f), f)).convert("RGB") for f in picks]
        pad = 4
        tw = params.sheet_width // cols
        th = round(tiles[0].height * tw / tiles[0].width)
        if rows * (th + pad) + pad > MAX_SHEET:  # tall frames: the sheet's height bounds the tiles
            th = (MAX_SHEET - pad) // rows - pad
            tw = max(1, round(tiles[0].width * th / tiles[0].height))
        sheet = Image.new("RGB", (cols * (tw + pad) + pad, rows * (th + pad) + pad), (12, 12, 14))
        for k, tile in enumerate(tiles):  # the frames carry their own time label (render's `label`)
            x, y = pad + (k % cols) * (tw + pad), pad + (k // cols) * (th + pad)
            sheet.paste(tile.resize((tw, th), Image.LANCZOS), (x, y))
        sheet.save(Path(ctx.out_dir) / "contact_sheet.png")
