"""Cache keys: what a stage's result depends on, hashed.

A stage's key is the sha256 of
- its implementation, hand ``version`` (for format changes) and ``code``: the sha256 of the source of
  its module and of every project module it imports, transitively (as joblib.Memory does for a
  function), so an edit to a kernel invalidates the entries it made without anyone bumping a version;
- its validated params (defaults included);
- the config values it declares in ``reads`` (dotted paths: a stage is keyed on the fields it uses,
  not on whole sections) and, if it declares "frames", the run's frame selection;
- its upstream keys; a per-frame artifact consumed by a whole-run stage counts with the frame
  selection (the whole-run result covers only those frames);
- the content of every file it reads: each ``InputFile`` field in its reads and params, found by the
  engine, plus what its ``external_files()`` hook adds.
A per-frame stage keys each frame by its stage key and the frame index.

A stage that ``extends`` a read (simulate: "scene.frames.count") also gets a resume key, its key with
that read left out: a run with a larger value continues from the cached entry of a smaller one.
"""
from __future__ import annotations

import errno
import hashlib
import importlib.util
import json
import os
import re
import stat
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .cache import Cache, file_sha256, hash_key
from .config import Config, dump_model
from .errors import ConfigError, InputChanged, PipelineError, StageFailed
from .graph import Graph, Node
from .reads import FRAMES, input_files, read_values, resolve
from .stage import Context, Stage, StageError


@dataclass
class Plan:
    config: Config
    graph: Graph
    cache: Cache
    keys: dict[str, str]
    components: dict[str, dict[str, Any]]
    frames: tuple[int, ...]
    resume: dict[str, tuple[str, int]]  # kind -> (resume key, value of the extended read)


def frame_key(stage_key: str, frame: int) -> str:
    return hash_key({"stage_key": stage_key, "frame": frame})


def selection_key(stage_key: str, frames: tuple[int, ...]) -> str:
    """The identity of a per-frame artifact restricted to a frame selection."""
    return hash_key({"stage_key": stage_key, "frames": list(frames)})


def context(config: Config, node: Node, out_dir: Path, frames: tuple[int, ...], **kw: Any) -> Context:
    return Context.for_stage(node.cls, config.sections(), out_dir=out_dir, config_dir=config.dir, frames=frames, **kw)


def call_hook(node: Node, hook: str, *args: Any) -> Any:
    """A stage's plan-time hook (check, estimate, external_files). StageError passes (the scene's fault);
    anything else is a bug in the stage, shown as one line naming the stage, the hook and where it raised."""
    try:
        return getattr(node.cls(), hook)(*args)
    except (StageError, PipelineError, KeyboardInterrupt):
        raise
    except BaseException as e:  # noqa: BLE001 - a plugin's own bug, sys.exit() included
        tb = traceback.extract_tb(e.__traceback__)
        where = f" (at {tb[-1].filename}:{tb[-1].lineno})" if tb else ""
        what = f"called sys.exit({e.code!r})" if isinstance(e, SystemExit) else f"failed: {type(e).__name__}: {e}"
        raise StageFailed(f"stage {node.label}: its {hook}() {what}{where}", user_error=False) from e


def plan(config: Config, graph: Graph, cache: Cache, frames: tuple[int, ...] | None = None) -> Plan:
    count = config.scene.scene.frames.count
    if frames is None:
        frames = tuple(range(count))
    frames = tuple(sorted(set(frames)))  # one selection, one key, whatever order or repeats a caller gave
    bad = [f for f in frames if not 0 <= f < count]
    if bad:
        raise ConfigError(f"--frames: frame {bad[0]} is outside the scene's frames 0..{count - 1}")
    sections = config.sections()
    keys: dict[str, str] = {}
    components: dict[str, dict[str, Any]] = {}
    resume: dict[str, tuple[str, int]] = {}
    for kind in graph.order():
        node = graph.nodes[kind]
        values = read_values(sections, node.cls.reads)
        comp: dict[str, Any] = {
            "stage": node.label,
            "version": node.cls.version,
            "code": code_hashes(node.cls),
            "params": dump_model(node.params),
            "scene": dump_model(values),
            "inputs": {name: (selection_key(keys[producer], frames)
                              if graph.nodes[producer].per_frame and not node.per_frame else keys[producer])
                       for name, producer in node.inputs},
            "files": _files(config, node, values, frames),
        }
        if FRAMES in node.cls.reads:
            comp["frames"] = list(frames)
        components[kind] = comp
        keys[kind] = hash_key(comp)
        ext = node.cls.extends
        if ext is not None and isinstance(comp["scene"].get(ext), int):
            rest = {**comp, "scene": {k: v for k, v in comp["scene"].items() if k != ext}}
            resume[kind] = (hash_key({"resume": ext, **rest}), comp["scene"][ext])
    return Plan(config=config, graph=graph, cache=cache, keys=keys, components=components, frames=frames,
                resume=resume)


def _files(config: Config, node: Node, values: dict[str, Any], frames: tuple[int, ...]) -> dict[str, str]:
    """``{path: sha256}`` of every file the stage reads."""
    # (dotted field, its path in the config for Config.where, file)
    found: list[tuple[str, tuple, Path]] = []
    for read, value in values.items():
        found += [(where, _field_path(where), resolve(config.dir, p)) for where, p in input_files(value, read)]
    found += [(f"stages.{node.kind}.{where}", ("stages", node.kind) + _field_path(where), resolve(config.dir, p))
              for where, p in input_files(node.params, "")]
    try:
        extra = call_hook(node, "external_files", context(config, node, config.dir, frames), node.params)
    except StageError as e:
        raise StageFailed(f"stage {node.label}: {e}", user_error=True) from None
    found += [("external file", ("stages", node.kind), Path(f)) for f in extra]
    files: dict[str, str] = {}
    for where, field, path in found:
        here = f"{config.where(*field)}: stage {node.label}: {where}"
        try:
            # stat first: a symlink loop, a name too long or a NUL byte is the config's mistake (resolve() raised
            # RuntimeError, stat OSError/ValueError: exit 1 with no config line)
            if not stat.S_ISREG(os.stat(path).st_mode):
                raise FileNotFoundError(errno.ENOENT, "not a file", str(path))
            name = _file_name(path, config.dir)
            if name not in files:
                files[name] = _file_hash(path)
        except (FileNotFoundError, NotADirectoryError):
            raise StageFailed(f"{here}: input file not found: {path}", user_error=True) from None
        except OSError as exc:  # ELOOP, ENAMETOOLONG, EACCES, EIO
            raise StageFailed(f"{here}: cannot read input file {path}: {exc.strerror or exc}", user_error=True) from None
        except (ValueError, RuntimeError) as exc:  # an embedded NUL (a plugin's external_files), a loop in resolve()
            raise StageFailed(f"{here}: cannot read input file {path!r}: {exc}", user_error=True) from None
    return files


def _field_path(dotted: str) -> tuple:
    """``"walls.1.file"`` -> ``("walls", 1, "file")``, the path Config.where takes."""
    return tuple(int(p) if p.isdigit() else p for p in dotted.split(".") if p)


def _file_name(path: Path, config_dir: Path) -> str:
    """A file's name in a key: its path relative to the config's folder, so a project moved or cloned
    elsewhere (with its assets where they were beside it) keeps its keys and its cache; absolute only
    where no relative path exists (another drive)."""
    try:
        return Path(os.path.relpath(Path(path).resolve(), Path(config_dir).resolve())).as_posix()
    except ValueError:
        return str(Path(path).resolve())


# (resolved path, device, inode, size, mtime_ns, ctime_ns) -> sha256. Size and mtime alone let a file replaced by
# one of the same size and mtime (cp -p, shutil.copy2, rsync -a) keep its old hash in a long-lived process (a
# notebook calling pipeline.run twice was served the stale result); a write or utime always moves ctime, a
# replacement by rename the inode.
_FILE_HASHES: dict[tuple, str] = {}
# a file changed within this many ns of being hashed is not memoised: a second write within the filesystem's
# clock tick (a few ms) would leave ctime as it was ("racy git")
_RACY_NS = 2_000_000_000


def check_inputs_unchanged(config_dir: str | Path, files: dict[str, str]) -> None:
    """Raise InputChanged if a file of ``files`` (a key's {name: sha256}) no longer has the content the key
    was made from: a stage reads its inputs after the plan hashed them (a camera after the whole
    simulation), and an edit in between made an entry under the old key from the new content."""
    changed = [name for name, sha in files.items()
               if not (path := Path(config_dir, name)).is_file() or _file_hash(path) != sha]
    if changed:
        raise InputChanged(f"{', '.join(changed)} changed while the run used it; nothing made from it "
                           "was kept: run again")


def _file_sig(path: Path | str) -> tuple:
    st = os.stat(path)
    return (str(Path(path).resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _file_hash(path: Path) -> str:
    sig = _file_sig(path)
    sha = _FILE_HASHES.get(sig)
    if sha is None:
        sha = file_sha256(path)
        if time.time_ns() - sig[-1] > _RACY_NS:
            _FILE_HASHES[sig] = sha
    return sha


# -- code hashes -----------------------------------------------------------------------------------
_SOURCES: dict[str, tuple[tuple[int, ...], str, tuple[str, ...]]] = {}  # file -> (stat, sha, imports)
# import statements, also inside functions; a regex rather than ast: parsing every module on each run
# costs seconds, and a false match in a docstring only adds a module to the hash
_FROM_IMPORT = re.compile(r"^[ \t]*from[ \t]+(\.*)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]*)", re.M)
_IMPORT = re.compile(r"^[ \t]*import[ \t]+([\w., \t]+)", re.M)
_IMPORT_MODULE = re.compile(r"import_module\(\s*[\"']([\w.]+)[\"']")


def code_hashes(cls: type[Stage]) -> dict[str, str]:
    """``{module: sha256 of its source}`` for the stage's module and every module of source code it imports,
    transitively: the project's (``pipeline``, ``stages``), the stage's own top-level package, and any other
    module outside the standard library and site-packages (a studio library on PYTHONPATH, an editable
    install, a sibling module); imports inside functions and ``import_module("...")`` literals count too,
    the packages' ``__init__`` only when imported by name (pipeline's would pull in the whole engine).
    A package installed in site-packages counts by its version (``{top: "version X"}``), not its sources: an
    upgrade of numba or trimesh re-keys what was made with it. A stage whose module has no source file
    (a class defined in a notebook cell or ``python -c``) cannot be hashed: it gets a key no later run
    shares, so it is recomputed on every run (and said once). Parsed sources are reused while a file's inode,
    size, mtime and ctime are unchanged."""
    roots = {"pipeline", "stages", cls.__module__.split(".")[0]}
    out: dict[str, str] = {}
    todo = [cls.__module__]
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        top = name.split(".")[0]
        if name in seen or top in seen or (top not in roots and top in _STDLIB):
            continue
        seen.add(name)
        file = _module_file(name)
        if file is None:
            if name == cls.__module__:
                out[name] = _unhashable(cls)
            continue
        if top not in roots and _installed(file):
            seen.add(top)
            out[top] = _installed_version(top, file)
            continue
        sha, imports = _source(file, name)
        out[name] = sha
        todo += imports
    return dict(sorted(out.items()))


def changed_since_loaded(code: dict[str, str]) -> list[str]:
    """Modules of a stage's code hashes (the plan's ``components[kind]["code"]``) that this process has loaded
    and whose file changed on disk since this process first hashed it: a run would key the new source but
    execute the old (a notebook, a DCC session, a script calling ``pipeline.run`` again after an edit)."""
    changed = []
    for name, sha in code.items():
        file = getattr(sys.modules.get(name), "__file__", None)
        if file and _FIRST_SEEN.get(file, sha) != sha:
            changed.append(name)
    return changed


_FIRST_SEEN: dict[str, str] = {}  # file -> its sha when this process first hashed it (close to when it was imported)
_STDLIB = frozenset(sys.stdlib_module_names) | frozenset(sys.builtin_module_names) | {"__future__"}
_VERSIONS: dict[str, str] = {}
_WARNED_UNHASHABLE: set[type] = set()


def _installed(file: str) -> bool:
    """A module installed into an environment (site-packages), not source being worked on."""
    parts = Path(file).parts
    return "site-packages" in parts or "dist-packages" in parts


def _installed_version(top: str, file: str) -> str:
    """An installed package's version, the same on every host sharing a cache (its files' mtimes are not)."""
    if top not in _VERSIONS:
        from importlib import metadata

        try:
            version = metadata.version(top)
        except metadata.PackageNotFoundError:
            names = metadata.packages_distributions().get(top) or []
            version = metadata.version(names[0]) if names else None
        # a module no distribution records: its own source stands in for a version
        _VERSIONS[top] = f"version {version}" if version else "source " + _source(file, top)[0]
    return _VERSIONS[top]


def _unhashable(cls: type) -> str:
    if cls not in _WARNED_UNHASHABLE:
        _WARNED_UNHASHABLE.add(cls)
        import logging

        logging.getLogger("pipeline").warning(
            "stage %s is defined in %s, which has no source file: its code cannot be hashed, so it is recomputed "
            "on every run (define it in a module file to cache it)", cls.qualname(), cls.__module__)
    return "unhashable " + os.urandom(8).hex()


def _module_file(name: str) -> str | None:
    """The source file of module ``name``, found without importing anything (an import may compile
    numba kernels; a top-level package not imported yet is looked up on sys.path, so the answer does not
    depend on what this process happened to import already); None when there is no such source file."""
    mod = sys.modules.get(name)
    if mod is not None:
        file = getattr(mod, "__file__", None)
    else:
        top, *rest = name.split(".")
        pkg = sys.modules.get(top)
        if pkg is not None:
            pkg_dirs, origin = getattr(pkg, "__path__", None), getattr(pkg, "__file__", None)
        else:
            try:
                spec = importlib.util.find_spec(top)
            except (ImportError, ValueError):
                spec = None
            if spec is None:
                return None
            pkg_dirs, origin = spec.submodule_search_locations, spec.origin
        if not rest:
            file = origin
        elif not pkg_dirs:
            return None
        else:
            file = None
            for d in pkg_dirs:
                base = Path(d).joinpath(*rest)
                for cand in (base.with_suffix(".py"), base / "__init__.py"):
                    if cand.is_file():
                        file = str(cand)
                        break
                if file:
                    break
    return file if file and file.endswith(".py") else None


def _source(file: str, name: str) -> tuple[str, tuple[str, ...]]:
    st = os.stat(file)
    sig = (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)  # as _file_sig: a same-size, same-mtime copy is new
    hit = _SOURCES.get(file)
    if hit is not None and hit[0] == sig:
        return hit[1], hit[2]
    data = Path(file).read_bytes()
    sha = hashlib.sha256(data).hexdigest()[:16]
    _FIRST_SEEN.setdefault(file, sha)
    package = name if file.endswith("__init__.py") else name.rpartition(".")[0]
    imports: list[str] = []
    text = data.decode("utf-8", "replace")
    for m in _FROM_IMPORT.finditer(text):
        dots, module, names = m.group(1), m.group(2), m.group(3).strip("()")
        if dots:
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - len(dots) + 1] + ([module] if module else []))
        else:
            base = module
        imports.append(base)
        imports += [f"{base}.{n.split()[0]}" for n in names.replace("\\", " ").split(",") if n.split()]  # submodules
    for m in _IMPORT.finditer(text):
        imports += [n.split()[0] for n in m.group(1).split(",") if n.split()]
    imports += _IMPORT_MODULE.findall(text)
    _SOURCES[file] = (sig, sha, tuple(dict.fromkeys(i for i in imports if i)))
    return sha, _SOURCES[file][2]


# -- resume index ----------------------------------------------------------------------------------
def _resume_index(cache: Cache, kind: str, resume_key: str) -> Path:
    return cache.root / "resume" / kind / f"{resume_key}.json"


def resume_source(cache: Cache, kind: str, resume: tuple[str, int]) -> Path | None:
    """The cached entry of the same stage with the largest smaller value of the extended read."""
    resume_key, value = resume
    try:
        index = json.loads(_resume_index(cache, kind, resume_key).read_text())
    except (OSError, ValueError):
        return None
    for old in sorted((int(v) for v in index if int(v) < value), reverse=True):
        hit = cache.lookup(kind, index[str(old)])
        if hit is not None:
            return hit.path
    return None


def record_resume(cache: Cache, kind: str, resume: tuple[str, int], key: str) -> None:
    path = _resume_index(cache, kind, resume[0])
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError):
        index = {}
    index[str(resume[1])] = key
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(index, sort_keys=True))
    os.replace(tmp, path)
