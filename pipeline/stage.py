"""The contract every stage implementation fulfils.

A stage is a small class: its kind (the DAG node it can fill, e.g. ``simulate``), its implementation
name (chosen in the config with ``use:``), a hand-bumped code ``version``, a typed ``Params`` model,
the artifacts it consumes and produces, the scene sections it reads, and ``run`` (or ``run_frame`` for
per-frame stages). The engine checks the contract when the stage is registered and hashes
``version``, the validated params (defaults included), the scene sections it reads, its upstream keys
and the content of the external files it names into the cache key.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping

from pydantic import BaseModel, ConfigDict

# The stage kinds of the DAG, in dependency order, and the artifact each one produces. The engine
# knows these names (they are the vocabulary of configs), never the implementations.
STAGE_KINDS: tuple[str, ...] = (
    "mesh_import", "sdf_bake", "simulate", "surface_extract", "wall_snap", "render", "movie", "export",
)

# The scene sections a stage may declare in ``reads``.
SCENE_SECTIONS: tuple[str, ...] = ("scene", "walls", "fluid", "effects", "camera")


class Params(BaseModel):
    """Base of every stage's parameter model: unknown keys are errors, NaN/inf are errors, values
    validated on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


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


@dataclass
class Context:
    """What a running stage may use: its scratch output folder, the scene sections it declared, the
    config file's folder (paths in the config are relative to it), the frame set, a logger and a
    progress factory."""

    out_dir: Path
    scene: Mapping[str, Any]
    config_dir: Path
    frames: tuple[int, ...]
    log: logging.Logger
    make_progress: Callable[[str, float], Progress] = lambda description, total: Progress()
    threads: int | None = None
    # a folder that survives an interrupted run of this stage key (checkpoints); None when not cached
    checkpoint_dir: Path | None = None

    def progress(self, description: str, total: float) -> Progress:
        return self.make_progress(description, total)

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
    reads: ClassVar[tuple[str, ...]] = ()
    per_frame: ClassVar[bool] = False
    default: ClassVar[bool] = False  # the implementation used when the config names none for the kind
    description: ClassVar[str] = ""

    # -- hooks -------------------------------------------------------------------------------
    def input_names(self, params: Params) -> tuple[str, ...]:
        """Artifacts this stage consumes with these params (defaults to ``inputs``)."""
        return self.inputs

    def external_files(self, ctx: Context, params: Params) -> list[Path]:
        """Files outside the cache that this stage reads; their content goes into the key."""
        return []

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
        if not cls.outputs:
            raise TypeError(f"stage {where}: declares no outputs")
        for section in cls.reads:
            if section not in SCENE_SECTIONS:
                raise TypeError(f"stage {where}: reads unknown scene section {section!r}")
        hook = "run_frame" if cls.per_frame else "run"
        if getattr(cls, hook) is getattr(Stage, hook):
            raise TypeError(f"stage {where}: per_frame={cls.per_frame} but {hook}() is not implemented")
