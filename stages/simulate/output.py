"""Particle cache output and checkpoints (shared by SPH and MPS).

Checkpoints are npz files written atomically (temporary name, then rename) into the engine's
checkpoint folder, with the output frames written so far copied beside them, so a killed run
resumes from the latest checkpoint and continues bitwise as if never stopped."""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np

from stages.common.formats import FRAMES_DIR, ParticleFrame, frame_path, load_particle_frame, save_particle_frame

_CKPT = re.compile(r"^state_(\d{5})\.npz$")


def write_frame(out_dir: Path, frame: int, f: ParticleFrame, checkpoint_dir: Path | None,
                spacing: float | None = None) -> None:
    path = save_particle_frame(out_dir, frame, f, spacing)
    if checkpoint_dir is not None:
        dst = frame_path(checkpoint_dir, frame)
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_suffix(".tmp")
        shutil.copyfile(path, tmp)
        os.replace(tmp, dst)


def save_checkpoint(checkpoint_dir: Path, frame: int, state: dict) -> Path:
    """Atomically write the solver state at the end of ``frame``; keep only the latest two."""
    checkpoint_dir = Path(checkpoint_dir)
    checkpoint_dir.mkdir(parents=True, exist_ok=True)
    dst = checkpoint_dir / f"state_{frame:05d}.npz"
    tmp = checkpoint_dir / f".state_{frame:05d}.tmp.npz"
    np.savez(tmp, **state)
    os.replace(tmp, dst)
    old = sorted(p for p in checkpoint_dir.iterdir() if _CKPT.match(p.name))[:-2]
    for p in old:
        p.unlink(missing_ok=True)
    return dst


def latest_checkpoint(checkpoint_dir: Path | None, frame_count: int,
                      earlier: Path | None = None) -> tuple[int, dict] | None:
    """(frame, state) of the newest readable checkpoint whose frames are all present, else None. ``earlier``:
    the entry of the shorter run a longer shot continued from (Stage.extends), which holds its first frames: a
    killed extension's checkpoint folder has only the frames after them, and its checkpoints were passed over
    (frames 30-48 of a 60-frame extension of a 30-frame shot done again)."""
    if checkpoint_dir is None or not Path(checkpoint_dir).is_dir():
        return None
    found = sorted((int(m.group(1)), p) for p in Path(checkpoint_dir).iterdir() if (m := _CKPT.match(p.name)))
    for frame, path in reversed(found):
        if frame >= frame_count:
            continue
        try:
            with np.load(path) as z:
                state = {k: z[k] for k in z.files}
        except Exception:  # noqa: BLE001 - a damaged checkpoint is skipped, an older one used
            continue
        if all(_frame_source(checkpoint_dir, f, earlier) is not None for f in range(frame + 1)):
            return frame, state
    return None


def _frame_source(checkpoint_dir: Path, frame: int, earlier: Path | None) -> Path | None:
    for folder in (checkpoint_dir, earlier):
        if folder is not None and frame_path(folder, frame).exists():
            return frame_path(folder, frame)
    return None


def restore_frames(checkpoint_dir: Path, out_dir: Path, upto: int, earlier: Path | None = None) -> None:
    """Copy the frames 0..upto written before the interruption (or, for an extension, by the shorter run:
    ``earlier``) into the new output folder."""
    (Path(out_dir) / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
    for f in range(upto + 1):
        shutil.copyfile(_frame_source(checkpoint_dir, f, earlier), frame_path(out_dir, f))


def iter_frames(out_dir: Path, count: int):
    for f in range(count):
        yield f, load_particle_frame(out_dir, f)
