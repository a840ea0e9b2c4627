"""Run one stage directly, without the graph or the cache: for stage authors' tests."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from .scene import SceneConfig
from .stage import Artifact, Context, Stage


def scene_sections(config: Mapping[str, Any] | SceneConfig) -> dict[str, Any]:
    """Validated scene sections (scene, walls, fluid, effects, camera) from a plain dict or a SceneConfig."""
    sc = config if isinstance(config, SceneConfig) else SceneConfig.model_validate(dict(config))
    return {"scene": sc.scene, "walls": sc.walls, "fluid": sc.fluid, "effects": sc.effects, "camera": sc.camera}


def stage_context(stage_cls: type[Stage], out_dir: Path, *, scene: Mapping[str, Any] | SceneConfig,
                  frames: tuple[int, ...] | None = None, config_dir: Path | None = None, **kw: Any) -> Context:
    """The Context the engine would give ``stage_cls``: only its declared reads are visible."""
    sections = scene_sections(scene)
    if frames is None:
        frames = tuple(range(sections["scene"].frames.count))
    return Context.for_stage(stage_cls, sections, out_dir=Path(out_dir), config_dir=config_dir or Path.cwd(),
                             frames=tuple(frames), **kw)


def run_stage(stage_cls: type[Stage], out_dir: Path, *, scene: Mapping[str, Any] | SceneConfig,
              params: Mapping[str, Any] | None = None, inputs: Mapping[str, Path] | None = None,
              frames: tuple[int, ...] | None = None, config_dir: Path | None = None) -> Path:
    """Validate ``params`` with the stage's model and run it into ``out_dir``; whole-run inputs are
    given as folders. Per-frame stages run every frame in ``frames`` (default: all scene frames), then
    ``summarise`` over them."""
    stage_cls.check_contract()
    sections = scene_sections(scene)
    p = stage_cls.Params.model_validate(dict(params or {}))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if frames is None:
        frames = tuple(range(sections["scene"].frames.count))
    ctx = stage_context(stage_cls, out_dir, scene=sections, frames=frames, config_dir=config_dir)
    arts = {name: Artifact(name=name, key="test", path=Path(path)) for name, path in (inputs or {}).items()}
    stage = stage_cls()
    if stage_cls.per_frame:
        for f in frames:
            stage.run_frame(ctx, arts, p, f)
        # as the engine: once all frames are done, read only (out_dir None)
        stage.summarise(Context.for_stage(stage_cls, sections, out_dir=None, config_dir=config_dir or Path.cwd(),
                                          frames=tuple(frames)), p, {f: out_dir for f in frames})
    else:
        stage.run(ctx, arts, p)
    return out_dir
