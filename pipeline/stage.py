"""The contract every stage implementation fulfils.

A stage is a small class: its kind (the DAG node it can fill, e.g. ``simulate``), its implementation
name (chosen in the config with ``use:``), a hand-bumped code ``version``, a typed ``Params`` model,
the artifacts it consumes and produces, the config fields it reads, and ``run`` (or ``run_frame`` for
per-frame stages, and optionally ``summarise`` over all of a run's frames). The engine checks the
contract when the stage is registered; pipeline.keys says what goes into the cache key.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from .memory import refusal
from .reads import FRAMES, SceneReads, UndeclaredRead, check_read
from .scene import no_bool_for_a_number

# The stage kinds of the DAG, in dependency order, and the artifact each one produces. The engine
# knows these names (they are the vocabulary of configs), never the implementations.
STAGE_KINDS: tuple[str, ...] = (
    "mesh_import", "sdf_bake", "simulate", "surface_extract", "wall_snap", "render", "movie", "export",
)

# The scene sections a stage may read (``reads`` names them or dotted fields inside them).
SCENE_SECTIONS: tuple[str, ...] = ("scene", "walls", "fluid", "effects", "camera")


class Params(BaseModel):
    """Base of every stage's parameter model: unknown keys are errors, NaN/inf are errors, a true/false for a
    number is an error, values validated on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
    _no_bool_for_a_number = field_validator("*", mode="before")(classmethod(no_bool_for_a_number))


class StageError(Exception):
    """A stage failed because of its input (bad file, empty mesh...). The message is shown to the user
    as one line, prefixed with the stage name; exit code 2."""


@dataclass
class Artifact:
    """A finished cache entry of an upstream stage as a downstream stage sees it.

    ``path`` is the entry's folder for a whole-run artifact; for a per-frame artifact ``frames`` maps
    each frame index to its folder (and ``path`` is None)."""

    name: str
    key: str
    path: Path | None = None
    frames: dict[int, Path] = field(default_factory=dict)

    def frame(self, i: int) -> Path:
        if self.path is not None:
            return self.path
        try:
            return self.frames[i]
        except KeyError:
            raise StageError(f"artifact {self.name!r} has no frame {i}") from None


class Progress:
    """Progress of a long stage; the engine gives a rich progress bar, tests a silent one."""

    def __init__(self, update: Callable[[float], None] | None = None) -> None:
        self._update = update

    def advance(self, amount: float = 1.0) -> None:
        if self._update is not None:
            self._update(amount)


class Context:
    """What a running stage may use: its scratch output folder, the config fields it declared in
    ``reads`` (``scene``: section -> value or a view of the declared fields), the config file's folder
    (paths in the config are relative to it), the frame selection (only if it declared "frames"), a
    logger and a progress factory. Reading anything undeclared raises UndeclaredRead."""

    def __init__(self, out_dir: Path | None, scene: Mapping[str, Any], config_dir: Path,
                 frames: tuple[int, ...] | None, log: logging.Logger,
                 make_progress: Callable[[str, float], Progress] | None = None, threads: int | None = None,
                 checkpoint_dir: Path | None = None, resume_from: Path | None = None,
                 allow_large: bool = False) -> None:
        self.out_dir = out_dir  # None for Stage.summarise, which writes nothing
        self.scene = scene
        self.config_dir = config_dir
        self._frames = None if frames is None else tuple(frames)
        self.log = log
        self.make_progress = make_progress or (lambda description, total: Progress())
        self.threads = threads
        # a folder that survives an interrupted run of this stage key (checkpoints); None when not cached
        self.checkpoint_dir = checkpoint_dir
        # read-only: the cached entry of a shorter run of the same shot (Stage.extends), to continue from
        self.resume_from = resume_from
        # wall and CPU seconds spent in warm_up (one-off work such as JIT compilation), left out of the
        # stage's cost by the engine
        self.warmup_seconds = 0.0
        self.warmup_cpu_seconds = 0.0
        self.allow_large = allow_large  # --yes / config allow_large: true (check_memory lets anything pass)

    @classmethod
    def for_stage(cls, stage_cls: type["Stage"], sections: Mapping[str, Any], *, out_dir: Path | None, config_dir: Path,
                  frames: tuple[int, ...], extra_reads: tuple[str, ...] = (), **kw: Any) -> "Context":
        """The context the engine gives ``stage_cls``: only its declared reads (and ``extra_reads``) are visible."""
        return cls(out_dir=out_dir, scene=SceneReads(sections, stage_cls.reads + extra_reads), config_dir=config_dir,
                   frames=frames if FRAMES in stage_cls.reads else None,
                   log=kw.pop("log", None) or logging.getLogger(f"stage.{stage_cls.qualname()}"), **kw)

    @property
    def frames(self) -> tuple[int, ...]:
        """The frames this run computes (``--frames``); declare "frames" in ``reads`` to use it."""
        if self._frames is None:
            raise UndeclaredRead('ctx.frames: the stage does not declare "frames" in its reads')
        return self._frames

    def progress(self, description: str, total: float) -> Progress:
        return self.make_progress(description, total)

    def warm_up(self, fn: Callable[[], Any]) -> Any:
        """Run ``fn`` (one-off work a second run in this process would not pay, e.g. a throw-away step
        that JIT-compiles a solver's kernels) and leave its time out of the stage's recorded cost."""
        w, c = time.perf_counter(), time.process_time()
        try:
            return fn()
        finally:
            self.warmup_seconds += time.perf_counter() - w
            self.warmup_cpu_seconds += time.process_time() - c

    def check_memory(self, need_bytes: float, details: str) -> None:
        """Refuse (exit 2, one line with ``details``) work about to allocate ``need_bytes`` when that exceeds
        the memory available now, unless the run allows large plans; for sizes only the inputs tell (the
        config alone did for the plan's size check before the run)."""
        refused = refusal(need_bytes, details, self.allow_large)
        if refused:
            raise StageError(refused)

    def resolve(self, path: str | Path) -> Path:
        """A path from the config, relative to the config file's folder."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else (self.config_dir / p)


class Stage:
    """Base class of stage implementations. Subclasses set the class attributes and implement
    ``run`` (whole-run stage) or ``run_frame`` (per-frame stage)."""

    kind: ClassVar[str]
    name: ClassVar[str]
    version: ClassVar[str]
    Params: ClassVar[type[Params]] = Params
    inputs: ClassVar[tuple[str, ...]] = ()
    optional_inputs: ClassVar[tuple[str, ...]] = ()
    outputs: ClassVar[tuple[str, ...]] = ()
    # config fields the stage reads, as dotted paths ("scene.units", "fluid.spacing", "walls"), and
    # "frames" if it uses the run's frame selection; the key holds exactly these, ctx exposes only these
    reads: ClassVar[tuple[str, ...]] = ()
    # config fields the plan-time hooks (``estimate``, ``check``) read beyond ``reads``: to size work made from
    # its inputs (the SDF's grid from the walls' bounds), to refuse walls that move; not keyed: the result
    # depends on them through the inputs' keys
    estimate_reads: ClassVar[tuple[str, ...]] = ()
    # a read whose growth the stage can continue from a cached shorter run ("scene.frames.count")
    extends: ClassVar[str | None] = None
    # the first run in a process pays one-off costs a second one does not (numba JIT compilation of its
    # set-up and stepping kernels): a study first runs it once on a 2-frame copy of the variant, untimed
    warm_up_run: ClassVar[bool] = False
    per_frame: ClassVar[bool] = False
    default: ClassVar[bool] = False  # the implementation used when the config names none for the kind
    description: ClassVar[str] = ""

    # -- hooks -------------------------------------------------------------------------------
    def input_names(self, params: Params) -> tuple[str, ...]:
        """Artifacts this stage consumes with these params (defaults to ``inputs``)."""
        return self.inputs

    def external_files(self, ctx: Context, params: Params) -> list[Path]:
        """Files outside the cache that this stage reads beyond the config's ``InputFile`` fields (which the
        engine finds itself), e.g. the layers a USD file composes; their content goes into the key."""
        return []

    def check(self, ctx: Context, params: Params) -> None:
        """Raise StageError (one line) for a scene this implementation cannot run, from the config alone before
        anything runs (``reads`` and ``estimate_reads``); what only its inputs show is refused when it runs."""

    def estimate(self, ctx: Context, params: Params) -> dict[str, float] | None:
        """The size of this stage's work from the config alone, before anything runs (no inputs yet):
        any of ``particles``, ``sdf_nodes``, ``steps``, ``memory_bytes`` (peak, this stage). None or a
        missing key when unknown (e.g. walls from a file whose bounds are not read yet)."""
        return None

    def frame_count(self, ctx: Context, params: Params, inputs: Mapping[str, Artifact]) -> int | None:
        """For whole-run stages whose output has frames: how many (None when not framed)."""
        return None

    def run(self, ctx: Context, inputs: Mapping[str, Artifact], params: Params) -> None:
        raise NotImplementedError

    def run_frame(self, ctx: Context, inputs: Mapping[str, Artifact], params: Params, frame: int) -> None:
        raise NotImplementedError

    def summarise(self, ctx: Context, params: Params, frames: Mapping[int, Path]) -> None:
        """Per-frame stages: say what only the frames together tell (how many came out empty), once per run.
        Frames may run in worker processes, each seeing only its own, so ``run_frame`` records what the summary
        needs in the frame's folder and the engine calls this in the process driving the run, once every frame
        of the run is in the cache and at least one was computed by this run (not when all came from the cache,
        a frame failed or the run was stopped). ``frames`` maps each of the run's frames to its entry folder,
        cached frames included (an entry another run made may lack what this code records). Read only:
        ``ctx.out_dir`` is None."""

    # -- helpers -----------------------------------------------------------------------------
    @classmethod
    def qualname(cls) -> str:
        return f"{cls.kind}.{cls.name}"

    @classmethod
    def check_contract(cls) -> None:
        """Raise TypeError naming the class when the declaration is incomplete or inconsistent."""
        where = f"{cls.__module__}.{cls.__qualname__}"
        for attr in ("kind", "name", "version"):
            if not isinstance(getattr(cls, attr, None), str) or not getattr(cls, attr):
                raise TypeError(f"stage {where}: class attribute {attr!r} must be a non-empty string")
        if cls.kind not in STAGE_KINDS:
            raise TypeError(f"stage {where}: kind {cls.kind!r} is not one of {', '.join(STAGE_KINDS)}")
        if not (isinstance(cls.Params, type) and issubclass(cls.Params, BaseModel)):
            raise TypeError(f"stage {where}: Params must be a pydantic model")
        if cls.Params.model_config.get("extra") != "forbid":
            raise TypeError(f"stage {where}: Params must forbid unknown keys (extra='forbid')")
        for attr in ("inputs", "optional_inputs", "outputs", "reads", "estimate_reads"):
            value = getattr(cls, attr)
            if isinstance(value, str) or not all(isinstance(v, str) for v in value):
                raise TypeError(f"stage {where}: {attr} must be a tuple of names, not {value!r}")
        if not cls.outputs:
            raise TypeError(f"stage {where}: declares no outputs")
        if "use" in cls.Params.model_fields:  # the config's 'use:' picks the implementation: never a parameter
            raise TypeError(f"stage {where}: Params may not have a field named 'use'")
        defaults = {n: f.get_default(call_default_factory=True) for n, f in cls.Params.model_fields.items()
                    if not f.is_required()}
        try:  # a default the model's own constraints refuse would run, and be keyed, as if valid
            cls.Params.model_validate(defaults)
        except ValidationError as e:
            for err in e.errors():
                if err["type"] != "missing":  # a required field has no default to check
                    raise TypeError(f"stage {where}: Params default of {'.'.join(map(str, err['loc']))} "
                                    f"({err.get('input')!r}) is not valid: {err['msg']}") from None
        for read in cls.reads:
            try:
                check_read(read)
            except ValueError as e:
                raise TypeError(f"stage {where}: reads {e}") from None
        if cls.extends is not None and cls.extends not in cls.reads:
            raise TypeError(f"stage {where}: extends {cls.extends!r} must also be declared in reads")
        hook = "run_frame" if cls.per_frame else "run"
        if getattr(cls, hook) is getattr(Stage, hook):
            raise TypeError(f"stage {where}: per_frame={cls.per_frame} but {hook}() is not implemented")
