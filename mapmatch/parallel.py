"""Running batch matching over many tracks: local process pool or a Dask cluster, resumable.

Tracks are grouped into partitions. Each partition is matched by one worker (which loads the
map once per process) and written as one GeoParquet file ``part-NNNNN.parquet`` in the parts
folder, atomically; a restarted run skips the partitions already written, so nothing is done
twice and no row is lost or duplicated. The final output (GeoJSON, CSV or GeoParquet file) is
assembled from the parts; when the output is a folder, the parts are the output (partitioned
Parquet, what a Dask run on a cluster writes).

Input partitions: each Parquet file of an input folder is a partition that the worker reads
itself (so a cluster reads partitioned Parquet in parallel); other inputs are read here and cut
into partitions of ``partition_size`` tracks.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from graph.files import atomic_path
from mapmatch.config import BATCH_CONFIG, UBODT_MAX_BYTES, MatchConfig
from mapmatch.errors import MatchError
from mapmatch.io import (
    DEFAULT_COLUMNS,
    RESULT_COLUMNS,
    Columns,
    read_results,
    read_tracks,
    results_table,
    write_geoparquet,
    write_results,
)
from mapmatch.types import Track

MANIFEST = "_run.json"
ROUTE_TABLE_PREFIX = "_route_table-"
PARQUET_SUFFIXES = (".parquet", ".geoparquet", ".pq")


class RunError(MatchError):
    """A batch run cannot start or finish (bad output path, parts from another run...)."""


@dataclass(frozen=True)
class Partition:
    """One unit of work: either a Parquet file the worker reads, or tracks shipped to it."""

    index: int
    source: str | None = None
    tracks: tuple[Track, ...] = ()
    n_points: int = 0


@dataclass
class RunSummary:
    """What a run did."""

    partitions: int = 0
    skipped: int = 0
    tracks: int = 0
    points: int = 0
    seconds: float = 0.0
    output: str = ""
    parts_dir: str = ""
    failed: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------- worker side
_CACHE: dict[tuple[str, float, float, float, int | None, str | None], Any] = {}


def _matcher(
    map_path: str,
    ubodt_delta: float | None,
    turn_cost: float,
    ubodt_max_bytes: int | None = None,
    ubodt_path: str | None = None,
) -> Any:
    """The process's matcher for a map file (and optional route table, its routes costing
    ``turn_cost`` per turn back, of at most about ``ubodt_max_bytes``: mapped from
    ``ubodt_path`` when the run built it once for every worker, else built here), loaded once."""
    from graph.artifact import load_map
    from mapmatch.batch import BatchMatcher
    from mapmatch.route_table import Ubodt

    key = (
        os.path.abspath(map_path),
        os.path.getmtime(map_path),
        float(ubodt_delta or 0.0),
        float(turn_cost),
        ubodt_max_bytes,
        ubodt_path,
    )
    m = _CACHE.get(key)
    if m is None:
        _CACHE.clear()
        graph = load_map(map_path)
        table = None
        if ubodt_path:
            table = Ubodt.load(ubodt_path)
        elif ubodt_delta:
            table = Ubodt.build(graph, ubodt_delta, turn_cost=turn_cost, max_bytes=ubodt_max_bytes)
        m = _CACHE[key] = BatchMatcher(graph, ubodt=table)
    return m


def match_partition(
    map_path: str,
    part: Partition,
    out_file: str,
    config: MatchConfig | None = None,
    columns: Columns = DEFAULT_COLUMNS,
    ubodt_delta: float | None = None,
    ubodt_max_bytes: int | None = None,
    ubodt_path: str | None = None,
) -> tuple[int, int]:
    """Match one partition and write its results file atomically: ``(tracks, points)``."""
    turn_cost = (config or BATCH_CONFIG).batch.turn_cost
    matcher = _matcher(map_path, ubodt_delta, turn_cost, ubodt_max_bytes, ubodt_path)
    tracks = list(part.tracks) if part.source is None else read_tracks(part.source, columns=columns)
    results = [matcher.match(t, config) for t in tracks]
    write_geoparquet(out_file, results_table(results, matcher.graph))
    return len(tracks), sum(len(t) for t in tracks)


# ---------------------------------------------------------------------- planning
def plan_partitions(
    inputs: Sequence[str | os.PathLike[str]], *, columns: Columns = DEFAULT_COLUMNS, partition_size: int = 64
) -> list[Partition]:
    """Partitions of the inputs, in a stable order (the same inputs give the same plan)."""
    parts: list[Partition] = []
    loose: list[Track] = []
    for inp in inputs:
        p = Path(inp)
        if p.is_dir():
            files = sorted(q for q in p.iterdir() if q.name.lower().endswith(PARQUET_SUFFIXES))
            if not files:
                raise RunError(f"{p}: no Parquet files in the folder")
            for q in files:
                parts.append(Partition(index=0, source=str(q), n_points=_parquet_rows(q)))
        else:
            loose.extend(read_tracks(p, columns=columns))
    size = max(int(partition_size), 1)
    for i in range(0, len(loose), size):
        chunk = tuple(loose[i : i + size])
        parts.append(Partition(index=0, tracks=chunk, n_points=sum(len(t) for t in chunk)))
    return [Partition(i, p.source, p.tracks, p.n_points) for i, p in enumerate(parts)]


def _parquet_rows(path: Path) -> int:
    import pyarrow.parquet as pq

    return int(pq.ParquetFile(path).metadata.num_rows)


def _fingerprint(
    inputs: Sequence[str | os.PathLike[str]],
    map_path: str,
    config: MatchConfig | None,
    columns: Columns,
    size: int,
) -> str:
    h = hashlib.sha256()
    for p in [*inputs, map_path]:
        q = Path(p)
        files = sorted(q.iterdir()) if q.is_dir() else [q]
        for f in files:
            st = f.stat()
            h.update(f"{f.resolve()}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    h.update(
        json.dumps([config.to_dict() if config else None, asdict(columns), size], sort_keys=True).encode()
    )
    return h.hexdigest()


def parts_dir_for(out: Path) -> Path:
    """Where the partition files of an output go: the folder itself, or ``OUT.parts/``."""
    return out if _is_dir_output(out) else out.with_name(out.name + ".parts")


def _is_dir_output(out: Path) -> bool:
    return out.is_dir() or not out.suffix


# ---------------------------------------------------------------------- the run
def run_batch(
    inputs: Sequence[str | os.PathLike[str]],
    map_path: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    config: MatchConfig | None = None,
    columns: Columns = DEFAULT_COLUMNS,
    workers: int | None = None,
    scheduler: str | Any | None = None,
    partition_size: int = 64,
    ubodt_delta: float | None = None,
    ubodt_max_bytes: int | None = UBODT_MAX_BYTES,
    progress: Callable[[int, int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
) -> RunSummary:
    """Match every track of ``inputs`` against the map file and write ``out``.

    Parameters
    ----------
    inputs
        Track files (CSV, GPX, Parquet) and folders of Parquet parts.
    map_path
        A map file written by ``mapmatch prep`` (read by every worker; on a cluster it must be
        at the same path on every machine).
    out
        ``.geojson``, ``.csv``, ``.parquet``/``.geoparquet`` file, or a folder for
        partitioned GeoParquet output.
    workers
        Local processes (default: the machine's cores; 1 runs in this process).
    scheduler
        ``tcp://host:port`` of a dask.distributed scheduler, or a ``distributed.Client``.
    partition_size
        Tracks per partition for non-Parquet inputs.
    ubodt_delta
        When given, a route table (:class:`mapmatch.route_table.Ubodt`) of this bound in metres
        is precomputed: faster matching for more memory and start-up time. With worker
        processes or Dask, the run builds it once into the parts folder and every worker maps
        that file (one table's memory on a machine, however many workers); in process, it is
        built there.
    ubodt_max_bytes
        The table's memory budget (about; ``None``: no limit). Where the bound's
        table would not fit, a shorter bound is used; the matches are the same.
    progress
        Called with ``(points, tracks)`` as partitions finish (after resumed ones).
    on_total
        Called once with the total number of points to match.
    """
    t0 = time.perf_counter()
    outp = Path(out)
    map_s = str(map_path)
    if not Path(map_s).is_file():
        raise RunError(f"no such map file: {map_s}")
    if not _is_dir_output(outp) and not outp.name.lower().endswith(
        (".geojson", ".json", ".csv", ".parquet", ".geoparquet")
    ):
        raise RunError(f"{outp}: unknown output format (use .geojson, .csv, .parquet or a folder)")
    parts = plan_partitions(inputs, columns=columns, partition_size=partition_size)
    pdir = parts_dir_for(outp)
    fp = _fingerprint(inputs, map_s, config, columns, partition_size)
    _prepare_parts_dir(pdir, fp, len(parts))
    files = [pdir / f"part-{p.index:05d}.parquet" for p in parts]
    todo = [p for p, f in zip(parts, files, strict=True) if not f.exists()]
    summary = RunSummary(partitions=len(parts), skipped=len(parts) - len(todo), parts_dir=str(pdir))
    if on_total:
        on_total(sum(p.n_points for p in todo))
    in_process = scheduler is None and (workers == 1 or len(todo) <= 1)
    shared = None
    if ubodt_delta and todo and not in_process:  # built once, mapped by every worker
        turn_cost = (config or BATCH_CONFIG).batch.turn_cost
        shared = _shared_route_table(pdir, map_s, ubodt_delta, ubodt_max_bytes, turn_cost)
    route_table = (ubodt_delta, ubodt_max_bytes, str(shared) if shared else None)
    done: Iterable[tuple[int, int]]
    if scheduler is not None:
        done = _run_dask(scheduler, map_s, todo, files, config, columns, route_table)
    elif in_process:
        done = (match_partition(map_s, p, str(files[p.index]), config, columns, *route_table) for p in todo)
    else:
        done = _run_pool(workers, map_s, todo, files, config, columns, route_table)
    for ntr, npts in done:
        summary.tracks += ntr
        summary.points += npts
        if progress:
            progress(npts, ntr)
    if shared is not None:
        shutil.rmtree(shared, ignore_errors=True)
    if not _is_dir_output(outp):
        if files:
            table = pd.concat([read_results(f) for f in files], ignore_index=True)
        else:
            table = pd.DataFrame({c: [] for c in RESULT_COLUMNS})
        write_results(outp, table)
        shutil.rmtree(pdir, ignore_errors=True)
    summary.output = str(outp)
    summary.seconds = time.perf_counter() - t0
    return summary


def _shared_route_table(
    pdir: Path, map_s: str, delta: float, max_bytes: int | None, turn_cost: float
) -> Path:
    """The run's route table in the parts folder, built once for every worker (each maps the
    same file, so N workers hold one table's memory, not N); kept for a resumed run."""
    from graph.artifact import load_map
    from mapmatch.route_table import TABLE_FILE_VERSION, Ubodt

    st = os.stat(map_s)
    key = json.dumps(
        [os.path.abspath(map_s), st.st_mtime_ns, st.st_size, delta, max_bytes, turn_cost, TABLE_FILE_VERSION]
    )
    folder = pdir / f"{ROUTE_TABLE_PREFIX}{hashlib.sha256(key.encode()).hexdigest()[:16]}"
    for old in pdir.glob(ROUTE_TABLE_PREFIX + "*"):
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    if not (folder / "table.json").exists():
        Ubodt.build(load_map(map_s), delta, turn_cost=turn_cost, max_bytes=max_bytes).save(folder)
    return folder


def _prepare_parts_dir(pdir: Path, fingerprint: str, n: int) -> None:
    """Create the parts folder, or check that its parts belong to this same run (else start over)."""
    man = pdir / MANIFEST
    if pdir.is_dir() and man.exists():
        try:
            old = json.loads(man.read_text())
        except (OSError, ValueError):
            old = {}
        if old.get("fingerprint") == fingerprint and old.get("partitions") == n:
            return
        for f in pdir.glob("part-*.parquet"):
            f.unlink()
    elif pdir.is_dir() and any(pdir.glob("part-*.parquet")):
        raise RunError(f"{pdir} holds parts of an unknown run; remove them or choose another output")
    pdir.mkdir(parents=True, exist_ok=True)
    with atomic_path(man) as tmp:
        tmp.write_text(json.dumps({"fingerprint": fingerprint, "partitions": n}))


def _run_pool(
    workers: int | None,
    map_s: str,
    todo: list[Partition],
    files: list[Path],
    config: MatchConfig | None,
    columns: Columns,
    table: tuple[float | None, int | None, str | None],
) -> Iterable[tuple[int, int]]:
    import multiprocessing as mp

    n = workers or os.cpu_count() or 1
    ctx = mp.get_context("spawn")  # no fork of a process holding threads
    with ProcessPoolExecutor(max_workers=min(n, len(todo)), mp_context=ctx) as ex:
        futs: list[Future[tuple[int, int]]] = [
            ex.submit(match_partition, map_s, p, str(files[p.index]), config, columns, *table) for p in todo
        ]
        for f in as_completed(futs):
            yield f.result()


def _run_dask(
    scheduler: str | Any,
    map_s: str,
    todo: list[Partition],
    files: list[Path],
    config: MatchConfig | None,
    columns: Columns,
    table: tuple[float | None, int | None, str | None],
) -> Iterable[tuple[int, int]]:
    from distributed import Client
    from distributed import as_completed as dask_completed

    own = isinstance(scheduler, str)
    client: Any = Client(scheduler) if own else scheduler
    try:
        futs = [
            client.submit(
                match_partition,
                map_s,
                p,
                str(files[p.index]),
                config,
                columns,
                *table,
                key=f"mapmatch-part-{p.index}-{id(p)}",
            )
            for p in todo
        ]
        for f in dask_completed(futs):
            yield f.result()
    finally:
        if own:
            client.close()
