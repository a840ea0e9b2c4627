"""The memory a run may take: what is available now, and the one refusal line (exit 2) shared by the
plan's size check before anything runs (estimate.check_size) and a stage's own check once its inputs
tell the size (Context.check_memory). Imports nothing of the engine, so stages' keys do not follow it."""
from __future__ import annotations

import os


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


def human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1024 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PB"


def refusal(need: float, details: str, allow_large: bool) -> str | None:
    """The refusal (without its prefix naming the config or stage) when ``need`` bytes exceed the memory
    available now and ``allow_large`` (--yes, config allow_large: true) is not set; else None."""
    avail = available_memory()
    if allow_large or avail is None or need <= avail:
        return None
    return (f"would need about {human(need)} of memory ({details}) but {human(avail)} is available; make "
            f"fluid.spacing or the scene smaller, or run anyway with --yes (config: allow_large: true)")
