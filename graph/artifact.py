"""The prepared map artifact: one versioned file, written atomically, memory-mapped on load.

Layout of a map file (little-endian)::

    8 bytes   magic  b"RGMAP\\x00\\x00\\x01"
    8 bytes   uint64 length H of the JSON manifest
    H bytes   manifest (UTF-8 JSON), padded with spaces to a 64-byte boundary
    ...       the arrays, raw C order, each starting on a 64-byte boundary

The manifest holds the format version, CRS, bbox, counts, map statistics, the source's
checksum, the build parameters, the lookup tables, and per array its dtype, shape, offset and
SHA-256. Loading maps the file once (``numpy.memmap``, read-only) and verifies every checksum;
it imports neither osmnx nor networkx.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.errors import ArtifactError
from graph.road_graph import ARRAY_FIELDS, PIECE_FIELDS, RoadGraph

MAGIC = b"RGMAP\x00\x00\x01"
FORMAT = "mapmatch-roadgraph"
FORMAT_VERSION = 1
_ALIGN = 64


def _pad(n: int) -> int:
    return (-n) % _ALIGN


def _jsonable(obj: Any) -> Any:
    """Coerce numpy scalars, paths, tuples and sets into plain JSON values."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    return str(obj)


def edge_length_histogram(graph: RoadGraph) -> dict[str, list[float]]:
    """Counts of edge lengths in log-spaced bins (1 m .. 100 km; the first bin starts at 0)."""
    edges = [0.0, *np.logspace(0, 5, 11).tolist()]
    counts, _ = np.histogram(np.clip(graph.edge_len, 0.0, edges[-1]), bins=edges)
    return {"bins_m": [round(x, 3) for x in edges], "counts": counts.tolist()}


def manifest_for(graph: RoadGraph) -> dict[str, Any]:
    """The manifest fields that describe a graph (without the array table)."""
    meta = _jsonable(graph.meta)
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "crs": graph.crs,
        "bbox": list(graph.bbox),
        "counts": {
            "nodes": graph.n_nodes,
            "edges": graph.n_edges,
            "segments": len(graph.seg_xy),
            "restrictions": len(graph.restrictions),
        },
        "stats": _jsonable({**graph.stats(), "edge_len_histogram": edge_length_histogram(graph)}),
        "source": meta.get("source", {}),
        "build": meta.get("build", {}),
        "meta": meta,
        "names": list(graph.names),
        "highways": list(graph.highways),
    }


def save_map(graph: RoadGraph, path: str | os.PathLike[str]) -> None:
    """Write ``graph`` to the map file ``path`` atomically (temporary file, then rename).

    Parameters
    ----------
    graph
        The road graph to store.
    path
        Destination file. An existing file is replaced only once the new one is complete.

    Raises
    ------
    ArtifactError
        When the file cannot be written.
    """
    dest = Path(path)
    arrays = {k: np.ascontiguousarray(v) for k, v in graph.arrays().items()}
    raw = {k: a.reshape(-1).view(np.uint8) for k, a in arrays.items()}
    table: dict[str, dict[str, Any]] = {}
    offset = 0
    for name in ARRAY_FIELDS:
        a = arrays[name]
        table[name] = {
            "dtype": a.dtype.str,
            "shape": list(a.shape),
            "offset": offset,
            "nbytes": int(a.nbytes),
            "sha256": hashlib.sha256(raw[name].data).hexdigest(),
        }
        offset += a.nbytes + _pad(a.nbytes)
    manifest = manifest_for(graph)
    manifest["arrays"] = table
    head = json.dumps(manifest, separators=(",", ":"), allow_nan=False, default=str).encode()
    head += b" " * _pad(len(MAGIC) + 8 + len(head))
    tmp_name = ""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC)
            f.write(np.uint64(len(head)).tobytes())
            f.write(head)
            for name in ARRAY_FIELDS:
                a = arrays[name]
                f.write(raw[name].data)
                f.write(b"\0" * _pad(a.nbytes))
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, dest)
    except (OSError, ValueError) as exc:
        if tmp_name:
            Path(tmp_name).unlink(missing_ok=True)
        raise ArtifactError(f"cannot write map file {dest}: {exc}") from exc
    except BaseException:
        if tmp_name:
            Path(tmp_name).unlink(missing_ok=True)
        raise


def _read_head(f: Any, path: Path) -> tuple[dict[str, Any], int]:
    start = f.read(len(MAGIC) + 8)
    if len(start) < len(MAGIC) + 8 or start[: len(MAGIC) - 1] != MAGIC[:-1]:
        raise ArtifactError(f"{path} is not a prepared map file")
    if start[len(MAGIC) - 1] != MAGIC[-1]:
        raise ArtifactError(f"{path}: unsupported map file version {start[len(MAGIC) - 1]}")
    hlen = int(np.frombuffer(start[len(MAGIC) :], dtype="<u8")[0])
    if hlen > os.fstat(f.fileno()).st_size - len(start):
        raise ArtifactError(f"{path} is truncated or corrupt (manifest length beyond the end of the file)")
    raw = f.read(hlen)
    if len(raw) != hlen:
        raise ArtifactError(f"{path} is truncated")
    try:
        manifest = json.loads(raw)
    except ValueError as exc:
        raise ArtifactError(f"{path}: corrupt manifest") from exc
    if manifest.get("format") != FORMAT or manifest.get("format_version") != FORMAT_VERSION:
        raise ArtifactError(
            f"{path}: unsupported map format {manifest.get('format')!r} "
            f"version {manifest.get('format_version')!r} (this program reads version {FORMAT_VERSION})"
        )
    return manifest, len(MAGIC) + 8 + hlen


def read_manifest(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of a map file, without reading its arrays."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            return _read_head(f, p)[0]
    except FileNotFoundError as exc:
        raise ArtifactError(f"no such map file: {p}") from exc
    except IsADirectoryError as exc:
        raise ArtifactError(f"{p} is a directory, not a map file") from exc
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc


def load_map(path: str | os.PathLike[str], *, verify: bool = True) -> RoadGraph:
    """Load a map file written by :func:`save_map`.

    The arrays are read-only memory maps of the file. Every array's SHA-256 is checked
    unless ``verify`` is False.

    Raises
    ------
    ArtifactError
        Missing file, wrong format or version, truncated file, or a checksum mismatch.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            manifest, data_start = _read_head(f, p)
        size = p.stat().st_size
    except FileNotFoundError as exc:
        raise ArtifactError(f"no such map file: {p}") from exc
    except IsADirectoryError as exc:
        raise ArtifactError(f"{p} is a directory, not a map file") from exc
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc
    table = manifest.get("arrays", {})
    # maps written before way pieces get one piece per edge (RoadGraph fills them in)
    missing = [k for k in ARRAY_FIELDS if k not in table and k not in PIECE_FIELDS]
    if missing:
        raise ArtifactError(f"{p}: map file lacks arrays {', '.join(missing)}")
    end = data_start + max((t["offset"] + t["nbytes"] for t in table.values()), default=0)
    if end > size:
        raise ArtifactError(f"{p} is truncated ({size} of {end} bytes)")
    buf: NDArray[np.uint8] = np.memmap(p, dtype=np.uint8, mode="r") if size else np.empty(0, np.uint8)
    arrays: dict[str, NDArray[Any]] = {}
    for name in (k for k in ARRAY_FIELDS if k in table):
        t = table[name]
        lo = data_start + int(t["offset"])
        raw = buf[lo : lo + int(t["nbytes"])]
        if verify and hashlib.sha256(raw.data).hexdigest() != t["sha256"]:
            raise ArtifactError(f"{p}: checksum mismatch in {name} (file corrupt)")
        try:
            arrays[name] = raw.view(np.dtype(t["dtype"])).reshape(t["shape"])
        except (TypeError, ValueError) as exc:
            raise ArtifactError(f"{p}: bad array {name}: {exc}") from exc
    meta = manifest.get("meta", {})
    meta = {**meta, "artifact": {"path": str(p), "bytes": size}}
    return RoadGraph(
        crs=str(manifest["crs"]),
        names=list(manifest.get("names", [])),
        highways=list(manifest.get("highways", [])),
        meta=meta,
        **arrays,
    )


def file_sha256(path: str | os.PathLike[str], *, chunk: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes (the source checksum in the manifest)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def open_map(path: str | os.PathLike[str]) -> RoadGraph:
    """A prepared map file (fast, memory-mapped), or else an OSM/GIS source built on the fly.

    The source case imports the builder (osmnx) only when it is needed.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(len(MAGIC))
    except FileNotFoundError:
        raise ArtifactError(f"no such map file: {p}") from None
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc
    if head[:-1] == MAGIC[:-1]:  # any format version: load_map reports a mismatch
        return load_map(p)
    from graph.build import build_map

    return build_map(p)
