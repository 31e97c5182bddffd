"""numba's on-disk kernel caches kept in step with the package's sources.

numba checks a cached kernel against its own source file only: a kernel that calls one from
another file keeps the old callee's machine code after that file changes (numba documents
this), so after a ``git pull`` or an edit in an editable install the matcher would run old
code. :func:`refresh_installed`, run by :func:`graph.jit.njit` before the first kernel of a process
is defined (so before any cached kernel loads), compares the sources with those of
the last run (a stamp file); when any changed, it deletes the cached kernels of every file
that has kernels, wherever numba keeps them, so all of them compile anew on first use. An
unchanged tree costs a ``stat`` per file.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

STAMP_NAME = "mapmatch-kernel-sources.stamp"
KERNEL_PACKAGES = ("graph", "mapmatch")
"""The top-level packages whose modules define kernels (siblings in one install)."""


def source_files(dirs: Iterable[Path]) -> list[Path]:
    """The ``.py`` files under ``dirs``, sorted."""
    return sorted(p for d in dirs for p in Path(d).rglob("*.py") if "__pycache__" not in p.parts)


def fingerprint(files: Iterable[Path]) -> str:
    """A digest of the files' paths, sizes and modification times (a ``stat`` each)."""
    h = hashlib.sha256()
    for f in files:
        st = f.stat()
        h.update(f"{f}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def content_digest(files: Iterable[Path]) -> str:
    """A digest of the files' paths and contents."""
    h = hashlib.sha256()
    for f in files:
        h.update(f"{f}\0".encode())
        h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()


def _locators(source: Path) -> list[Any]:
    """numba's cache locators that could hold the kernels of ``source`` (``NUMBA_CACHE_DIR``,
    ``__pycache__`` beside the file, the user's cache folder)."""
    from numba.core import caching, config

    def probe() -> None:
        """Stands for a kernel of ``source`` (a locator reads the line of its code)."""

    names = ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator")
    found: list[Any] = []
    for name in names:
        cls = getattr(caching, name, None) or getattr(caching, f"_{name}", None)
        if cls is None or (name.startswith("UserProvided") and not getattr(config, "CACHE_DIR", "")):
            continue
        try:
            locator = cls(probe, str(source))
            locator.get_cache_path()
        except Exception:  # a locator this numba lacks or cannot place
            continue
        found.append(locator)
    return found


def cache_files(source: Path) -> list[Path]:
    """numba's cache files (index and data) of the kernels in ``source``, wherever its cache
    locators would put them (``NUMBA_CACHE_DIR``, ``__pycache__`` beside the file, the user's
    cache folder)."""
    found: list[Path] = []
    for locator in _locators(source):
        folder = Path(locator.get_cache_path())
        found += [p for ext in ("nbi", "nbc") for p in folder.glob(f"{source.stem}.*.{ext}")]
    return found


def has_cached(source: Path, kernel: str) -> bool:
    """Whether numba's cache holds kernel ``kernel`` (a top-level function of ``source``)
    compiled from the file's current contents, by this numba and Python, where numba would look
    first (``NUMBA_CACHE_DIR``, else ``__pycache__`` beside the file when writable, else the
    user's cache folder): read from its cache index, without importing the module (so before
    deciding how kernels run)."""
    from numba.core import caching

    def probe() -> None:
        """Stands for a kernel of ``source``."""

    pyver = f"py{sys.version_info[0]}{sys.version_info[1]}"
    try:
        locators: list[Any] = list(caching.CacheImpl._locator_classes)
    except AttributeError:  # unknown numba internals: not cached
        return False
    for cls in locators:
        try:
            locator = cls.from_function(probe, str(source))
        except Exception:
            continue
        if locator is None:
            continue
        folder = Path(locator.get_cache_path())
        for index in folder.glob(f"{source.stem}.{kernel}-*.{pyver}*.nbi"):
            try:
                cache = caching.IndexDataCacheFile(str(folder), index.name[:-4], locator.get_source_stamp())
                if cache._load_index():  # empty: written for another source or numba version
                    return True
            except Exception:  # unknown numba internals or an unreadable index: not cached
                continue
        return False  # numba uses the first locator that applies
    return False


def refresh(dirs: Iterable[Path], stamp: Path) -> bool:
    """Delete the cached kernels of the files under ``dirs`` if any source's content changed
    since the last run recorded in ``stamp``. Returns whether it did.

    The stamp holds the sources' content digest and their :func:`fingerprint`: an unchanged
    fingerprint costs no reading; a changed one with the same contents (a checkout, a touch)
    only updates the stamp. Without a stamp (a first run, a new cache folder) nothing is
    deleted. Nothing is deleted either when ``stamp`` cannot be written (a read-only install),
    as then every run would compile every kernel anew.
    """
    tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}.tmp")
    try:
        files = source_files(dirs)
        old = stamp.read_text().split() if stamp.is_file() else []
        if old[1:2] == [fingerprint(files)]:
            return False
        digest = content_digest(files)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text("")  # the stamp's folder is writable
        changed = bool(old) and old[0] != digest
        if changed:
            for f in files:
                if b"njit" in f.read_bytes():
                    for cached in cache_files(f):
                        cached.unlink(missing_ok=True)
        tmp.write_text(f"{digest} {fingerprint(files)}\n")
        os.replace(tmp, stamp)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        return False
    return changed


def refresh_installed() -> bool:
    """:func:`refresh` for the packages that hold kernels: ``graph`` and its sibling ``mapmatch``
    (found beside this package, installed or in a source tree, without importing it); the stamp
    goes where numba caches (``NUMBA_CACHE_DIR``, else ``graph/__pycache__``)."""
    here = Path(__file__).resolve().parent
    dirs = [d for d in (here.parent / name for name in KERNEL_PACKAGES) if d.is_dir()]
    cache = os.environ.get("NUMBA_CACHE_DIR")
    stamp = Path(cache) / STAMP_NAME if cache else here / "__pycache__" / STAMP_NAME
    return refresh(dirs, stamp)
