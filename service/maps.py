"""The registry of loaded maps: several cities per server, loaded and replaced at run time.

Each entry holds the read-only :class:`RoadGraph`, its :class:`EdgeIndex` and the shared,
thread-safe online and batch matchers built on it. Requests name a map by id; an empty id
means the only loaded map.

A map is loaded and warmed up (:func:`warm_up`) before it is registered, so a replacement
that fails leaves the map it would replace serving. A map file is opened once
(:class:`MapSource`) and memory-mapped from that descriptor, which the entry keeps: batch
worker processes get the same descriptor, so a file replaced under the same name changes
nothing served. Files named by clients (:func:`resolve_map_path`) must be regular files
inside the configured map folder, reached without a symlink; a map from an OSM/GIS source
is built in a child process with time and memory limits that dies with the server
(:func:`load_map_file`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import resource
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from graph.artifact import MAGIC, load_map_fd, save_map
from graph.errors import GraphError
from graph.files import ReadOnlyFile
from graph.index import EdgeIndex
from graph.projection import point_to_lonlat
from graph.road_graph import ARRAY_FIELDS, RoadGraph
from mapmatch.config import BATCH_CONFIG, DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ValidationError
from mapmatch.types import Fix, State, Track
from service.children import die_with_parent
from service.errors import LimitError, MapLoadError, MapNotFoundError, MapPathError

__all__ = [
    "LoadLimits",
    "MapEntry",
    "MapNotFoundError",
    "MapRegistry",
    "MapSource",
    "graph_checksum",
    "is_map_file",
    "load_map_file",
    "make_entry",
    "open_map_path",
    "resolve_map_path",
    "stop_builds",
    "warm_up",
]


def graph_checksum(graph: RoadGraph) -> str:
    """A short content hash of the graph's arrays and CRS: equal maps, equal checksums."""
    h = hashlib.blake2b(digest_size=16)
    h.update(graph.crs.encode())
    for name in ARRAY_FIELDS:
        a = getattr(graph, name)
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


@dataclass(eq=False)
class MapEntry:
    """One loaded map and the matchers serving it."""

    map_id: str
    graph: RoadGraph
    source: str
    checksum: str
    index: EdgeIndex
    online: Any
    config: MatchConfig = DEFAULT_CONFIG
    batch_config: MatchConfig = BATCH_CONFIG
    path: Path | None = None  # the map file it was loaded from, for display (never opened again)
    file: ReadOnlyFile | None = None  # its open descriptor: batch worker processes map the same file
    _batch: Any = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def batch(self) -> Any:
        """The map's batch matcher (thread-safe, with ``batch_config``), built on first use."""
        with self._lock:
            if self._batch is None:
                from mapmatch.batch import BatchMatcher

                self._batch = BatchMatcher(self.graph, index=self.index, config=self.batch_config)
            return self._batch

    @property
    def version(self) -> str:
        art = self.graph.meta.get("artifact")
        if not art:
            return ""
        from graph.artifact import FORMAT, FORMAT_VERSION

        return f"{FORMAT}/{FORMAT_VERSION}"

    @property
    def build_parameters(self) -> dict[str, Any]:
        """The map's build metadata, with file paths cut to their file names."""
        meta = self.graph.meta
        return {k: _no_paths(v) for k, v in meta.items() if k != "artifact"}


def _no_paths(obj: Any) -> Any:
    """``obj`` with every string that looks like a file path reduced to its last part."""
    if isinstance(obj, dict):
        return {k: _no_paths(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_no_paths(v) for v in obj]
    if isinstance(obj, str) and ("/" in obj or "\\" in obj or obj.startswith("~")):
        return obj.replace("\\", "/").rstrip("/").rsplit("/", 1)[-1]
    return obj


def make_entry(
    map_id: str,
    graph: RoadGraph,
    *,
    source: str = "",
    config: MatchConfig = DEFAULT_CONFIG,
    batch_config: MatchConfig = BATCH_CONFIG,
) -> MapEntry:
    """Build the index and matchers for a graph (``config`` the online matcher's parameters,
    ``batch_config`` the batch matcher's)."""
    from mapmatch.online import OnlineMatcher

    index = EdgeIndex(graph)
    online = OnlineMatcher(graph, index=index, config=config)
    return MapEntry(
        map_id=map_id,
        graph=graph,
        source=source,
        checksum=graph_checksum(graph),
        index=index,
        online=online,
        config=config,
        batch_config=batch_config,
    )


class MapRegistry:
    """Thread-safe registry of loaded maps by id.

    The id -> entry dict is never changed in place: a change builds a new dict (under the
    lock) and replaces the old one in one assignment, so :meth:`get`, which runs once per fix,
    reads without the lock.

    ``on_unload`` is called with a map id after it is removed (the session store drops its sessions).
    """

    def __init__(
        self, *, config: MatchConfig = DEFAULT_CONFIG, batch_config: MatchConfig = BATCH_CONFIG
    ) -> None:
        self._maps: dict[str, MapEntry] = {}
        self._lock = threading.Lock()
        self.config = config
        self.batch_config = batch_config
        self.on_unload: list[Callable[[str], int]] = []

    def add(
        self,
        map_id: str,
        graph: RoadGraph,
        *,
        source: str = "",
        warm: bool = True,
        batch: bool = True,
        path: Path | None = None,
        file: ReadOnlyFile | None = None,
    ) -> MapEntry:
        """Build, warm up (unless ``warm`` is False; the batch matcher too unless ``batch`` is
        False) and register a map, replacing one of the same id only once the new one has
        passed; returns its entry. ``path`` and ``file``: the map file ``graph`` was read
        from, if any, and its open descriptor."""
        entry = self.prepare(map_id, graph, source=source)
        if file is not None:  # a map file's entry: batch worker processes read that descriptor
            entry.path, entry.file = path, file
        if warm:
            warm_up(entry, batch=batch)
        return self.install(entry)

    def prepare(self, map_id: str, graph: RoadGraph, *, source: str = "") -> MapEntry:
        """A map's entry (index and matchers), not yet registered."""
        if not map_id or "/" in map_id:
            raise ValidationError("map_id", "must be a non-empty name without '/'")
        return make_entry(map_id, graph, source=source, config=self.config, batch_config=self.batch_config)

    def install(self, entry: MapEntry) -> MapEntry:
        """Register a prepared (and warmed-up) entry, replacing any map of the same id."""
        with self._lock:
            old = self._maps.get(entry.map_id)
            self._maps = {**self._maps, entry.map_id: entry}
        if old is not None and old.checksum != entry.checksum:
            self._dropped(entry.map_id)  # sessions refer to the old map's edges
        return entry

    def load(
        self,
        map_id: str,
        path: Path | MapSource,
        *,
        limits: LoadLimits | None = None,
        source: str = "",
        batch: bool = True,
    ) -> MapEntry:
        """Load a map file (or source), warm it up and register it. ``path``: an opened
        :class:`MapSource`, or a path to open once (:func:`open_map_path`).

        Raises
        ------
        MapLoadError, GraphError, LimitError
            The file cannot be served; a map of the same id stays as it was.
        """
        src = path if isinstance(path, MapSource) else open_map_path(Path(path), name=source)
        shown = source or Path(src.shown).name
        graph = load_map_file(src, limits=limits or LoadLimits(), name=shown)
        if not src.is_map:
            return self.add(map_id, graph, source=shown, batch=batch)
        return self.add(map_id, graph, source=shown, batch=batch, path=Path(src.path), file=src.file)

    def unload(self, map_id: str) -> int:
        """Remove a map; returns the number of sessions dropped with it."""
        with self._lock:
            if map_id not in self._maps:
                raise MapNotFoundError(map_id, sorted(self._maps))
            self._maps = {k: v for k, v in self._maps.items() if k != map_id}
        return self._dropped(map_id)

    def _dropped(self, map_id: str) -> int:
        return sum(cb(map_id) for cb in self.on_unload)

    def get(self, map_id: str = "") -> MapEntry:
        """The named map, or the only one when ``map_id`` is empty (no lock: see the class)."""
        maps = self._maps
        entry = maps.get(map_id) if map_id else None
        if entry is not None:
            return entry
        if not map_id and len(maps) > 1:
            names = ", ".join(sorted(maps))
            raise ValidationError("map_id", f"is required when several maps are loaded ({names})")
        if not map_id:
            entry = next(iter(maps.values()), None)
        if entry is None:
            raise MapNotFoundError(map_id, sorted(maps))
        return entry

    @property
    def default_id(self) -> str:
        with self._lock:
            return next(iter(self._maps)) if len(self._maps) == 1 else ""

    def entries(self) -> list[MapEntry]:
        with self._lock:
            return [self._maps[k] for k in sorted(self._maps)]

    def __len__(self) -> int:
        with self._lock:
            return len(self._maps)

    def __contains__(self, map_id: object) -> bool:
        with self._lock:
            return map_id in self._maps


# ---------------------------------------------------------------------------------- loading
_OPEN = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | getattr(os, "O_NOCTTY", 0)
SHAPEFILE_SIDECARS = (".shx", ".dbf", ".prj", ".cpg")
"""Files a Shapefile source is read with, opened beside it (those present)."""


@dataclass(eq=False)
class MapSource:
    """A map file or OSM/GIS source, opened once: everything after reads its descriptor.

    Attributes
    ----------
    file : ReadOnlyFile
        The open descriptor (a regular file, checked with ``fstat``).
    shown : str
        The name messages and ``MapInfo.source`` give it (relative to the map folder).
    path : str
        A path for display (``os.fspath`` gives it); never opened again.
    size : int
        Bytes, as ``fstat`` gave them.
    is_map : bool
        A prepared map file (else a source to build from).
    sidecars : dict
        For a Shapefile, its companion files by suffix, opened beside it.
    """

    file: ReadOnlyFile
    shown: str
    path: str
    size: int
    is_map: bool
    sidecars: dict[str, ReadOnlyFile] = field(default_factory=dict)

    def __fspath__(self) -> str:
        return self.path


def is_map_file(path: Path) -> bool:
    """Whether ``path`` is a prepared map file (not an OSM/GIS source); never blocks."""
    try:
        fd = os.open(path, _OPEN)
    except OSError:
        return False
    try:
        return stat.S_ISREG(os.fstat(fd).st_mode) and os.pread(fd, len(MAGIC), 0)[:-1] == MAGIC[:-1]
    finally:
        os.close(fd)


@dataclass(frozen=True)
class LoadLimits:
    """Limits of one map load.

    Attributes
    ----------
    max_bytes : int
        Largest file read.
    timeout : float
        Seconds a build from an OSM/GIS source may take.
    memory_bytes : int
        Address-space limit of the child process that builds from a source.
    """

    max_bytes: int = 4 * 1024**3
    timeout: float = 300.0
    memory_bytes: int = 8 * 1024**3


def _source(fd: int, *, shown: str, path: str) -> MapSource | None:
    """The :class:`MapSource` of an open descriptor (it takes the descriptor); None (the
    descriptor closed) unless it is a regular file."""
    file = ReadOnlyFile(fd, name=shown)
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        file.close()
        return None
    head = os.pread(fd, len(MAGIC), 0) if st.st_size else b""
    is_map = len(head) == len(MAGIC) and head[:-1] == MAGIC[:-1]
    return MapSource(file=file, shown=shown, path=path, size=st.st_size, is_map=is_map)


def open_map_path(path: Path, *, name: str = "") -> MapSource:
    """Open a map file or source the server's operator named (configuration, command line):
    once, non-blocking, checked to be a regular file. :class:`MapLoadError` otherwise."""
    shown = name or path.name
    try:
        fd = os.open(path, _OPEN)
    except FileNotFoundError:
        raise MapLoadError(f"path: no such map file {shown!r}") from None
    except OSError as exc:
        raise MapLoadError(f"path: cannot read map file {shown!r} ({exc.strerror})") from None
    src = _source(fd, shown=shown, path=str(path))
    if src is None:
        raise MapLoadError(f"path: {shown!r} is not a regular file")
    if path.suffix.lower() == ".shp":
        for suffix in SHAPEFILE_SIDECARS:
            with contextlib.suppress(OSError):
                side = os.open(path.with_suffix(suffix), _OPEN)
                src.sidecars[suffix] = ReadOnlyFile(side, name=shown)
    return src


def _relative_parts(map_dir: Path, requested: str) -> list[str]:
    """The components of a client-named path below ``map_dir``; :class:`MapPathError` for
    ``..``, an empty name, or an absolute path outside the folder."""
    rel = requested
    if os.path.isabs(requested):
        for root in {os.path.abspath(map_dir), _real_dir(map_dir)}:
            if requested.startswith(root.rstrip(os.sep) + os.sep):
                rel = requested[len(root.rstrip(os.sep)) + 1 :]
                break
        else:
            raise MapPathError()
    parts = [p for p in rel.split("/") if p not in ("", ".")]
    if not parts or ".." in parts:
        raise MapPathError()
    return parts


def _real_dir(map_dir: Path) -> str:
    try:
        return os.path.realpath(map_dir)
    except (OSError, ValueError):
        return os.path.abspath(map_dir)


def resolve_map_path(map_dir: Path | None, requested: str) -> MapSource:
    """Open a client-named map file inside ``map_dir``: :class:`MapPathError` (one message
    for every reason) unless it is a regular file there.

    The name is opened once, component by component relative to the folder's descriptor,
    each with ``O_NOFOLLOW`` (a symlink anywhere in it is refused, wherever it points), the
    file itself non-blocking (a FIFO or device never blocks) and checked with ``fstat``.
    No later step opens the name again, so a file swapped for a symlink between calls is
    either refused or read as the regular file it was when opened.
    """
    if map_dir is None or not requested or "\0" in requested:
        raise MapPathError()
    parts = _relative_parts(map_dir, requested)
    try:
        dir_fd = os.open(map_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        raise MapPathError() from None
    try:
        for part in parts[:-1]:
            sub = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=dir_fd)
            os.close(dir_fd)
            dir_fd = sub
        fd = os.open(parts[-1], _OPEN | os.O_NOFOLLOW, dir_fd=dir_fd)
        shown = "/".join(parts)
        # the path shown is under the folder's real path, as callers name the folder
        src = _source(fd, shown=shown, path=os.path.join(_real_dir(map_dir), shown))
        if src is None:
            raise MapPathError()
        if parts[-1].lower().endswith(".shp"):
            stem = parts[-1][: -len(".shp")]
            for suffix in SHAPEFILE_SIDECARS:
                with contextlib.suppress(OSError):
                    side = os.open(stem + suffix, _OPEN | os.O_NOFOLLOW, dir_fd=dir_fd)
                    src.sidecars[suffix] = ReadOnlyFile(side, name=shown)
        return src
    except OSError:
        raise MapPathError() from None
    finally:
        os.close(dir_fd)


def load_map_file(path: Path | MapSource, *, limits: LoadLimits, name: str = "") -> RoadGraph:
    """A map from a prepared map file (memory-mapped from its open descriptor), or built from
    an OSM/GIS source in a child process limited to ``limits.timeout`` seconds and
    ``limits.memory_bytes`` of memory (it reads the same descriptor).

    ``path``: a :class:`MapSource` (already open), or a path to open (:func:`open_map_path`).
    Errors name the file as ``name`` (never the server's path).
    """
    src = path if isinstance(path, MapSource) else open_map_path(path, name=name)
    shown = name or src.shown
    if src.size > limits.max_bytes:
        raise LimitError(
            "max_map_bytes",
            f"map file {shown!r} has {src.size} bytes, over the limit of {limits.max_bytes}",
        )
    try:
        if src.is_map:
            return load_map_fd(src.file.fileno(), name=shown)
        return _build_in_child(src, limits=limits)
    except GraphError as exc:
        raise MapLoadError(f"path: map {shown!r}: {_hide(str(exc), Path(src.path), shown)}") from None


def _hide(text: str, path: Path, shown: str) -> str:
    return text.replace(str(path), shown).replace(str(path.parent) + os.sep, "")


BUILD_PREFIX = "mapmatch-build-"
"""Temporary folders of builds: ``mapmatch-build-<server pid>-<random>`` in the temp folder."""
_BUILDS: set[subprocess.Popen[bytes]] = set()
_BUILDS_LOCK = threading.Lock()


def stop_builds() -> int:
    """Kill every build child still running (the server is stopping); returns how many.
    Their loads fail at once, and their temporary folders are removed."""
    with _BUILDS_LOCK:
        procs = list(_BUILDS)
    for proc in procs:
        with contextlib.suppress(OSError):
            proc.kill()
    return len(procs)


def _sweep_stale_builds() -> None:
    """Remove build folders whose server process is gone (killed before it could)."""
    root = Path(tempfile.gettempdir())
    with contextlib.suppress(OSError):
        for d in root.glob(BUILD_PREFIX + "*"):
            pid = d.name[len(BUILD_PREFIX) :].split("-", 1)[0]
            if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
                shutil.rmtree(d, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _build_in_child(src: MapSource, *, limits: LoadLimits) -> RoadGraph:
    """Build a map from a source in a child process with resource limits. The child reads
    the source's open descriptor (passed to it), writes a map file in a temporary folder,
    and that file is memory-mapped here. The child dies with this process
    (:func:`service.children.die_with_parent`) and removes its folder when it is stopped."""
    _sweep_stale_builds()
    tmp = Path(tempfile.mkdtemp(prefix=f"{BUILD_PREFIX}{os.getpid()}-"))
    out = tmp / "built.map"
    fds = {"": src.file.fileno(), **{k: f.fileno() for k, f in src.sidecars.items()}}
    cmd = [sys.executable, "-m", __name__, json.dumps({
        "fds": fds,
        "name": Path(src.shown).name,
        "out": str(out),
        "memory": limits.memory_bytes,
        "cpu": max(1, math.ceil(limits.timeout)),
        "parent": os.getpid(),
    })]  # fmt: skip
    try:
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            pass_fds=tuple(fds.values()),
        )
        with _BUILDS_LOCK:
            _BUILDS.add(proc)
        try:
            _, err = proc.communicate(timeout=limits.timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise LimitError("load_timeout", f"building the map took over {limits.timeout:g} s") from None
        finally:
            with _BUILDS_LOCK:
                _BUILDS.discard(proc)
        _check_build(proc.returncode, err, limits)
        fd = os.open(out, os.O_RDONLY | os.O_CLOEXEC | os.O_NOFOLLOW)
        try:
            return load_map_fd(fd, name="built.map")
        finally:
            os.close(fd)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # the memory map keeps the data


def _check_build(code: int, stderr: bytes, limits: LoadLimits) -> None:
    """The error of a build child's exit status ``code`` (none for 0)."""
    if code == 0:
        return
    lines = stderr.decode(errors="replace").strip().splitlines()
    last = lines[-1] if lines else f"exit status {code}"
    if code == -signal.SIGXCPU:
        raise LimitError("load_timeout", f"building the map took over {limits.timeout:g} s of CPU")
    if code < 0 or "MemoryError" in last:
        raise LimitError(
            "load_memory_bytes",
            f"building the map was stopped ({last}; limits {limits.memory_bytes} bytes, "
            f"{limits.timeout:g} s)",
        )
    raise MapLoadError(f"path: cannot build a map from it: {last}")


def _child_main(argv: list[str]) -> int:
    """A build child: ``argv[0]`` is JSON with the source descriptors (``fds``, by suffix;
    ``""`` the source itself), its file ``name``, ``out``, ``memory`` (bytes), ``cpu``
    (seconds) and the ``parent`` pid. Limit this process, build, save."""
    job = json.loads(argv[0])
    tmp = Path(job["out"]).parent

    def gone(*_: Any) -> None:  # the server ended or stops this build: leave nothing behind
        shutil.rmtree(tmp, ignore_errors=True)
        os._exit(143)

    signal.signal(signal.SIGTERM, gone)
    die_with_parent(int(job["parent"]), sig=signal.SIGTERM)
    threading.Thread(target=_watch_parent, args=(int(job["parent"]), gone), daemon=True).start()
    memory, cpu = int(job["memory"]), int(job["cpu"])
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))
    # the source as a name the builders can open (their formats go by the file name): links
    # to this process's descriptors of the files the server opened
    source = tmp / "source" / job["name"]
    source.parent.mkdir()
    stem = source.name[: -len(".shp")] if source.name.lower().endswith(".shp") else ""
    for suffix, fd in job["fds"].items():
        link = source if not suffix else source.with_name(stem + suffix)
        os.symlink(f"/proc/self/fd/{int(fd)}", link)
    from graph.build import build_map

    try:
        save_map(build_map(source), job["out"])
    except GraphError as exc:
        print(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, file=sys.stderr)
        return 2
    except MemoryError:
        print("MemoryError: over the memory limit", file=sys.stderr)
        return 3
    return 0


def _watch_parent(parent: int, gone: Callable[..., None]) -> None:
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:
            gone()


# ---------------------------------------------------------------------------------- warm-up
def warm_up(entry: MapEntry, *, batch: bool = True) -> None:
    """One online fix at the start of the map's longest road (and, with ``batch``, one batch
    match when the batch kernels are compiled: :func:`warm_batch`) through the matchers and
    converters requests use; raises :class:`MapLoadError` when the map cannot serve. Leaves no
    session behind."""
    from service import convert

    g = entry.graph
    if g.n_edges == 0:
        raise MapLoadError(f"path: map {entry.map_id!r} has no roads")
    e = int(g.edge_len.argmax())
    lon0, lat0 = (float(x) for x in g.node_lonlat[int(g.edge_u[e])])
    # at the road's start node: on the road whatever its shape
    heading = float(g.edge_bearing_start[e]) % 360.0
    fix = Fix(time=0.0, lat=lat0, lon=lon0, heading=heading, pos_sigma=5.0, speed=5.0)
    # a second fix a little way on: the placement kernels load (or compile) now, not on a
    # vehicle's first fix
    step = min(3.0, 0.5 * float(g.edge_len[e]))
    x0, y0 = (float(v) for v in g.node_xy[int(g.edge_u[e])])
    rad = math.radians(heading)
    lon1, lat1 = point_to_lonlat(g.crs, x0 + step * math.sin(rad), y0 + step * math.cos(rad))
    fix1 = Fix(time=1.0, lat=lat1, lon=lon1, heading=heading, pos_sigma=5.0, speed=step)
    try:
        fix.validate()
        state = entry.online.new_session()
        result = entry.online.update(state, fix)
        convert.snap_result_to_proto(result)
        convert.snap_result_to_proto(entry.online.update(state, fix1))
    except (ValidationError, GraphError) as exc:
        raise MapLoadError(f"path: map {entry.map_id!r} failed its warm-up query ({exc})") from None
    except Exception as exc:
        raise MapLoadError(
            f"path: map {entry.map_id!r} failed its warm-up query ({type(exc).__name__})"
        ) from None
    if result.state is State.OFF_ROAD or not math.isfinite(result.time):
        raise MapLoadError(
            f"path: map {entry.map_id!r} failed its warm-up: a fix on one of its roads came back off-road "
            "(wrong CRS or coordinates?)"
        )
    if batch:
        warm_batch(entry)


def warm_batch(entry: MapEntry, *, compile: bool = False) -> None:
    """One batch match along the map's longest road when the batch kernels are compiled, or
    with ``compile`` also when they are not (a batch worker process compiles them before it
    reports ready; the server process itself never waits for that); raises
    :class:`MapLoadError` when it fails."""
    from mapmatch.kernels import is_cached

    if not compile and not is_cached("batch"):
        return
    g = entry.graph
    e = int(g.edge_len.argmax())
    lon0, lat0 = (float(x) for x in g.node_lonlat[int(g.edge_u[e])])
    lon, lat = (float(x) for x in g.node_lonlat[int(g.edge_v[e])])
    try:
        entry.batch.match(
            Track(
                track_id="warmup",
                time=np.array([0.0, 1.0]),
                lat=np.array([lat0, lat]),
                lon=np.array([lon0, lon]),
            )
        )
    except Exception as exc:
        raise MapLoadError(
            f"path: map {entry.map_id!r} failed its batch warm-up ({type(exc).__name__})"
        ) from None


if __name__ == "__main__":
    sys.exit(_child_main(sys.argv[1:]))
