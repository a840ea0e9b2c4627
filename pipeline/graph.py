"""The stage DAG of one config: which stages the wanted outputs need, and partial-run selections.

Building walks back from the wanted outputs through each stage's required inputs; optional inputs
are wired only when their producer is needed anyway. ``only``/``from_``/``until`` are pure functions
that return a new Graph: ``nodes`` are the stages whose keys must be known (the needed ones and their
upstream), ``runnable`` those allowed to compute; the others are read from the cache.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from .config import Config
from .errors import ConfigError
from .stage import STAGE_KINDS, Params, Stage


@dataclass(frozen=True)
class Node:
    kind: str
    cls: type[Stage]
    params: Params
    inputs: tuple[tuple[str, str], ...]  # (artifact name, producer kind)

    @property
    def per_frame(self) -> bool:
        return self.cls.per_frame

    @property
    def label(self) -> str:
        return f"{self.kind}.{self.cls.name}"


@dataclass(frozen=True)
class Graph:
    nodes: dict[str, Node]  # kind -> node, in dependency order
    outputs: tuple[str, ...]  # wanted artifacts that this graph produces
    runnable: frozenset[str] = field(default_factory=frozenset)

    def order(self) -> list[str]:
        return [k for k in STAGE_KINDS if k in self.nodes]

    def upstream(self, kind: str) -> set[str]:
        seen: set[str] = set()
        stack = [kind]
        while stack:
            for _, producer in self.nodes[stack.pop()].inputs:
                if producer not in seen:
                    seen.add(producer)
                    stack.append(producer)
        return seen

    def downstream(self, kind: str) -> set[str]:
        return {k for k in self.nodes if kind in self.upstream(k)}

    def _require(self, kind: str, flag: str) -> None:
        if kind not in self.nodes:
            raise ConfigError(f"{flag} {kind}: not a stage this config runs (it runs: {', '.join(self.order())})")

    # -- pure selections -----------------------------------------------------------------------
    def only(self, kind: str) -> "Graph":
        self._require(kind, "--only")
        keep = self.upstream(kind) | {kind}
        return replace(self, nodes={k: v for k, v in self.nodes.items() if k in keep},
                       outputs=tuple(o for o in self.outputs if self.producer(o) == kind),
                       runnable=frozenset({kind}))

    def from_(self, kind: str) -> "Graph":
        """``kind`` and what follows it: the outputs made by ``kind`` or its descendants, with their upstream
        read from the cache. An output not downstream of ``kind`` (the USD export for ``--from render``) is
        not made and its stage is not needed in the cache (it was required: a run stopped before export
        could not go on with ``--from render``); what an earlier run published of it stays (publish.drop_stale)."""
        self._require(kind, "--from")
        tail = self.downstream(kind) | {kind}
        keep = tail.union(*(self.upstream(k) for k in tail))
        return replace(self, nodes={k: v for k, v in self.nodes.items() if k in keep},
                       outputs=tuple(o for o in self.outputs if self.producer(o) in tail),
                       runnable=frozenset(self.runnable & tail))

    def until(self, kind: str) -> "Graph":
        self._require(kind, "--until")
        keep = self.upstream(kind) | {kind}
        return replace(self, nodes={k: v for k, v in self.nodes.items() if k in keep},
                       outputs=tuple(o for o in self.outputs if self.producer(o) in keep),
                       runnable=frozenset(self.runnable & keep))

    def producer(self, artifact: str) -> str | None:
        for kind, node in self.nodes.items():
            if artifact in node.cls.outputs:
                return kind
        return None


def _unloadable(config: Config) -> str:
    """Why a default stage that would have produced it is missing: it failed to load (an import error)."""
    return "".join(f"; the default {kind} stage failed to load: {why}" for kind, why in config.unloadable.items())


def build_graph(config: Config) -> Graph:
    producers: dict[str, str] = {}
    for kind, choice in config.stages.items():
        for out in choice.cls.outputs:
            producers.setdefault(out, kind)

    needed: set[str] = set()
    stack: list[str] = []
    for out in config.outputs:
        if out not in producers:
            raise ConfigError(f"{config.path}: outputs: no installed stage produces {out!r}{_unloadable(config)}")
        stack.append(producers[out])
    while stack:
        kind = stack.pop()
        if kind in needed:
            continue
        needed.add(kind)
        choice = config.stages[kind]
        for name in choice.cls().input_names(choice.params):
            if name not in producers:
                raise ConfigError(f"{config.path}: stage {kind}.{choice.cls.name} needs artifact {name!r}, which no configured "
                                  f"stage produces{_unloadable(config)}")
            stack.append(producers[name])

    nodes: dict[str, Node] = {}
    for kind in STAGE_KINDS:
        if kind not in needed:
            continue
        choice = config.stages[kind]
        wired = [(n, producers[n]) for n in choice.cls().input_names(choice.params)]
        wired += [(n, producers[n]) for n in choice.cls.optional_inputs
                  if n in producers and producers[n] in needed and (n, producers[n]) not in wired]
        for _, producer in wired:
            if STAGE_KINDS.index(producer) >= STAGE_KINDS.index(kind):
                raise ConfigError(f"{config.path}: stage {kind} cannot consume the output of {producer}, which runs after it")
        nodes[kind] = Node(kind=kind, cls=choice.cls, params=choice.params, inputs=tuple(wired))
    return Graph(nodes=nodes, outputs=tuple(o for o in config.outputs), runnable=frozenset(nodes))
