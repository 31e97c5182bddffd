"""The registry of loaded maps: several cities per server, loaded and replaced at run time.

Each entry holds the read-only :class:`RoadGraph`, its :class:`EdgeIndex` and the shared,
thread-safe online and batch matchers built on it. Requests name a map by id; an empty id
means the only loaded map.

A map is loaded and warmed up (:func:`warm_up`) before it is registered, so a replacement
that fails leaves the map it would replace serving. Files named by clients
(:func:`resolve_map_path`) must be regular files inside the configured map folder; a map
built from an OSM/GIS source is built in a child process with time and memory limits
(:func:`load_map_file`).
"""

from __future__ import annotations

import hashlib
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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from graph.artifact import MAGIC, load_map, save_map
from graph.errors import GraphError
from graph.index import EdgeIndex
from graph.projection import point_to_lonlat
from graph.road_graph import ARRAY_FIELDS, RoadGraph
from mapmatch.config import BATCH_CONFIG, DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ValidationError
from mapmatch.types import Fix, State, Track
from service.errors import LimitError, MapLoadError, MapNotFoundError, MapPathError

__all__ = [
    "LoadLimits",
    "MapEntry",
    "MapNotFoundError",
    "MapRegistry",
    "graph_checksum",
    "is_map_file",
    "load_map_file",
    "make_entry",
    "resolve_map_path",
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
    path: Path | None = None  # the map file it was loaded from (batch worker processes map it too)
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
    ) -> MapEntry:
        """Build, warm up (unless ``warm`` is False; the batch matcher too unless ``batch`` is
        False) and register a map, replacing one of the same id only once the new one has
        passed; returns its entry. ``path``: the map file ``graph`` was read from, if any."""
        entry = self.prepare(map_id, graph, source=source)
        entry.path = path
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
        self, map_id: str, path: Path, *, limits: LoadLimits | None = None, source: str = ""
    ) -> MapEntry:
        """Load a map file (or source) from disk, warm it up and register it.

        Raises
        ------
        MapLoadError, GraphError, LimitError
            The file cannot be served; a map of the same id stays as it was.
        """
        graph = load_map_file(Path(path), limits=limits or LoadLimits(), name=source or Path(path).name)
        file = Path(path) if is_map_file(Path(path)) else None
        return self.add(map_id, graph, source=source or Path(path).name, path=file)

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
def is_map_file(path: Path) -> bool:
    """Whether ``path`` is a prepared map file (not an OSM/GIS source); never blocks."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return False
    try:
        return stat.S_ISREG(os.fstat(fd).st_mode) and os.read(fd, len(MAGIC))[:-1] == MAGIC[:-1]
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


def resolve_map_path(map_dir: Path | None, requested: str) -> Path:
    """The real path of a client-named map file; :class:`MapPathError` (one message for
    every reason) unless it is a regular file inside ``map_dir``.

    The file is opened non-blocking and checked with ``fstat``, so a FIFO or device never
    blocks; symlinks may point anywhere inside ``map_dir`` but not out of it.
    """
    if map_dir is None or not requested or "\0" in requested:
        raise MapPathError()
    root = os.path.realpath(map_dir)
    real = os.path.realpath(os.path.join(root, requested))
    if os.path.commonpath([root, real]) != root or real == root:
        raise MapPathError()
    try:
        fd = os.open(real, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError:
        raise MapPathError() from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise MapPathError()
    finally:
        os.close(fd)
    return Path(real)


def load_map_file(path: Path, *, limits: LoadLimits, name: str = "") -> RoadGraph:
    """A map from a prepared map file, or built from an OSM/GIS source in a child process
    limited to ``limits.timeout`` seconds and ``limits.memory_bytes`` of memory.

    Errors name the file as ``name`` (never the server's path).
    """
    shown = name or path.name
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise MapLoadError(f"path: no such map file {shown!r}") from None
    except OSError as exc:
        raise MapLoadError(f"path: cannot read map file {shown!r} ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise MapLoadError(f"path: {shown!r} is not a regular file")
        if st.st_size > limits.max_bytes:
            raise LimitError(
                "max_map_bytes",
                f"map file {shown!r} has {st.st_size} bytes, over the limit of {limits.max_bytes}",
            )
        head = os.read(fd, len(MAGIC))
    finally:
        os.close(fd)
    try:
        if head[:-1] == MAGIC[:-1]:
            return load_map(path)
        return _build_in_child(path, limits=limits)
    except GraphError as exc:
        raise MapLoadError(f"path: map {shown!r}: {_hide(str(exc), path, shown)}") from None


def _hide(text: str, path: Path, shown: str) -> str:
    return text.replace(str(path), shown).replace(str(path.parent) + os.sep, "")


def _build_in_child(path: Path, *, limits: LoadLimits) -> RoadGraph:
    """Build a map from a source file in a child process with resource limits; the child
    writes a map file that is memory-mapped here."""
    tmp = Path(tempfile.mkdtemp(prefix="mapmatch-build-"))
    out = tmp / "built.map"

    try:
        try:
            proc = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    __name__,
                    str(path),
                    str(out),
                    str(limits.memory_bytes),
                    str(max(1, math.ceil(limits.timeout))),
                ],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                timeout=limits.timeout,
                check=False,
            )
        except subprocess.TimeoutExpired:
            raise LimitError("load_timeout", f"building the map took over {limits.timeout:g} s") from None
        if proc.returncode != 0:
            lines = proc.stderr.decode(errors="replace").strip().splitlines()
            last = lines[-1] if lines else f"exit status {proc.returncode}"
            if proc.returncode == -signal.SIGXCPU:
                raise LimitError("load_timeout", f"building the map took over {limits.timeout:g} s of CPU")
            if proc.returncode < 0 or "MemoryError" in last:
                raise LimitError(
                    "load_memory_bytes",
                    f"building the map was stopped ({last}; limits {limits.memory_bytes} bytes, "
                    f"{limits.timeout:g} s)",
                )
            raise MapLoadError(f"path: cannot build a map from it: {last}")
        graph = load_map(out)
        return graph
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # the memory map keeps the data


def _child_main(argv: list[str]) -> int:
    """``SOURCE OUT MEMORY_BYTES CPU_SECONDS``: limit this process, build, save."""
    memory, cpu = int(argv[2]), int(argv[3])
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))
    from graph.build import build_map

    try:
        save_map(build_map(Path(argv[0])), argv[1])
    except GraphError as exc:
        print(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, file=sys.stderr)
        return 2
    except MemoryError:
        print("MemoryError: over the memory limit", file=sys.stderr)
        return 3
    return 0


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


def warm_batch(entry: MapEntry) -> None:
    """One batch match along the map's longest road when the batch kernels are compiled (on a
    machine's first run the first MatchTrack compiles them, about a minute, and nothing need
    wait for that); raises :class:`MapLoadError` when it fails."""
    from mapmatch.kernels import is_cached

    if not is_cached("batch"):
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
