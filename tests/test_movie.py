"""movie.ffmpeg: the playback rate of a high-fps shot, and ffmpeg's own output kept off the terminal."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline.testing import run_stage, stage_context
from stages.movie.ffmpeg_movie import FfmpegMovie, MovieParams


@pytest.fixture
def frames_dir(tmp_path):
    import imageio.v3 as iio

    folder = tmp_path / "frames"
    folder.mkdir()
    for f in range(6):
        iio.imwrite(folder / f"frame_{f:05d}.png", np.full((48, 64, 3), 40 * f, np.uint8))
    return folder


def test_a_shot_faster_than_a_movie_plays_in_slow_motion_and_says_so(tmp_path, frames_dir, caplog):
    """scene.frames.fps 10000 wrote a 10,000 fps movie 0.6 ms long (players read 0 fps), in silence: the movie's
    own fps is limited to 240 but its default copied the scene's."""
    import imageio_ffmpeg

    scene = {"scene": {"name": "t", "frames": {"fps": 10000, "count": 6}}}
    with caplog.at_level(logging.WARNING):
        FfmpegMovie().check(stage_context(FfmpegMovie, tmp_path, scene=scene), MovieParams())
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "\n" not in warned[0]
    assert "plays at 30 fps" in warned[0] and "stages.movie.fps" in warned[0], warned
    out = run_stage(FfmpegMovie, tmp_path / "slow", scene=scene, inputs={"frames": frames_dir})
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))
    assert n == 6 and secs == pytest.approx(6 / 30, abs=0.02)
    # a rate the user chose, or a scene's own up to 240, is kept without a word
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        FfmpegMovie().check(stage_context(FfmpegMovie, tmp_path, scene=scene), MovieParams(fps=240))
        FfmpegMovie().check(stage_context(FfmpegMovie, tmp_path, scene={"scene": {
            "name": "t", "frames": {"fps": 240, "count": 6}}}), MovieParams())
    assert not caplog.records
    out = run_stage(FfmpegMovie, tmp_path / "chosen", scene=scene, params={"fps": 120}, inputs={"frames": frames_dir})
    assert imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))[1] == pytest.approx(0.05, abs=0.01)


def test_ffmpeg_lines_stay_off_the_terminal(tmp_path, frames_dir, monkeypatch, capfd, caplog):
    """x264's "MB rate > level limit" reached the terminal raw (imageio-ffmpeg lets ffmpeg's stderr through): what
    ffmpeg says goes to the log, and its last line into the error when the movie is not finished."""
    import imageio_ffmpeg

    real = imageio_ffmpeg.get_ffmpeg_exe()
    fake = tmp_path / "ffmpeg"
    fake.write_text(f"#!/bin/sh\necho '[libx264 @ 0x1] MB rate > level limit' >&2\nexec \"{real}\" \"$@\"\n")
    fake.chmod(0o755)
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(fake))
    scene = {"scene": {"name": "t", "frames": {"fps": 30, "count": 6}}}
    capfd.readouterr()
    with caplog.at_level(logging.DEBUG):
        out = run_stage(FfmpegMovie, tmp_path / "m", scene=scene, inputs={"frames": frames_dir})
    # ffmpeg's own line, as it writes it (a console log handler left by an earlier test in this process may show
    # the log's debug record of it, which is not ffmpeg writing to the terminal)
    raw = "[libx264 @ 0x1] MB rate > level limit"
    assert raw not in [line.strip() for line in capfd.readouterr().err.splitlines()]
    assert "MB rate > level limit" in caplog.text
    assert imageio_ffmpeg.count_frames_and_secs(str(out / "movie.mp4"))[0] == 6


def test_a_contact_sheet_of_tall_frames_stays_within_its_largest_side(tmp_path):
    """Tiles are scaled to the sheet's width: a 16 x 8192 frame (render's resolution allows it) at 600 px a tile
    asked PIL for a 1800 x 921,000 sheet (5 GB). The sheet's height now bounds the tiles; the frames keep their
    shape."""
    import imageio.v3 as iio
    from PIL import Image
    from stages.movie.ffmpeg_movie import MAX_SHEET

    folder = tmp_path / "frames"
    folder.mkdir()
    for f in range(3):
        iio.imwrite(folder / f"frame_{f:05d}.png", np.full((8192, 16, 3), 80 * f, np.uint8))
    out = run_stage(FfmpegMovie, tmp_path / "tall", scene={"scene": {"name": "t", "frames": {"fps": 30, "count": 3}}},
                    inputs={"frames": folder})
    with Image.open(out / "contact_sheet.png") as sheet:
        w, h = sheet.size
    assert h <= MAX_SHEET and w < 200, (w, h)
    assert h > 0.9 * MAX_SHEET  # the tiles as large as the bound lets them be


@pytest.mark.parametrize("width, columns, ok", [(1800, 3, True), (800, 8, True), (799, 8, False), (200, 3, False)])
def test_a_contact_sheets_tiles_are_large_enough_to_read(width, columns, ok):
    if ok:
        MovieParams(sheet_width=width, sheet_columns=columns)
    else:
        with pytest.raises(ValueError, match="px a tile"):
            MovieParams(sheet_width=width, sheet_columns=columns)
