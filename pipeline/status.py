"""What `pipeline status` and `pipeline clean` tell and do: per stage cached / stale (with the cause:
params, config field, code, frame selection, upstream, input file) / missing; removing a config's entries."""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .cache import Cache, running
from .config import load_config
from .errors import ConfigError
from .graph import Graph, build_graph
from .keys import frame_key, plan, resume_source
from .registry import Registry
from .runner import default_cache_dir


@dataclass
class StageStatus:
    kind: str
    implementation: str
    key: str
    state: str  # cached / stale / missing / partial / running
    reason: str
    seconds: float | None


def _diff(old: dict[str, Any], new: dict[str, Any], graph: Graph, config_dir: Path) -> str:
    if old.get("stage") != new.get("stage"):
        return f"implementation {old.get('stage')} -> {new.get('stage')}"
    if old.get("version") != new.get("version"):
        return f"code version {old.get('version')} -> {new.get('version')}"
    oc, nc = old.get("code", {}), new.get("code", {})
    if oc != nc:
        changed = sorted(m for m in set(oc) | set(nc) if oc.get(m) != nc.get(m))
        return f"code changed: {', '.join(changed[:3])}{' ...' if len(changed) > 3 else ''}"
    if old.get("frames") != new.get("frames"):
        return f"frame selection changed ({len(old.get('frames') or [])} -> {len(new.get('frames') or [])} frames)"
    for section in ("params", "scene"):
        a, b = _flatten(old.get(section, {})), _flatten(new.get(section, {}))
        changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        if changed:
            k = changed[0]
            more = f" (+{len(changed) - 1} more)" if len(changed) > 1 else ""
            return f"{section}: {k} {a.get(k, '<unset>')!r} -> {b.get(k, '<unset>')!r}{more}"
    oi, ni = old.get("inputs", {}), new.get("inputs", {})
    for name in sorted(set(oi) | set(ni)):
        if oi.get(name) != ni.get(name):
            return f"upstream {name} changed"
    of, nf = old.get("files", {}), new.get("files", {})
    for name in sorted(set(of) | set(nf)):
        if of.get(name) != nf.get(name):
            if name not in nf:  # a layer a USD no longer composes: gone (the run refuses it), or no longer named
                gone = not Path(config_dir, name).exists()
                return f"input file {'missing' if gone else 'no longer read'}: {name}"
            return f"input file changed: {name}"
    return "key schema changed"


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, (dict, list)) and value:
        out: dict[str, Any] = {}
        for k, v in (value.items() if isinstance(value, dict) else enumerate(value)):
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix.rstrip("."): value}


def status(config_path: str | Path, *, registry: Registry | None = None, overrides: tuple[str, ...] = (),
           cache_dir: str | Path | None = None, frames: tuple[int, ...] | None = None) -> list[StageStatus]:
    registry = registry or Registry.from_entry_points()
    config = load_config(config_path, registry, overrides)
    graph = build_graph(config)
    cache = Cache(Path(cache_dir) if cache_dir else default_cache_dir(config))
    p = plan(config, graph, cache, frames)
    last = cache.read_state(config.path)
    rows: list[StageStatus] = []
    for kind in graph.order():
        node, key = graph.nodes[kind], p.keys[kind]
        prev = last.get(kind, {})
        if node.per_frame:
            hits = [cache.lookup(kind, frame_key(key, f)) for f in p.frames]
            n = sum(h is not None for h in hits)
            seconds = sum(float(h.manifest.get("seconds", 0)) for h in hits if h is not None) if n else None
            if n == len(p.frames):
                rows.append(StageStatus(kind, node.cls.name, key, "cached", f"{n} frames", seconds))
                continue
            if n:
                rows.append(StageStatus(kind, node.cls.name, key, "partial", f"{n}/{len(p.frames)} frames cached", seconds))
                continue
        else:
            hit = cache.lookup(kind, key)
            if hit is not None:
                rows.append(StageStatus(kind, node.cls.name, key, "cached", "up to date",
                                        float(hit.manifest.get("seconds", 0.0))))
                continue
            if cache.exists(kind, key):
                rows.append(StageStatus(kind, node.cls.name, key, "stale", "entry damaged (files differ from manifest)", None))
                continue
        extends = ""
        if kind in p.resume and resume_source(cache, kind, p.resume[kind]) is not None:
            extends = f"; continues the cached shorter run ({node.cls.extends})"
        if prev.get("key") and prev["key"] != key:
            rows.append(StageStatus(kind, node.cls.name, key, "stale",
                                    _diff(prev.get("components", {}), p.components[kind], graph, config.dir) + extends,
                                    prev.get("seconds")))
        elif (holder := running(cache, key)) is not None:
            rows.append(StageStatus(kind, node.cls.name, key, "running", f"being computed by {holder}", None))
        else:
            rows.append(StageStatus(kind, node.cls.name, key, "missing", "never run with these inputs" + extends, None))
    return rows


def clean(config_path: str | Path, *, registry: Registry | None = None, stage: str | None = None,
          cache_dir: str | Path | None = None, overrides: tuple[str, ...] = ()) -> int:
    """Remove the cache entries (all frames) of this config, and those of its last run (whatever it was run
    with), or only one stage's; returns how many. With ``overrides`` (parsed as run's --set), only the
    entries of the config with them applied. Entries made under other overrides stay: entries are
    content-addressed (shared by every config that gives a stage the same inputs) and do not record which
    config or overrides made them. A cache folder that does not exist is left so (0 removed)."""
    return clean_cache(config_path, registry=registry, stage=stage, cache_dir=cache_dir, overrides=overrides)[0]


def clean_cache(config_path: str | Path, *, registry: Registry | None = None, stage: str | None = None,
                cache_dir: str | Path | None = None, overrides: tuple[str, ...] = ()) -> tuple[int, Path | None]:
    """``clean``, and the cache folder when there is none there (for `pipeline clean` to say so), else None."""
    registry = registry or Registry.from_entry_points()
    config = load_config(config_path, registry, overrides)
    graph = build_graph(config)
    if stage is not None and stage not in graph.nodes:
        raise ConfigError(f"--stage {stage}: not a stage of this config ({', '.join(graph.order())})")
    cache = Cache(Path(cache_dir) if cache_dir else default_cache_dir(config))
    p = plan(config, graph, cache, tuple(range(config.scene.scene.frames.count)))  # a bad input file: still said
    if not cache.root.is_dir():  # a mistyped --cache was made (with locks/runs.lock) to report 0 removed
        return 0, cache.root
    # the last run's keys (the state is per config file, whatever overrides that run had): not with overrides,
    # which name one variant
    last = cache.read_state(config.path) if not overrides else {}
    with cache.alone("clean"):
        return _remove(cache, graph, p, last, stage), None


def _remove(cache: Cache, graph, p, last: dict, stage: str | None) -> int:
    """Remove the planned entries of each stage (or ``stage``) and those of the last run (its frames)."""
    removed = 0
    for kind in graph.order():
        if stage is not None and kind != stage:
            continue
        keys = {p.keys[kind]: p.frames}
        if kind in last:  # the last run's frames: a shot since shortened left its tail behind
            made = set(keys.get(last[kind]["key"], ())) | set(last[kind].get("frames", p.frames))
            keys[last[kind]["key"]] = tuple(sorted(made))
        for key, frames in keys.items():
            if graph.nodes[kind].per_frame:
                removed += sum(cache.remove(kind, frame_key(key, f)) for f in frames)
            else:
                removed += int(cache.remove(kind, key))
                shutil.rmtree(cache.checkpoint_dir(key), ignore_errors=True)
    return removed
