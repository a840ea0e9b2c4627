"""Stage implementations, found through the ``pipeline.stages`` entry-point group.

Entry point names are ``<kind>.<implementation>``; the value is ``module:Class``. Modules are
imported lazily, only when a config needs that implementation (importing every stage would pull in
open3d, pyvista and friends for a ``pipeline status``). The engine never imports a stage module by
name; tests and embedding code may also ``add`` classes directly.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from .errors import RegistryError
from .stage import STAGE_KINDS, Stage

GROUP = "pipeline.stages"


@dataclass
class _Entry:
    kind: str
    name: str
    source: str  # "module:Class" or "<added>"
    entry_point: EntryPoint | None = None
    cls: type[Stage] | None = None
    error: str | None = None


def _origin(ep: EntryPoint | None) -> str:
    dist = getattr(ep, "dist", None)
    return f"{ep.value if ep else '?'} (from {dist.name} {dist.version})" if dist is not None else (ep.value if ep else "?")


class Registry:
    def __init__(self) -> None:
        self._entries: dict[tuple[str, str], _Entry] = {}

    @classmethod
    def from_entry_points(cls, group: str = GROUP) -> "Registry":
        reg = cls()
        for ep in sorted(entry_points(group=group), key=lambda e: e.name):
            kind, _, name = ep.name.partition(".")
            if not name or kind not in STAGE_KINDS:
                reg._entries[(kind, name or "?")] = _Entry(kind, name, ep.value, ep,
                                                           error=f"entry point name {ep.name!r} must be <kind>.<name> with a known kind")
                continue
            known = reg._entries.get((kind, name))
            if known is not None and known.source != ep.value:  # which one loads would depend on sys.path order
                known.error = (f"registered twice, as {_origin(known.entry_point)} and as {_origin(ep)}: "
                               "uninstall one (or rename its entry point)")
                continue
            reg._entries[(kind, name)] = _Entry(kind, name, ep.value, ep)
        return reg

    def add(self, stage_cls: type[Stage]) -> type[Stage]:
        """Register a class directly (checks the contract now)."""
        try:
            stage_cls.check_contract()
        except TypeError as e:
            raise RegistryError(str(e)) from None
        self._entries[(stage_cls.kind, stage_cls.name)] = _Entry(stage_cls.kind, stage_cls.name, "<added>", cls=stage_cls)
        return stage_cls

    def implementations(self, kind: str) -> list[str]:
        return sorted(name for (k, name) in self._entries if k == kind)

    def entries(self) -> list[tuple[str, str, str]]:
        return [(e.kind, e.name, e.source) for e in sorted(self._entries.values(), key=lambda e: (e.kind, e.name))]

    def get(self, kind: str, name: str) -> type[Stage]:
        entry = self._entries.get((kind, name))
        if entry is None:
            known = ", ".join(self.implementations(kind)) or "none installed"
            raise RegistryError(f"no {kind} implementation named {name!r} (installed: {known})")
        if entry.cls is None:
            if entry.error is None:
                try:
                    loaded = entry.entry_point.load()  # type: ignore[union-attr]
                    if not (isinstance(loaded, type) and issubclass(loaded, Stage)):
                        raise TypeError(f"{entry.source} is not a Stage subclass")
                    loaded.check_contract()
                    if (loaded.kind, loaded.name) != (kind, name):
                        raise TypeError(f"{entry.source} declares {loaded.kind}.{loaded.name}, registered as {kind}.{name}")
                    entry.cls = loaded
                except Exception as e:  # an installed plugin that fails to import is reported, not fatal
                    entry.error = f"{type(e).__name__}: {e}"
            if entry.cls is None:
                raise RegistryError(f"stage {kind}.{name} ({entry.source}) cannot be loaded: {entry.error}")
        return entry.cls

    def default(self, kind: str) -> type[Stage]:
        names = self.implementations(kind)
        if not names:
            raise RegistryError(f"no {kind} implementation is installed")
        if len(names) == 1:
            return self.get(kind, names[0])
        defaults = []
        for n in names:
            try:
                c = self.get(kind, n)
            except RegistryError:
                continue
            if c.default:
                defaults.append(c)
        if len(defaults) != 1:
            raise RegistryError(f"stage kind {kind} has implementations {', '.join(names)}; "
                                f"name one with 'use:' ({len(defaults)} are marked default)")
        return defaults[0]

    def load_error(self, kind: str, name: str) -> str | None:
        try:
            self.get(kind, name)
        except RegistryError as e:
            return str(e)
        return None
