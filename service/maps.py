"""The registry of loaded maps: several cities per server, loaded and unloaded at run time.

Each entry holds the read-only :class:`RoadGraph`, its :class:`EdgeIndex` and the shared,
thread-safe online and batch matchers built on it. Requests name a map by id; an empty id
means the only loaded map.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from graph.artifact import open_map
from graph.errors import GraphError
from graph.index import EdgeIndex
from graph.road_graph import ARRAY_FIELDS, RoadGraph
from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import MatchError, ValidationError


class MapNotFoundError(MatchError, LookupError):
    """A request named a map this server has not loaded (gRPC NOT_FOUND)."""

    def __init__(self, map_id: str, known: list[str]) -> None:
        have = ", ".join(known) if known else "none"
        msg = f"map_id: unknown map {map_id!r} (loaded: {have})" if map_id else "map_id: no map is loaded"
        super().__init__(msg)
        self.map_id = map_id
        self.field = "map_id"


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
    _batch: Any = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def batch(self) -> Any:
        """The map's batch matcher (thread-safe, with the batch defaults), built on first use."""
        with self._lock:
            if self._batch is None:
                from mapmatch.batch import BatchMatcher

                self._batch = BatchMatcher(self.graph, index=self.index)
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
        meta = self.graph.meta
        return {k: v for k, v in meta.items() if k != "artifact"}


def make_entry(
    map_id: str, graph: RoadGraph, *, source: str = "", config: MatchConfig = DEFAULT_CONFIG
) -> MapEntry:
    """Build the index and matchers for a graph."""
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
    )


class MapRegistry:
    """Thread-safe registry of loaded maps by id.

    ``on_unload`` is called with a map id after it is removed (the session store drops its sessions).
    """

    def __init__(self, *, config: MatchConfig = DEFAULT_CONFIG) -> None:
        self._maps: dict[str, MapEntry] = {}
        self._lock = threading.Lock()
        self.config = config
        self.on_unload: list[Callable[[str], int]] = []

    def add(self, map_id: str, graph: RoadGraph, *, source: str = "") -> MapEntry:
        """Register (or replace) a map; returns its entry."""
        if not map_id or "/" in map_id:
            raise ValueError("map id must be a non-empty name without '/'")
        entry = make_entry(map_id, graph, source=source, config=self.config)
        with self._lock:
            old = self._maps.get(map_id)
            self._maps[map_id] = entry
        if old is not None and old.checksum != entry.checksum:
            self._dropped(map_id)  # sessions refer to the old map's edges
        return entry

    def load(self, map_id: str, path: Path) -> MapEntry:
        """Load a map file (or source) from disk and register it."""
        try:
            graph = open_map(Path(path))
        except (GraphError, MatchError, OSError):
            raise
        except Exception as exc:  # e.g. a corrupt file the loader did not recognise
            raise ValidationError(
                "path", f"cannot load map {map_id!r} from {path} ({type(exc).__name__})"
            ) from exc
        return self.add(map_id, graph, source=str(path))

    def unload(self, map_id: str) -> int:
        """Remove a map; returns the number of sessions dropped with it."""
        with self._lock:
            if map_id not in self._maps:
                raise MapNotFoundError(map_id, sorted(self._maps))
            del self._maps[map_id]
        return self._dropped(map_id)

    def _dropped(self, map_id: str) -> int:
        return sum(cb(map_id) for cb in self.on_unload)

    def get(self, map_id: str = "") -> MapEntry:
        """The named map, or the only one when ``map_id`` is empty."""
        with self._lock:
            if map_id:
                entry = self._maps.get(map_id)
            elif len(self._maps) > 1:
                raise ValidationError(
                    "map_id", f"is required when several maps are loaded ({', '.join(sorted(self._maps))})"
                )
            else:
                entry = next(iter(self._maps.values()), None)
            if entry is None:
                raise MapNotFoundError(map_id, sorted(self._maps))
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
