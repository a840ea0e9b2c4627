"""The real ``pipeline`` command with only the toy stages registered, so a test process starts without
importing numba, VTK or open3d (the reliability tests launch it dozens of times)."""
from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/, for toy_stages (also in workers)
# Ctrl-C as a terminal gives it to its foreground job: the suite itself may run as a background job of a
# shell without job control, whose children inherit SIGINT ignored (the Ctrl-C tests then hung)
signal.signal(signal.SIGINT, signal.default_int_handler)

from pipeline.registry import Registry  # noqa: E402
from toy_stages import TOY_STAGES  # noqa: E402


def _toy_registry(cls, group: str = "pipeline.stages") -> Registry:
    reg = cls()
    for stage in TOY_STAGES:
        reg.add(stage)
    return reg


Registry.from_entry_points = classmethod(_toy_registry)

if os.environ.get("TOY_SEGV_FRAME"):  # a native crash (as VTK or numba may have) in one frame's job
    import faulthandler

    import toy_stages

    _run_frame = toy_stages.ToyRender.run_frame

    def _crashing(self, ctx, inputs, params, frame):
        if frame == int(os.environ["TOY_SEGV_FRAME"]):
            faulthandler._sigsegv()
        return _run_frame(self, ctx, inputs, params, frame)

    toy_stages.ToyRender.run_frame = _crashing

if __name__ == "__main__":
    from pipeline.cli import main

    main()
