"""Before anything runs: each stage's ``check`` hook (a scene its implementation cannot run is refused in
one line, exit 2), and the plan's size: each stage's ``estimate`` hook (particles, SDF nodes, steps,
memory), printed, and checked against the machine's available memory.

A run whose estimated peak memory (the largest single stage: stages run one after another, per-frame
jobs are small) exceeds the memory available now is refused with exit 2 and the numbers, unless
``--yes`` or the config's ``allow_large: true`` says to try anyway.
"""
from __future__ import annotations

import logging
from typing import Any

from .errors import ConfigError, StageFailed
from .keys import call_hook, context
from .stage import StageError
from .memory import human, refusal

log = logging.getLogger("pipeline")

# a plan estimated at more steps than this is said before it runs (scene.frames.fps 0.01 made a 15-frame shot 1,500 s
# long: 2.2 M steps, said only in the plan's info line, and the run looked hung)
LONG_RUN_STEPS = 1e6


def check_stages(config: Any, graph: Any) -> None:
    """ConfigError naming the config file and the stage's ``use`` line when a stage's ``check`` refuses the
    scene (DFSPH and walls[].motion were refused only once the import and the bake had run)."""
    frames = tuple(range(config.scene.scene.frames.count))
    for kind in graph.order():
        node = graph.nodes[kind]
        ctx = context(config, node, config.dir, frames, extra_reads=node.cls.estimate_reads)
        try:
            call_hook(node, "check", ctx, node.params)
        except StageError as e:
            raise ConfigError(f"{config.where('stages', kind, 'use')}: {e}") from None


def plan_size(p: Any) -> dict[str, dict[str, float]]:
    """Each stage's estimate (stages whose hook knows nothing are left out). The hook sees the stage's
    ``reads`` and its ``estimate_reads`` (config its inputs are made from, e.g. the walls for the SDF's
    bounds): an estimate is not keyed, so reading more does not change a key."""
    sizes: dict[str, dict[str, float]] = {}
    for kind in p.graph.order():
        node = p.graph.nodes[kind]
        ctx = context(p.config, node, p.config.dir, p.frames, extra_reads=node.cls.estimate_reads)
        est = call_hook(node, "estimate", ctx, node.params)
        if est:
            try:
                sizes[kind] = {k: float(v) for k, v in est.items() if v is not None}
            except (AttributeError, TypeError, ValueError) as e:
                raise StageFailed(f"stage {node.label}: its estimate() returned {est!r}, not a mapping of numbers "
                                  f"({e})", user_error=False) from None
    return sizes


def check_size(p: Any, *, allow_large: bool = False) -> dict[str, dict[str, float]]:
    """Log the plan's size; raise ConfigError (exit 2) when its memory estimate exceeds the available
    memory and ``allow_large`` is not set."""
    sizes = plan_size(p)
    if not sizes:
        return sizes
    parts = []
    for kind, est in sizes.items():
        shown = [f"{int(est['particles']):,} particles" if "particles" in est else "",
                 f"{int(est['sdf_nodes']):,} SDF nodes" if "sdf_nodes" in est else "",
                 f"~{int(est['steps']):,} steps" if "steps" in est else "",
                 f"~{human(est['memory_bytes'])}" if "memory_bytes" in est else ""]
        parts.append(f"{kind}: " + ", ".join(x for x in shown if x))
    peak_kind, peak = max(((k, e.get("memory_bytes", 0.0)) for k, e in sizes.items()), key=lambda t: t[1])
    refused = refusal(peak, "; ".join(parts), allow_large)
    if refused:
        raise ConfigError(f"{p.config.path}: stage {peak_kind} {refused}")
    log.info("plan size: %s", "; ".join(parts))  # a refusal carries the numbers in its one line
    frames = p.config.scene.scene.frames
    for kind, est in sizes.items():
        if est.get("steps", 0.0) > LONG_RUN_STEPS:
            log.warning("stage %s: about %s time steps for %g s of shot (scene.frames: %d at %g fps): hours of work; "
                        "check scene.frames, fluid.spacing and the emitters' speeds", kind, f"{int(est['steps']):,}",
                        frames.count / frames.fps, frames.count, frames.fps)
    return sizes
