"""One live table of every shot or study variant while they run: state, stage, progress of the current
step loop or frames, and an ETA from its rate so far. Fed with the runner's events (``{"label", "stage"}``,
``{"label", "task", "done", "total"}``, ``{"label", "state"}``), from this process or from Dask workers;
drawn on stderr only when it is a terminal."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class _Row:
    state: str = "queued"
    stage: str = ""
    task: str = ""
    done: float = 0.0
    total: float = 0.0
    task_start: float = field(default_factory=time.monotonic)
    start: float | None = None
    end: float | None = None


class LiveView:
    def __init__(self, labels: list[str], enabled: bool) -> None:
        self.rows = {label: _Row() for label in labels}
        self._lock = threading.Lock()
        self._live = None
        if enabled:
            from rich.console import Console
            from rich.live import Live

            self._live = Live(get_renderable=self.table, console=Console(stderr=True), refresh_per_second=2,
                              transient=False)

    def __call__(self, event: dict[str, Any]) -> None:
        with self._lock:
            row = self.rows.setdefault(event.get("label", "?"), _Row())
            now = time.monotonic()
            if row.start is None:
                row.start, row.state = now, "running"
            if "stage" in event:
                row.stage, row.task, row.done, row.total = event["stage"], "", 0.0, 0.0
            if "task" in event:
                if event["task"] != row.task:
                    row.task, row.task_start = event["task"], now
                row.done, row.total = float(event["done"]), float(event["total"])
            if "state" in event:
                row.state = event["state"]
                if row.state in ("done", "failed"):
                    row.end = now

    def table(self):
        from rich.table import Table

        table = Table("shot", "state", "stage", "progress", "elapsed", "ETA")
        colour = {"done": "green", "failed": "red", "running": "cyan", "queued": "dim"}
        now = time.monotonic()
        with self._lock:
            for label, r in self.rows.items():
                progress = f"{r.task} {r.done:.0f}/{r.total:.0f}" if r.task else ""
                eta = ""
                if r.state == "running" and r.task and 0 < r.done < r.total:
                    eta = f"{(now - r.task_start) * (r.total - r.done) / r.done:.0f} s"
                elapsed = "" if r.start is None else f"{(r.end or now) - r.start:.0f} s"
                table.add_row(label, f"[{colour.get(r.state, 'white')}]{r.state}[/]", r.stage, progress, elapsed, eta)
        return table

    def __enter__(self) -> "LiveView":
        if self._live is not None:
            self._live.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._live is not None:
            self._live.stop()
