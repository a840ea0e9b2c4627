"""Small stage implementations for the engine tests (registered as the 'toy' plugin in tests)."""
from __future__ import annotations

import os
import time

from pydantic import Field

from pipeline.errors import PipelineError
from pipeline.stage import Params, Stage, StageError


def _bump(ctx, name: str) -> None:
    """Append to a counter file beside the config, so tests can count how often a stage really ran."""
    with open(ctx.config_dir / f"ran_{name}.log", "a") as fh:
        fh.write(f"{os.getpid()}\n")


class ToyImport(Stage):
    kind, name, version = "mesh_import", "toy", "1"
    outputs = ("walls",)
    reads = ("scene", "walls")

    class Params(Params):
        value: int = Field(1, description="written into the artifact")
        source: str | None = Field(None, description="an external file whose content is hashed")
        edit: str | None = Field(None, description="written into source after reading it (a user's edit mid-run)")

    def external_files(self, ctx, params):
        return [ctx.resolve(params.source)] if params.source else []

    def run(self, ctx, inputs, params):
        _bump(ctx, "mesh_import")
        text = f"walls {params.value}"
        if params.source:
            text += " " + ctx.resolve(params.source).read_text()
            if params.edit is not None:
                ctx.resolve(params.source).write_text(params.edit)
        (ctx.out_dir / "walls.txt").write_text(text)


class ToyBake(Stage):
    kind, name, version = "sdf_bake", "toy", "1"
    inputs = ("walls",)
    outputs = ("sdf",)

    class Params(Params):
        cell: float = 0.5

    def run(self, ctx, inputs, params):
        _bump(ctx, "sdf_bake")
        walls = (inputs["walls"].path / "walls.txt").read_text()
        (ctx.out_dir / "sdf.txt").write_text(f"{walls} | sdf {params.cell}")


class Diverged(PipelineError):
    """As stages.simulate.driver.SimulationDiverged: a failed run, one line, exit 1."""

    exit_code = 1


class ToySimulate(Stage):
    kind, name, version = "simulate", "toy", os.environ.get("TOY_SIM_VERSION", "1")
    inputs = ("sdf",)
    outputs = ("particles",)
    reads = ("scene", "fluid")

    class Params(Params):
        steps: int = Field(3, ge=1)
        sleep: float = Field(0.0, ge=0, description="seconds to sleep mid-write (kill tests)")
        fail: str | None = Field(None, description="'user' raises StageError, 'bug' raises RuntimeError, "
                                                   "'diverged' an exit-1 PipelineError (as a blow-up), "
                                                   "'interrupted' a Ctrl-C wrapped in a SystemError")
        warm_up: float = Field(0.0, ge=0, description="seconds of one-off warm-up (Context.warm_up), as a JIT compile")

    def run(self, ctx, inputs, params):
        _bump(ctx, "simulate")
        if params.warm_up:
            ctx.warm_up(lambda: time.sleep(params.warm_up))
        if params.fail == "user":
            raise StageError("the emitter box is empty")
        if params.fail == "bug":
            raise RuntimeError("boom")
        if params.fail == "diverged":
            raise Diverged("the toy run blew up during frame 1")
        if params.fail == "interrupted":  # a Ctrl-C as numba's dispatcher lets it out
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt:
                raise SystemError("CPUDispatcher(<function _cells>) returned a result with an exception set")
        sdf = (inputs["sdf"].path / "sdf.txt").read_text()
        part = ctx.out_dir / "particles.txt"
        with open(part, "w") as fh:
            fh.write(sdf + " | sim")
            fh.flush()
            progress = ctx.progress("simulate", params.steps)
            for _ in range(params.steps):
                time.sleep(params.sleep / params.steps)
                fh.write(".")
                fh.flush()
                progress.advance()
        (ctx.out_dir / "done.txt").write_text("ok")
        seen = sorted(os.listdir(ctx.checkpoint_dir)) if ctx.checkpoint_dir and ctx.checkpoint_dir.is_dir() else []
        (ctx.out_dir / "checkpoints_seen.txt").write_text(" ".join(seen))  # what a resume would start from
        # a made-up accuracy figure that improves with steps, for the study tests
        (ctx.out_dir / "stats.json").write_text(f'{{"stats": {{"error": {1.0 / params.steps}}}}}')


class ToySurface(Stage):
    kind, name, version = "surface_extract", "toy", "1"
    inputs = ("particles",)
    outputs = ("raw_surface",)
    per_frame = True

    class Params(Params):
        iso: float = 0.5
        fail: str | None = Field(None, description="'frame' fails frame 2 (StageError), 'summary' summarise (a bug)")

    def run_frame(self, ctx, inputs, params, frame):
        _bump(ctx, "surface_extract")
        if params.fail == "frame" and frame == 2:
            raise StageError("frame 2 has no particles")
        src = (inputs["particles"].frame(frame) / "particles.txt").read_text()
        (ctx.out_dir / f"surface_{frame:05d}.txt").write_text(f"{src} | surface {frame} iso {params.iso}")

    def summarise(self, ctx, params, frames):
        """Records each call beside the config: the process, the frames and whether each entry is there."""
        if params.fail == "summary":
            raise RuntimeError("summary boom")
        with open(ctx.config_dir / "summarised.log", "a") as fh:
            fh.write(f"{os.getpid()} {' '.join(str(f) for f in frames if (frames[f] / f'surface_{f:05d}.txt').is_file())}"
                     f" out_dir={ctx.out_dir}\n")


class ToyRender(Stage):
    kind, name, version = "render", "toy", "1"
    inputs = ("raw_surface",)
    outputs = ("frames",)
    per_frame = True

    class Params(Params):
        width: int = Field(64, ge=1)
        sleep: float = Field(0.0, ge=0)
        camera: str | None = Field(None, description="an external file read by every frame")
        edit_at: int | None = Field(None, description="the frame during which the camera file is edited, once: "
                                    "if the file edit_camera is beside the config (removed then)")

    def external_files(self, ctx, params):
        return [ctx.resolve(params.camera)] if params.camera else []

    def run_frame(self, ctx, inputs, params, frame):
        _bump(ctx, "render")
        _span(ctx, "render", params.sleep)
        marker = ctx.config_dir / "edit_camera"
        if params.camera and frame == params.edit_at and marker.exists():
            marker.unlink()
            ctx.resolve(params.camera).write_text("camera B")
        src = (inputs["raw_surface"].frame(frame) / f"surface_{frame:05d}.txt").read_text()
        (ctx.out_dir / f"frame_{frame:05d}.txt").write_text(f"{src} | render {params.width}")


def _span(ctx, name: str, seconds: float, wait_for: str | None = None) -> None:
    """Sleep and record the (start, end) interval, so tests can see whether branches overlapped.

    A marker ``started_<name>`` is written at the start; with ``wait_for`` the span also lasts until the
    marker of that other stage exists (at most 60 s), so an overlap test does not depend on how fast
    worker processes start on a loaded machine: run one after the other, the spans still do not overlap."""
    t0 = time.time()
    (ctx.config_dir / f"started_{name}").touch()
    time.sleep(seconds)
    while wait_for and not (ctx.config_dir / f"started_{wait_for}").exists() and time.time() - t0 < 60:
        time.sleep(0.05)
    with open(ctx.config_dir / f"span_{name}.log", "a") as fh:
        fh.write(f"{t0} {time.time()}\n")


class ToyExport(Stage):
    kind, name, version = "export", "toy", "1"
    inputs = ("particles",)
    outputs = ("usd",)

    class Params(Params):
        sleep: float = Field(0.0, ge=0)
        wait_for: str | None = Field(None, description="also wait until this stage has started (overlap tests)")

    def run(self, ctx, inputs, params):
        _bump(ctx, "export")
        _span(ctx, "export", params.sleep, params.wait_for)
        (ctx.out_dir / "scene.txt").write_text((inputs["particles"].path / "particles.txt").read_text())


class ToyParticles(Stage):
    """Particle frames in the real format for the real surface stage (not in the toy plugin: a test adds it)."""

    kind, name, version = "simulate", "toy_particles", "1"
    outputs = ("particles",)

    class Params(Params):
        frames: str = Field("b", description="per frame: b a block, d lone drops 4 l0 apart, e no particle")

    def run(self, ctx, inputs, params):
        import numpy as np

        from stages.common.formats import ParticleFrame, ParticleMeta, save_particle_frame
        from stages.simulate.emitters import lattice
        from stages.simulate.kernels import lattice_mass

        l0 = 0.02
        ParticleMeta(spacing=l0, mass=lattice_mass(1000.0, l0, 2 * l0), density=1000.0, support=2 * l0, fps=10,
                     frame_count=len(params.frames), up_axis="Z", meters_per_unit=1.0, solver="toy").save(ctx.out_dir)
        shapes = {"b": lattice([0.0, 0.0, 0.0], [0.1, 0.1, 0.1], l0),
                  "d": lattice([0.0, 0.0, 0.0], [0.2, 0.2, 0.2], 4 * l0)[:8] + 1.0, "e": np.zeros((0, 3))}
        for i, c in enumerate(params.frames):
            x = shapes[c]
            n = len(x)
            save_particle_frame(ctx.out_dir, i, ParticleFrame(x=x, v=np.zeros((n, 3)), rho=np.full(n, 1000.0),
                                                              p=np.zeros(n), id=np.arange(n)))


TOY_STAGES = (ToyImport, ToyBake, ToySimulate, ToySurface, ToyRender, ToyExport)


def error_above(out_dir, *, study_dir, limit):
    """A study metric that fails on some variants, as a surge front that is not there."""
    import json
    error = json.loads((out_dir / "particles" / "stats.json").read_text())["stats"]["error"]
    if error < limit:
        raise ValueError("no front")
    return error


def scaled_error(out_dir, *, study_dir, factor):
    """A study metric computed by a function (pipeline.study Metric.function)."""
    import json
    return factor * json.loads((out_dir / "particles" / "stats.json").read_text())["stats"]["error"]


def minus_reference(out_dir, *, study_dir, reference):
    """A study metric that reads another variant's outputs (as the distance to the finest run does)."""
    import json

    from stages.simulate.validation import finest_variant

    def error(folder):
        return json.loads((folder / "particles" / "stats.json").read_text())["stats"]["error"]
    return error(out_dir) - error(finest_variant(out_dir, reference))
