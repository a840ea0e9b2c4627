"""An H.264 MP4 of the rendered frames (imageio-ffmpeg's own ffmpeg binary) and a contact sheet PNG."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, Mapping

import numpy as np
from pydantic import Field

from pipeline.stage import Artifact, Context, Params, Stage, StageError
from stages.common.formats import skipped_frame_marker


class MovieParams(Params):
    crf: int = Field(18, ge=0, le=51, description="x264 constant rate factor (lower = better, bigger)")
    # veryfast at crf 18 matches medium at crf 20 (PSNR 39.98 against 39.99 dB over the dam break's 60 frames at
    # 960 x 540) in 0.5 s of encoding instead of 1.3 s, for a 16 % larger file (0.73 against 0.63 MB)
    preset: Literal["ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower",
                    "veryslow"] = Field("veryfast", description="x264 speed preset (slower = smaller at the same "
                                                                "quality)")
    sheet_frames: int = Field(9, ge=1, le=64, description="frames on the contact sheet, evenly spaced")
    sheet_columns: int = Field(3, ge=1, le=8, description="columns of the contact sheet")
    sheet_width: int = Field(1800, ge=200, description="contact sheet width, pixels")


def frame_png(folder: Path, frame: int) -> Path:
    return Path(folder) / f"frame_{frame:05d}.png"


def evenly_spaced(items: list[int], count: int) -> list[int]:
    if len(items) <= count:
        return list(items)
    picks = np.linspace(0, len(items) - 1, count).round().astype(int)
    return [items[i] for i in sorted(set(picks.tolist()))]


class FfmpegMovie(Stage):
    kind = "movie"
    name = "ffmpeg"
    version = "3"
    Params = MovieParams
    inputs = ("frames",)
    outputs = ("movie",)
    reads = ("scene.frames.fps", "frames")
    default = True
    description = "movie.mp4 at the scene's fps and contact_sheet.png from the rendered frames"

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: MovieParams) -> None:
        import imageio.v3 as iio
        import imageio_ffmpeg

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
        paths = [frame_png(inputs["frames"].frame(f), f) for f in frames]
        # frames the render stage skipped (render.every: n) keep the simulated time: each rendered frame stays on
        # screen until the next one, n frames later (fps * rendered / selected ran 1.29 x fast for 7 frames, n = 3)
        step = min(np.diff(frames)) if len(frames) > 1 else len(every)
        fps = float(ctx.scene["scene"].frames.fps) / float(step)
        first = iio.imread(paths[0])[..., :3]
        h, w = first.shape[:2]
        # yuv420p needs even sizes: pad by one pixel rather than rescale
        H, W = h + h % 2, w + w % 2
        writer = imageio_ffmpeg.write_frames(
            str(Path(ctx.out_dir) / "movie.mp4"), (W, H), fps=fps,
            codec="libx264", pix_fmt_out="yuv420p", macro_block_size=1, quality=None,
            output_params=["-crf", str(params.crf), "-preset", params.preset, "-movflags", "+faststart"])
        writer.send(None)
        progress = ctx.progress("encoding movie", len(paths))
        try:
            for p in paths:
                img = iio.imread(p)[..., :3]
                if img.shape[:2] != (h, w):
                    raise StageError(f"movie.ffmpeg: {p} is {img.shape[1]}x{img.shape[0]}, expected {w}x{h}")
                if (H, W) != (h, w):
                    img = np.pad(img, ((0, H - h), (0, W - w), (0, 0)), mode="edge")
                writer.send(np.ascontiguousarray(img, np.uint8))
                progress.advance()
        finally:
            writer.close()
        self._contact_sheet(ctx, inputs, params, frames)

    @staticmethod
    def _contact_sheet(ctx: Context, inputs: Mapping[str, Artifact], params: MovieParams, frames: list[int]) -> None:
        from PIL import Image

        picks = evenly_spaced(frames, params.sheet_frames)
        cols = min(params.sheet_columns, len(picks))
        rows = math.ceil(len(picks) / cols)
        tiles = [Image.open(frame_png(inputs["frames"].frame(f), f)).convert("RGB") for f in picks]
        tw = params.sheet_width // cols
        th = round(tiles[0].height * tw / tiles[0].width)
        pad = 4
        sheet = Image.new("RGB", (cols * (tw + pad) + pad, rows * (th + pad) + pad), (12, 12, 14))
        for k, tile in enumerate(tiles):  # the frames carry their own time label (render's `label`)
            x, y = pad + (k % cols) * (tw + pad), pad + (k // cols) * (th + pad)
            sheet.paste(tile.resize((tw, th), Image.LANCZOS), (x, y))
        sheet.save(Path(ctx.out_dir) / "contact_sheet.png")
