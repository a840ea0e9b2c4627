"""What a stage may read of the config, and nothing more.

A stage declares ``reads``: dotted paths into the scene (``"scene.units"``, ``"fluid.spacing"``,
``"walls"``) and, if it uses the run's frame selection (``ctx.frames``), the name ``"frames"``. The
engine keys the stage on exactly those values, and the stage's Context exposes exactly those: reading an
undeclared field raises UndeclaredRead, so a stage cannot depend on a value that is not in its key.
Every field typed ``InputFile`` (pipeline.scene) inside the declared values or the stage's params is a
file the stage reads: the engine hashes its content into the key.
"""
from __future__ import annotations

import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Iterator

from pydantic import BaseModel

from .scene import INPUT_FILE, SceneConfig

FRAMES = "frames"  # the pseudo-read of the run's frame selection


class UndeclaredRead(LookupError):
    """A stage read a config field (or ctx.frames) that its ``reads`` does not declare: a bug in the
    stage, since the value is not in its cache key."""


# -- declarations ----------------------------------------------------------------------------------
def annotation_members(annotation: Any) -> list:
    """The types an annotation stands for: Annotated unwrapped, a union's members each."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return annotation_members(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(annotation) for m in annotation_members(a)]
    return [annotation]


def is_model(t: Any) -> bool:
    return isinstance(t, type) and issubclass(t, BaseModel)


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model behind an annotation (Optional and Annotated unwrapped), else None."""
    models = [m for m in annotation_members(annotation) if is_model(m)]
    return models[0] if len(models) == 1 else None


def check_read(path: str) -> None:
    """Raise ValueError unless ``path`` is "frames" or a dotted path through the scene models."""
    if path == FRAMES:
        return
    model: type[BaseModel] | None = SceneConfig
    walked: list[str] = []
    for part in path.split("."):
        if model is None:
            raise ValueError(f"{'.'.join(walked)} has no fields; {path!r} cannot be read")
        if part not in model.model_fields:
            raise ValueError(f"{path!r}: {'.'.join(walked + [part])} is not a config field")
        model = _model_of(model.model_fields[part].annotation)
        walked.append(part)


def normalise(reads: tuple[str, ...]) -> tuple[str, ...]:
    """Sorted, without duplicates and without paths inside another declared path."""
    unique = sorted(set(reads))
    return tuple(p for p in unique if not any(p.startswith(q + ".") for q in unique if q != p))


# -- values ----------------------------------------------------------------------------------------
def value_at(sections: Mapping[str, Any], path: str) -> Any:
    """The config value at a dotted path (None when a section on the way is absent)."""
    head, *rest = path.split(".")
    value = sections[head]
    for part in rest:
        if value is None:
            return None
        value = getattr(value, part)
    return value


class FieldView:
    """A read-only view of a config model that lets through only the declared sub-paths."""

    __slots__ = ("_value", "_path", "_allowed")

    def __init__(self, value: Any, path: str, allowed: tuple[str, ...]) -> None:
        object.__setattr__(self, "_value", value)
        object.__setattr__(self, "_path", path)
        object.__setattr__(self, "_allowed", allowed)

    def __getattr__(self, name: str) -> Any:
        path = f"{self._path}.{name}"
        if path in self._allowed:
            return getattr(self._value, name)
        if any(a.startswith(path + ".") for a in self._allowed):
            inner = getattr(self._value, name)
            return None if inner is None else FieldView(inner, path, self._allowed)
        raise UndeclaredRead(f"{path} is not in the stage's reads ({', '.join(self._allowed)})")

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("the config is read-only")

    def __reduce__(self):  # picklable for process pools despite __getattr__
        return FieldView, (self._value, self._path, self._allowed)

    def __repr__(self) -> str:
        return f"FieldView({self._path}: {', '.join(self._allowed)})"


class SceneReads(Mapping):
    """``ctx.scene``: section name -> the section (declared whole) or a FieldView (declared in part)."""

    def __init__(self, sections: Mapping[str, Any], reads: tuple[str, ...]) -> None:
        self._reads = normalise(tuple(r for r in reads if r != FRAMES))
        self._values: dict[str, Any] = {}
        for head in dict.fromkeys(r.split(".")[0] for r in self._reads):
            value = sections.get(head)
            whole = head in self._reads
            self._values[head] = value if whole or value is None else FieldView(value, head, self._reads)

    def __getitem__(self, section: str) -> Any:
        try:
            return self._values[section]
        except KeyError:
            raise UndeclaredRead(f"scene section {section!r} is not in the stage's reads "
                                 f"({', '.join(self._reads) or 'none'})") from None

    def __contains__(self, section: object) -> bool:
        return section in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __reduce__(self):
        return _rebuild_reads, (self._values, self._reads)


def _rebuild_reads(values: dict[str, Any], reads: tuple[str, ...]) -> SceneReads:
    obj = SceneReads.__new__(SceneReads)
    obj._values, obj._reads = values, reads
    return obj


def _unwrap(value: Any) -> Any:
    return value._value if isinstance(value, FieldView) else value


def read_values(sections: Mapping[str, Any], reads: tuple[str, ...]) -> dict[str, Any]:
    """``{dotted path: value}`` for each declared read (not "frames"), for the key."""
    return {p: value_at(sections, p) for p in normalise(tuple(r for r in reads if r != FRAMES))}


# -- input files -----------------------------------------------------------------------------------
def input_files(value: Any, path: str) -> Iterator[tuple[str, str]]:
    """``(dotted path, file path as written)`` of every InputFile field inside ``value``."""
    value = _unwrap(value)
    if isinstance(value, BaseModel):
        for name, field in type(value).model_fields.items():
            inner = getattr(value, name)
            where = f"{path}.{name}" if path else name
            if INPUT_FILE in field.metadata:
                if isinstance(inner, str):
                    yield where, inner
            else:
                yield from input_files(inner, where)
    elif isinstance(value, (list, tuple)):
        for i, inner in enumerate(value):
            yield from input_files(inner, f"{path}.{i}")
    elif isinstance(value, dict):
        for k, inner in value.items():
            yield from input_files(inner, f"{path}.{k}")


def resolve(config_dir: Path, path: str) -> Path:
    """A path from the config, relative to the config file's folder (as Context.resolve)."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else (Path(config_dir) / p)
