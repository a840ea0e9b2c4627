"""The project's own stage implementations, one folder per stage kind, one module per implementation.
They are registered through the ``pipeline.stages`` entry-point group (pyproject.toml), like any
third-party stage; ``common/`` holds the numerics and artifact formats that several stages share.

Importing the package points numba's on-disk cache at a folder named by the source of every module
here (``numba_cache_dir``): numba checks only the source file of the function it caches, not of the
functions it calls or inlines from other modules, so after an update that changed only walls/maps.py,
sph_kernels' integrate kept running the old eq. 16 push-out from its cache (session 14)."""
from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import time
from pathlib import Path

KEEP_DAYS = 30  # other versions' folders unused this long are removed (only under the default base)


def numba_cache_dir(root: Path, base: str) -> str:
    """``base``/<sha256 of every .py file under ``root``, names and contents, first 16 hex digits>."""
    digest = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        digest.update(f.relative_to(root).as_posix().encode() + b"\0")
        digest.update(f.read_bytes())
    return os.path.join(base, digest.hexdigest()[:16])


def _numba_base() -> tuple[str, bool]:
    """The folder the versioned numba caches live in, and whether the user chose it (NUMBA_CACHE_DIR)."""
    user_base = os.environ.get("NUMBA_CACHE_DIR")
    return (user_base or os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
                                      "fluid-pipeline", "numba")), bool(user_base)


@contextlib.contextmanager
def numba_cache_for(file: str | os.PathLike):
    """For a studio's stage package whose numba kernels are cached (``cache=True``): the kernels decorated
    inside this block are cached in a folder named by the sources of the package holding ``file``, as this
    package's are, so an edit to a helper kernel in another of its modules is compiled anew (numba checks
    only the file of the function it caches). In the package's ``__init__.py``::

        with stages.numba_cache_for(__file__):
            from . import kernels
    """
    import numba

    base, _ = _numba_base()
    path = numba_cache_dir(Path(file).resolve().parent, os.path.join(base, "plugins"))
    before = numba.config.CACHE_DIR
    try:
        os.makedirs(path, exist_ok=True)
        numba.config.CACHE_DIR = path
    except OSError:
        pass  # a read-only home: numba keeps its own cache locations
    try:
        yield path
    finally:
        numba.config.CACHE_DIR = before


def _use_versioned_numba_cache() -> None:
    base, user_base = _numba_base()
    path = numba_cache_dir(Path(__file__).resolve().parent, base)
    try:
        os.makedirs(path, exist_ok=True)
        os.utime(path)
    except OSError:
        return  # a read-only home: numba keeps its own cache locations
    import numba

    numba.config.CACHE_DIR = path  # read when each cached function is decorated: before any stage module
    if user_base:
        return  # the user's folder: not ours to tidy
    try:
        old = time.time() - KEEP_DAYS * 86400
        for entry in os.scandir(base):
            if entry.is_dir() and entry.path != path and len(entry.name) == 16 and entry.stat().st_mtime < old:
                shutil.rmtree(entry.path, ignore_errors=True)
    except OSError:
        pass


_use_versioned_numba_cache()
