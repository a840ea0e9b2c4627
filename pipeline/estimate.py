"""The plan's size before anything runs: each stage's ``estimate`` hook (particles, SDF nodes, steps,
memory), printed, and checked against the machine's available memory.

A run whose estimated peak memory (the largest single stage: stages run one after another, per-frame
jobs are small) exceeds the memory available now is refused with exit 2 and the numbers, unless
``--yes`` or the config's ``allow_large: true`` says to try anyway.
"""
from __future__ import annotations

import logging
import os
from typing import Any

from .errors import ConfigError
from .keys import context

log = logging.getLogger("pipeline")


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable), or None when unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return None


def _human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1024 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PB"


def plan_size(p: Any) -> dict[str, dict[str, float]]:
    """Each stage's estimate (stages whose hook knows nothing are left out)."""
    sizes: dict[str, dict[str, float]] = {}
    for kind in p.graph.order():
        node = p.graph.nodes[kind]
        ctx = context(p.config, node, p.config.dir, p.frames)
        est = node.cls().estimate(ctx, node.params)
        if est:
            sizes[kind] = {k: float(v) for k, v in est.items() if v is not None}
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
                 f"~{_human(est['memory_bytes'])}" if "memory_bytes" in est else ""]
        parts.append(f"{kind}: " + ", ".join(x for x in shown if x))
    peak_kind, peak = max(((k, e.get("memory_bytes", 0.0)) for k, e in sizes.items()), key=lambda t: t[1])
    avail = available_memory()
    if avail is not None and peak > avail and not allow_large:
        raise ConfigError(f"{p.config.path}: stage {peak_kind} would need about {_human(peak)} of memory "
                          f"({'; '.join(parts)}) but {_human(avail)} is available; make fluid.spacing or the "
                          f"scene smaller, or run anyway with --yes (config: allow_large: true)")
    log.info("plan size: %s", "; ".join(parts))  # a refusal carries the numbers in its one line
    return sizes
