"""Load a YAML config into typed models; every error names the file, the line and the field.

The YAML is parsed safely (no tags that construct objects), the node tree gives each value's line,
``--set a.b=value`` overrides are applied to the parsed data (values typed by YAML's rules), and the
result is validated: the scene sections by pipeline.scene, each stage's parameters by the ``Params``
model of the implementation the config picks with ``use:`` (looked up only among registered entry
points, so no config value can import or run arbitrary code).
"""
from __future__ import annotations

import datetime
import difflib
import os
import re

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from .errors import ConfigError, RegistryError
from .reads import annotation_members, is_model
from .registry import Registry
from .scene import SceneConfig
from .stage import STAGE_KINDS, Params, Stage

CONFIG_VERSION = 1
TOP_LEVEL = ("config_version", "scene", "walls", "fluid", "effects", "camera", "stages", "outputs", "allow_large")
OUTPUT_NAMES = ("walls", "sdf", "particles", "raw_surface", "surface", "frames", "movie", "usd")


@dataclass
class StageChoice:
    kind: str
    cls: type[Stage]
    params: Params


@dataclass
class Config:
    path: Path
    scene: SceneConfig
    stages: dict[str, StageChoice]  # every kind the config names or that has a default
    outputs: tuple[str, ...]
    raw: dict[str, Any] = field(repr=False, default_factory=dict)
    allow_large: bool = False  # run even when the plan's memory estimate exceeds the available memory
    unloadable: dict[str, str] = field(default_factory=dict)  # kind -> why its default stage could not be loaded
    lines: Any = field(default=None, repr=False)  # _Lines: where each key is in the file (or which --set)
    overrides: tuple[str, ...] = ()  # the --set assignments applied over the file, in order

    @property
    def name(self) -> str:
        return self.scene.scene.name

    @property
    def dir(self) -> Path:
        return self.path.parent

    def where(self, *path: str | int) -> str:
        """'file:line' of the YAML node at ``path`` (or of the closest one above it, or the --set that made it)."""
        return self.lines.where(tuple(path)) if self.lines is not None else str(self.path)

    def sections(self) -> dict[str, Any]:
        return {"scene": self.scene.scene, "walls": self.scene.walls, "fluid": self.scene.fluid,
                "effects": self.scene.effects, "camera": self.scene.camera}


# -- YAML with line numbers ----------------------------------------------------------------------
class _Lines:
    """Maps a path of keys/indexes to the 1-based line of the YAML node there."""

    def __init__(self, file: str) -> None:
        self.file = file
        self.lines: dict[tuple, int] = {}
        self.overrides: dict[tuple, str] = {}

    def where(self, path: tuple) -> str:
        # an override of the path or of a section above it replaced the file's lines there
        # (--set 'effects.viscosity={mu: -1}' was reported at the file's line of the old mu)
        for n in range(len(path), -1, -1):
            if path[:n] in self.overrides:
                return f"{self.file}: {self.overrides[path[:n]]}"
        # an error of a whole section (a check across its fields) that an override changed is named with it:
        # --set render.color_range=[2,1] was blamed on the file's 'render:' line alone
        below = [v for k, v in self.overrides.items() if len(k) > len(path) and k[:len(path)] == path]
        with_set = f" (with {', '.join(below)})" if below else ""
        for n in range(len(path), -1, -1):
            if path[:n] in self.lines:
                return f"{self.file}:{self.lines[path[:n]]}{with_set}"
        return f"{self.file}: {', '.join(below)}" if below else self.file


# Limits that keep a hostile file cheap: YAML aliases can make a 1 KB file expand to billions of
# nodes ("billion laughs") and deep nesting overflows Python's recursion. A real config has a few
# hundred nodes and a depth under 10.
MAX_DEPTH = 64
MAX_NODES = 20_000


class _TooDeep(ConfigError):
    """Nesting beyond MAX_DEPTH (never read as a plain string in --set values)."""


class _Loader(yaml.SafeLoader):
    """SafeLoader that refuses nesting deeper than MAX_DEPTH already in the scanner (PyYAML's scanner
    is quadratic in the flow depth) and while composing (before any recursion can overflow); the
    expanded size is checked before the tree is walked."""

    def __init__(self, stream: str, file: str) -> None:
        super().__init__(stream)
        self._file = file
        self._depth = 0

    def _too_deep(self) -> None:
        raise _TooDeep(f"{self._file}:{self.line + 1}: nested more than {MAX_DEPTH} levels deep; "
                          f"a config is a few levels of mappings and lists")

    def fetch_flow_collection_start(self, token_class):  # noqa: ANN001 - PyYAML's signature
        if self.flow_level >= MAX_DEPTH:
            self._too_deep()
        super().fetch_flow_collection_start(token_class)

    def add_indent(self, column):  # noqa: ANN001
        if len(self.indents) >= MAX_DEPTH:
            self._too_deep()
        return super().add_indent(column)

    def flatten_mapping(self, node):  # noqa: ANN001 - PyYAML's signature
        own = sum(1 for k, _ in node.value if k.tag != "tag:yaml.org,2002:merge")
        super().flatten_mapping(node)
        node.merged_pairs = len(node.value) - own  # merged pairs come first; _walk checks duplicates among the rest

    def compose_node(self, parent, index):  # noqa: ANN001 - PyYAML's signature
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                self._too_deep()
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


# YAML 1.2's core schema for plain scalars instead of PyYAML's YAML 1.1: 010 was octal (8), 1:30 base 60 (90),
# 0x10 and 1_000 numbers, yes/no/on/off booleans (so spacing: yes was 1.0); 1e-2 was a string. Now only
# true/false are booleans, numbers are decimal (1e-2 included), and the rest stays text for the validation.
_Loader.yaml_implicit_resolvers = {k: [(tag, rx) for tag, rx in v if tag not in (
    "tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                              list("tTfF"))
_Loader.add_implicit_resolver("tag:yaml.org,2002:int", re.compile(r"^[-+]?[0-9]+$"), list("-+0123456789"))
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+.0123456789"))


def _yaml_int(loader, node):  # noqa: ANN001 - PyYAML's constructor signature: decimal only ("010" is 10)
    return int(loader.construct_scalar(node))


_Loader.add_constructor("tag:yaml.org,2002:int", _yaml_int)


def _expanded_size(node: yaml.Node, memo: dict[int, int]) -> int:
    """How many values the data has once aliases are expanded (each shared node counted once per use)."""
    n = memo.get(id(node))
    if n is None:
        children = node.value if isinstance(node, yaml.SequenceNode) else (
            [v for _, v in node.value] if isinstance(node, yaml.MappingNode) else [])
        n = memo[id(node)] = 1 + sum(_expanded_size(c, memo) for c in children)
    return n


def _walk(node: yaml.Node, path: tuple, lines: _Lines) -> None:
    lines.lines[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        seen: set = set()
        merged = getattr(node, "merged_pairs", 0)  # pairs a merge key (<<) brought in: a key after them overrides
        for n, (k, v) in enumerate(node.value):
            if n < merged:
                continue
            if not isinstance(k, yaml.ScalarNode):
                raise ConfigError(f"{lines.file}:{k.start_mark.line + 1}: {_dotted(path) or 'top level'}: keys must be plain names")
            if k.value in seen:
                raise ConfigError(f"{lines.file}:{k.start_mark.line + 1}: {_dotted(path + (k.value,))}: duplicate key")
            seen.add(k.value)
            _walk(v, path + (k.value,), lines)
            lines.lines[path + (k.value,)] = k.start_mark.line + 1  # the key's line reads best
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            _walk(v, path + (i,), lines)


def _dotted(path: tuple) -> str:
    return ".".join(str(p) for p in path)


def _unshared(value: Any) -> Any:
    """A copy in which no two places hold the same dict or list (YAML aliases, merge keys): copy.deepcopy
    keeps such sharing."""
    if isinstance(value, dict):
        return {k: _unshared(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_unshared(v) for v in value]
    return value


def safe_yaml(text: str, file: str) -> tuple[Any, yaml.Node | None]:
    """Parse YAML safely with the depth limit; returns the data (no two places share an object: an alias is a
    copy, so a --set through one does not change the other) and its node tree (None when empty)."""
    bad = re.search(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]", text)  # the YAML reader refuses these, with no line
    if bad:
        raise ConfigError(f"{file}:{text.count(chr(10), 0, bad.start()) + 1}: a control character "
                          f"(U+{ord(bad.group()):04X}) is not allowed in YAML (a binary file, or not saved as UTF-8?)")
    loader = _Loader(text, file)
    try:
        node = loader.get_single_node()
        if node is not None and _expanded_size(node, {}) > MAX_NODES:  # before anything is expanded
            raise ConfigError(f"{file}: the config expands to more than {MAX_NODES} values "
                              f"(YAML aliases repeated inside aliases?)")
        data = _unshared(loader.construct_document(node)) if node is not None else None
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line = f":{mark.line + 1}" if mark is not None else ""
        problem, hint = e.problem or e.context, ""
        if problem and "'\\t'" in problem and mark is not None:  # a tab is invisible in the line: say where it is and what it is
            hint = f" (a tab, at column {mark.column + 1}: YAML allows only spaces here)"
        raise ConfigError(f"{file}{line}: not valid YAML: {problem}{hint}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{file}: not valid YAML: {str(e).splitlines()[0]}") from None
    finally:
        loader.dispose()
    return data, node


def _parse_yaml(text: str, file: str) -> tuple[dict, _Lines]:
    lines = _Lines(file)
    data, node = safe_yaml(text, file)
    if node is None or data is None:
        raise ConfigError(f"{file}: the config is empty; expected a mapping with 'scene', 'fluid', 'outputs'...")
    if not isinstance(data, dict):
        raise ConfigError(f"{file}:1: top level: expected a mapping of sections, got {type(data).__name__}")
    _walk(node, (), lines)
    return data, lines


# -- overrides -------------------------------------------------------------------------------------
def apply_override(data: dict, assignment: str, lines: _Lines) -> None:
    """Apply ``a.b.c=value`` to ``data``; a first component naming a stage kind means stages.<kind>."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment}: expected path.to.field=value")
    key, _, text = assignment.partition("=")
    parts: list[Any] = [p for p in key.strip().split(".")]
    if not key.strip() or any(not p for p in parts):
        raise ConfigError(f"--set {assignment}: expected path.to.field=value")
    if parts[0] in STAGE_KINDS:
        parts = ["stages"] + parts
    if parts[0] not in TOP_LEVEL:
        raise ConfigError(f"--set {key}: unknown section {parts[0]!r}; expected one of {', '.join(TOP_LEVEL)} or a stage kind")
    try:
        value = safe_yaml(text, f"--set {key}")[0] if text.strip() else None
    except _TooDeep:
        raise
    except ConfigError:
        value = text
    if "#" in text and (value is None or isinstance(value, str) and value != text.strip()
                        and text.strip().startswith(value)):
        value = text.strip()  # "shot #3", "#ffffff": a shell argument, not YAML with a comment ("'#fff'" stays #fff)
    node: Any = data
    path: tuple = ()
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not (part.isascii() and part.isdigit()) or int(part) >= len(node):
                raise ConfigError(f"--set {key}: {_dotted(path)} is a list of {len(node)}; {part!r} is not an index in it")
            part = int(part)
            parts[i] = part  # the override's path as the validation reports it (walls.0, not walls.'0')
        elif not isinstance(node, dict):
            raise ConfigError(f"--set {key}: {_dotted(path)} is not a mapping")
        path = path + (part,)
        if last:
            node[part] = value
        else:
            if isinstance(node, dict) and node.get(part) is None:
                node[part] = {}
            node = node[part]
    lines.overrides[tuple(parts)] = f"--set {key}"


# -- validation ------------------------------------------------------------------------------------
def _model_fields(model: Any, loc: tuple) -> set[str]:
    """The keys a model accepts at ``loc`` (its fields' names, every member's in a union, through lists
    and dicts), for the "did you mean" of an unknown key; empty when unknown."""
    import typing

    level = annotation_members(model)
    for part in loc:
        nxt: list = []
        for t in level:
            origin = typing.get_origin(t)
            if isinstance(part, int) and origin in (list, tuple):
                nxt += [m for a in typing.get_args(t)[:1] for m in annotation_members(a)]
            elif isinstance(part, str) and origin is dict:
                nxt += annotation_members(typing.get_args(t)[1])
            elif isinstance(part, str) and is_model(t) and part in t.model_fields:
                nxt += annotation_members(t.model_fields[part].annotation)
        level = nxt
    return {name for t in level if is_model(t) for name, f in t.model_fields.items() for name in (name, f.alias) if name}


def _first_error(err: ValidationError, prefix: tuple, lines: _Lines, model: Any = None) -> ConfigError:
    errors = err.errors(include_url=False)
    # a misspelt key is both an unknown key and, often, a missing field: name the key the user wrote, with
    # the field it was probably meant to be ("fluid.spacng: unknown key (did you mean spacing?)"), from the
    # model's own fields (a --set typo or an optional field misspelt leaves nothing missing)
    e = next((x for x in errors if x["type"] == "extra_forbidden"), errors[0])
    loc = prefix + tuple(e["loc"])
    # pydantic puts the union tag into loc (walls.0.builtin.size): drop tags that are not keys (only in the
    # lists of unions: a sink's 'box' is a key)
    clean: list = []
    for i, p in enumerate(loc):
        if (isinstance(p, str) and i > 1 and isinstance(loc[i - 1], int) and loc[i - 2] in ("walls", "emitters")
                and p in {"builtin", "file", "usd", "box", "sphere", "mesh"}):
            continue
        if isinstance(p, str) and (p in {"float", "int", "str", "bool"} or p.startswith("tuple[")):
            continue  # pydantic's union member tags (scale: float | Vec3)
        clean.append(p)
    loc = tuple(clean)
    hint = ""
    if e["type"] == "extra_forbidden" and isinstance(loc[-1], str):
        missing = [str(x["loc"][-1]) for x in errors if x["type"] == "missing" and x["loc"][:-1] == e["loc"][:-1]]
        # the model's keys where the unknown one is (the union tags dropped: every member's keys)
        known = sorted(_model_fields(model, loc[len(prefix):-1])) if model is not None else []
        kinds = {"walls": ("builtin", "file", "usd"), "emitters": ("box", "sphere", "mesh", "usd")}
        owner = loc[-3] if len(loc) >= 3 and isinstance(loc[-2], int) else None
        if owner in kinds and loc[-1] in kinds[owner]:  # a second kind key in one entry: "did you mean file?"
            hint = f" (a {owner[:-1]} has one of {', '.join(kinds[owner])})"
        else:
            known = [k for k in known if k != loc[-1]]
            close = difflib.get_close_matches(loc[-1], missing, n=1) or difflib.get_close_matches(loc[-1], known, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
    msg = e["msg"]
    if e["type"] == "extra_forbidden":
        msg = "unknown key"
    elif e["type"] == "missing":
        msg = "required field is missing"
    got = e.get("input")
    suffix = ""
    if e["type"] not in ("extra_forbidden", "missing") and not isinstance(got, (dict, list)) and got is not None:
        suffix = f" (got {got.isoformat() if isinstance(got, datetime.date) else repr(got)})"
        if e["type"] == "string_type" and isinstance(got, (bool, int, float, datetime.date)):
            kind = ("a boolean" if isinstance(got, bool) else "a date" if isinstance(got, datetime.date)
                    else "a number")
            hint = f" (YAML reads it as {kind}: put it in quotes to mean the text)"
    return ConfigError(f"{lines.where(loc)}: {_dotted(loc) or 'top level'}: {msg}{suffix}{hint}")


def _stage_params(kind: str, raw: Any, registry: Registry, lines: _Lines) -> StageChoice:
    path = ("stages", kind)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{lines.where(path)}: {_dotted(path)}: expected a mapping like {{use: NAME, ...}}")
    raw = dict(raw)
    use = raw.pop("use", None)
    try:
        if use is None:
            cls = registry.default(kind)
        else:
            if not isinstance(use, str):
                raise ConfigError(f"{lines.where(path + ('use',))}: {_dotted(path + ('use',))}: expected an implementation name")
            cls = registry.get(kind, use)
    except RegistryError as e:
        raise ConfigError(f"{lines.where(path + ('use',))}: {_dotted(path + ('use',))}: {e}") from None
    try:
        params = cls.Params.model_validate(raw)
    except ValidationError as e:
        err = _first_error(e, path, lines, cls.Params)
        first = next((x for x in e.errors() if x["type"] == "extra_forbidden"), e.errors()[0])  # as _first_error
        owners = [name for name in registry.implementations(kind) if name != cls.name
                  and first["type"] == "extra_forbidden" and len(first["loc"]) == 1
                  and _owns(registry, kind, name, first["loc"][0])]
        if owners:  # `--set simulate.use=mps` on a config holding sph's parameters: say whose they are
            head = str(err).split(" (did you mean")[0]
            raise ConfigError(f"{head} for {kind}: {{use: {cls.name}}} (a parameter of {' and '.join(owners)}; to "
                              f"switch, replace the whole section: --set \"{kind}={{use: {cls.name}}}\")") from None
        raise err from None
    return StageChoice(kind=kind, cls=cls, params=params)


def _owns(registry: Registry, kind: str, name: str, key: str) -> bool:
    try:
        return key in registry.get(kind, name).Params.model_fields
    except RegistryError:  # an implementation that does not load is not a candidate
        return False


def load_config(path: str | Path, registry: Registry, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    path = Path(path)
    file = str(path)
    if path.is_dir():
        raise ConfigError(f"{file}: a folder, not a config file (give the .yaml inside it)")
    if not path.is_file():
        raise ConfigError(f"{file}: config file not found")
    try:
        raw = path.read_bytes()
        text = raw.decode("utf-8-sig" if raw.startswith(b"\xef\xbb\xbf") else "utf-8")
    except OSError as e:
        raise ConfigError(f"{file}: cannot read the config: {e}") from None
    except UnicodeDecodeError as e:
        utf16 = raw[:2] in (b"\xff\xfe", b"\xfe\xff")
        line = raw.count(b"\n", 0, e.start) + 1
        raise ConfigError(f"{file}:{line}: not UTF-8 text (byte {e.start}); save the config "
                          f"as UTF-8" + (" (this is UTF-16, what Windows PowerShell 5's > writes)" if utf16 else "")) from None
    data, lines = _parse_yaml(text, file)
    for assignment in overrides:
        apply_override(data, assignment, lines)
    effects = data.get("effects")
    if isinstance(effects, dict):  # "gravity:" with nothing after it is the effect with its defaults, as {} is:
        for k, v in effects.items():  # null turned gravity off without a word (the fluid hung in the air)
            if v is None:
                effects[k] = {}

    if "study_version" in data and "config_version" not in data:
        raise ConfigError(f"{file}: a study (study_version), not a scene config: run it with `pipeline study {file}`")
    unknown = [k for k in data if k not in TOP_LEVEL]
    if unknown:
        k = unknown[0]
        close = difflib.get_close_matches(str(k).lower(), TOP_LEVEL, n=1)
        raise ConfigError(f"{lines.where((k,))}: {k}: unknown section"
                          + (f" (did you mean {close[0]}?)" if close else f"; expected one of {', '.join(TOP_LEVEL)}"))
    version = data.get("config_version")
    if version != CONFIG_VERSION:
        raise ConfigError(f"{lines.where(('config_version',))}: config_version: expected {CONFIG_VERSION}, got {version!r}")
    try:
        scene = SceneConfig.model_validate({k: data[k] for k in ("scene", "walls", "fluid", "effects", "camera") if k in data})
    except ValidationError as e:
        raise _first_error(e, (), lines, SceneConfig) from None

    outputs = data.get("outputs", ["usd", "frames", "movie"])
    if not isinstance(outputs, list) or not outputs or not all(isinstance(o, str) for o in outputs):
        raise ConfigError(f"{lines.where(('outputs',))}: outputs: expected a list of names from {', '.join(OUTPUT_NAMES)}")
    for i, o in enumerate(outputs):
        if o not in OUTPUT_NAMES:
            raise ConfigError(f"{lines.where(('outputs', i))}: outputs.{i}: unknown output {o!r}; expected one of {', '.join(OUTPUT_NAMES)}")

    allow_large = data.get("allow_large", False)
    if not isinstance(allow_large, bool):
        raise ConfigError(f"{lines.where(('allow_large',))}: allow_large: expected true or false, got {allow_large!r}")
    stages_raw = data.get("stages") or {}
    if not isinstance(stages_raw, dict):
        raise ConfigError(f"{lines.where(('stages',))}: stages: expected a mapping of stage kind to settings")
    for kind in stages_raw:
        if kind not in STAGE_KINDS:
            raise ConfigError(f"{lines.where(('stages', kind))}: stages.{kind}: unknown stage kind; expected one of {', '.join(STAGE_KINDS)}")
    stages: dict[str, StageChoice] = {}
    unloadable: dict[str, str] = {}
    for kind in STAGE_KINDS:
        if kind in stages_raw:
            stages[kind] = _stage_params(kind, stages_raw[kind], registry, lines)
        elif registry.implementations(kind):
            try:
                stages[kind] = _stage_params(kind, {}, registry, lines)
            except ConfigError as e:
                unloadable[kind] = str(e)  # only matters if the graph needs it: then it is the error to show
    # absolute, not resolved: a config linked into a shot's folder reads the files beside the link and keeps
    # its cache and outputs there (resolved, every shot linking one template shared the template's folder)
    return Config(path=Path(os.path.abspath(path)), scene=scene, stages=stages, outputs=tuple(dict.fromkeys(outputs)), raw=data,
                  allow_large=allow_large, unloadable=unloadable, lines=lines, overrides=tuple(overrides))


def dump_model(value: Any) -> Any:
    """JSON-ready canonical form of validated models (defaults included), for keys and manifests."""
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, (list, tuple)):
        return [dump_model(v) for v in value]
    if isinstance(value, dict):
        return {k: dump_model(v) for k, v in value.items()}
    return value
