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
import logging
import os
import shutil
import tempfile
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

    path = _usable_cache_dir(Path(file).resolve().parent, "plugins")
    before = numba.config.CACHE_DIR
    if path is not None:
        numba.config.CACHE_DIR = path
    try:
        yield path
    finally:
        numba.config.CACHE_DIR = before


def _writable(path: str) -> bool:
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
        return True
    except OSError:
        return False


def _usable_cache_dir(root: Path, sub: str = "") -> str | None:
    """The versioned cache folder for the sources under ``root`` in the first base that can be written: the
    user's NUMBA_CACHE_DIR or the home's cache, else one in the temporary folder (a farm's service user has no
    writable home). None if none can: numba then refuses to cache, which names the file, rather than write beside
    the sources (its own fallback: a NUMBA_CACHE_DIR it could not write sent 46 files into stages/*/__pycache__)."""
    base, user_base = _numba_base()
    fallback = os.path.join(tempfile.gettempdir(), f"fluid-pipeline-{getattr(os, 'getuid', lambda: 'user')()}", "numba")
    for b in (base, fallback):
        path = numba_cache_dir(root, os.path.join(b, sub) if sub else b)
        if _writable(path):
            if b != base:
                logging.getLogger(__name__).warning(
                    "%s %s cannot be written: numba's compiled kernels are cached in %s instead",
                    "NUMBA_CACHE_DIR" if user_base else "the numba cache folder", base, fallback)
            return path
    return None


def _use_versioned_numba_cache() -> None:
    import numba

    # only the folder set here, never the source tree's __pycache__ or numba's own user-wide folder
    numba.config.CACHE_LOCATOR_CLASSES = "UserProvidedCacheLocator"
    base, user_base = _numba_base()
    path = _usable_cache_dir(Path(__file__).resolve().parent)
    if path is None:
        return
    os.utime(path)
    numba.config.CACHE_DIR = path  # read when each cached function is decorated: before any stage module
    if user_base or not path.startswith(base):
        return  # the user's folder, or the fallback: not ours to tidy
    try:
        old = time.time() - KEEP_DAYS * 86400
        for entry in os.scandir(base):
            if entry.is_dir() and entry.path != path and len(entry.name) == 16 and entry.stat().st_mtime < old:
                shutil.rmtree(entry.path, ignore_errors=True)
    except OSError:
        pass


_use_versioned_numba_cache()
