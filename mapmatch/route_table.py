"""FMM-style route tables (UBODT): every route up to a bound, precomputed once per map.

A :class:`Ubodt` lists, for every edge, the edges reachable within ``delta`` metres with their
distances, so a route query within the bound is a look-up (a binary search over the row's
block heads, then over one block) instead of a search (:mod:`mapmatch.routing`); routes beyond
it are searched. Its size is estimated from a sample of rows (:func:`ubodt_estimate`) before
it is built, and a memory budget lowers the bound where the table would not fit
(:meth:`Ubodt.build`). The kernels read a table as a :class:`mapmatch.routing.RouteTable`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from graph.road_graph import RoadGraph
from mapmatch.arena import int64
from mapmatch.config import BATCH_CONFIG
from mapmatch.routing import INF, TABLE_BLOCK, RouteGraph, RouteTable, Workspace, _reset, _search, route_graph

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Ubodt:
    """Upper-bounded origin-destination table (FMM's UBODT, edge-based).

    For every edge ``e``, the edges ``f`` whose start is within ``delta`` metres (turn costs
    counted, as in the searches) of the end of
    ``e`` (turn rules applied), sorted by ``f``: ``tgt[ptr[e]:ptr[e+1]]`` with the distances in
    ``dist`` and the place in the same row of the edge before ``f`` on the route in
    ``pred_pos`` (-1 for a neighbour of ``e``), so a route is read back hop by hop without
    searching (that edge is ``tgt[ptr[e] + pred_pos[k]]``). A route query within the bound is
    then a look-up in the row (:func:`_row_place`) instead of a search.
    """

    delta: float
    ptr: NDArray[np.int64]
    tgt: NDArray[np.int32]
    dist: NDArray[np.float64]
    pred_pos: NDArray[np.int32]
    turn_cost: float = 0.0
    """The turn cost its routes were found with (:func:`~mapmatch.routing.route_graph`); a matcher uses the
    table only for a config with the same ``turn_cost``."""

    @classmethod
    def build(
        cls,
        graph: RoadGraph,
        delta: float,
        *,
        turn_cost: float | None = None,
        max_bytes: int | None = None,
    ) -> Ubodt:
        """Precompute the table for ``delta`` metres (time and memory grow fast with it), routes
        costing ``turn_cost`` metres per turn back (:func:`mapmatch.routing.turn_costs`; by default the batch
        matcher's, ``BATCH_CONFIG.batch.route.turn_cost``).

        With ``max_bytes``, the bound is first lowered until the table's estimated size
        (:func:`ubodt_estimate`) fits: a dense map then gets a shorter table, not an
        out-of-memory error. The matches stay the same, as routes beyond a table's bound are
        searched; the table's ``delta`` is the bound it was built for.
        """
        if not (math.isfinite(delta) and delta > 0):
            raise ValueError(f"delta must be a positive number of metres, got {delta!r}")
        if max_bytes is not None and not max_bytes > 0:
            raise ValueError(f"max_bytes must be a positive number of bytes, got {max_bytes!r}")
        if turn_cost is None:
            turn_cost = float(BATCH_CONFIG.batch.route.turn_cost)
        ws = Workspace.new(graph.n_edges)
        rg = route_graph(graph, turn_cost=turn_cost)
        asked = float(delta)
        delta, entries = _fit_delta(asked, max_bytes, graph.n_edges, rg, ws)
        if delta < asked:
            log.warning(
                "route table: %.0f m would not fit in %.3g MB; built for %.0f m instead "
                "(the same matches; routes beyond it are searched)",
                asked, (max_bytes or 0) / 2**20, delta,
            )  # fmt: skip
        cap = int(entries * ESTIMATE_HEADROOM) + 16  # no doubling, no copy: a lower peak
        ptr, tgt, dist, pos = _build_ubodt(delta, graph.n_edges, rg, ws, cap)
        return cls(delta, ptr, tgt, dist, pos, float(turn_cost))

    def save(self, folder: str | os.PathLike[str]) -> None:
        """Write the table to ``folder`` (created; one ``.npy`` file per array and ``table.json``),
        to be mapped by :meth:`load`. Written under a temporary name and renamed: a reader sees
        the whole table or none."""
        dest = Path(folder)
        tmp = dest.with_name(dest.name + f".tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            for name in _ARRAYS:
                np.save(tmp / f"{name}.npy", getattr(self, name))
            meta = {"version": TABLE_FILE_VERSION, "delta": self.delta, "turn_cost": self.turn_cost}
            (tmp / "table.json").write_text(json.dumps(meta))
            shutil.rmtree(dest, ignore_errors=True)
            os.replace(tmp, dest)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    @classmethod
    def load(cls, folder: str | os.PathLike[str]) -> Ubodt:
        """A table written by :meth:`save`, its arrays mapped from the files (copy on write,
        never written): processes that load one table share its pages."""
        src = Path(folder)
        meta = json.loads((src / "table.json").read_text())
        if meta.get("version") != TABLE_FILE_VERSION:
            raise ValueError(f"{src}: route table version {meta.get('version')!r}, not {TABLE_FILE_VERSION}")
        # plain ndarray views of the mappings (a np.memmap costs time per scalar read in Python)
        arrays = {name: np.load(src / f"{name}.npy", mmap_mode="c").view(np.ndarray) for name in _ARRAYS}
        return cls(float(meta["delta"]), turn_cost=float(meta["turn_cost"]), **arrays)

    @property
    def table(self) -> RouteTable:
        """The arrays as the compiled kernels read them."""
        return RouteTable(self.delta, self.ptr, self.tgt, self._head, self.dist, self.pred_pos)

    @cached_property
    def _head(self) -> NDArray[np.int32]:
        """Every :data:`~mapmatch.routing.TABLE_BLOCK`-th target (``RouteTable.head``), kept in
        memory (a saved table is read, not copied: its arrays stay mapped)."""
        return np.ascontiguousarray(self.tgt[::TABLE_BLOCK])

    @property
    def nbytes(self) -> int:
        return int(
            self.ptr.nbytes
            + self.tgt.nbytes
            + self.dist.nbytes
            + self.pred_pos.nbytes
            + 4 * -(-len(self.tgt) // TABLE_BLOCK)
        )


_ARRAYS = ("ptr", "tgt", "dist", "pred_pos")

TABLE_FILE_VERSION = 2
"""Version of :meth:`Ubodt.save`'s folder layout (1 also held each entry's predecessor edge,
which ``pred_pos`` gives)."""

UBODT_ENTRY_BYTES = 4 + 8 + 4 + 4 / TABLE_BLOCK
"""Bytes per entry of a :class:`Ubodt` (``tgt``, ``dist``, ``pred_pos``, and the block heads
its look-ups read first); each edge adds 8 (``ptr``)."""

ESTIMATE_SAMPLE = 512
"""Rows searched to estimate a table's size (edges evenly spaced in the map's spatial order)."""

FIT_STEPS = 6
"""Bisection steps of a bound lowered to fit a memory budget (within 1/64 of the last halving)."""

ESTIMATE_HEADROOM = 1.15
"""The build's first allocation over the estimated entries (it grows if the estimate was low)."""


def ubodt_estimate(graph: RoadGraph, delta: float, *, turn_cost: float | None = None) -> int:
    """The estimated size in bytes of ``Ubodt.build(graph, delta, turn_cost=turn_cost)``, from
    the rows of :data:`ESTIMATE_SAMPLE` edges evenly spaced through the map's edges (a map
    prepared by :func:`graph.build.build_map` stores them in spatial order, so the
    sample spreads over the map)."""
    if turn_cost is None:
        turn_cost = float(BATCH_CONFIG.batch.route.turn_cost)
    rg = route_graph(graph, turn_cost=turn_cost)
    entries = _estimate_entries(float(delta), graph.n_edges, rg, Workspace.new(graph.n_edges))
    return _table_bytes(entries, graph.n_edges)


def _table_bytes(entries: float, n_edges: int) -> int:
    return int(entries * UBODT_ENTRY_BYTES + 8 * (n_edges + 1))


def _estimate_entries(delta: float, n_edges: int, g: RouteGraph, ws: Workspace) -> float:
    if n_edges == 0:
        return 0.0
    sample = np.unique(np.linspace(0, n_edges - 1, min(n_edges, ESTIMATE_SAMPLE)).astype(np.int64))
    rows = _row_lengths(delta, sample, g, ws)
    return float(rows.mean()) * n_edges


def _fit_delta(
    delta: float, max_bytes: int | None, n_edges: int, g: RouteGraph, ws: Workspace
) -> tuple[float, float]:
    """The largest bound up to ``delta`` whose estimated table fits ``max_bytes`` (``None``:
    ``delta``), to within :data:`FIT_STEPS` halvings of the last step, and its estimated
    entries."""
    entries = _estimate_entries(delta, n_edges, g, ws)
    if max_bytes is None or _table_bytes(entries, n_edges) <= max_bytes:
        return delta, entries
    hi = lo = delta
    while lo >= 1.0:  # halve until it fits
        hi, lo = lo, lo / 2
        entries = _estimate_entries(lo, n_edges, g, ws)
        if _table_bytes(entries, n_edges) <= max_bytes:
            break
    for _ in range(FIT_STEPS):  # then bisect between the bounds that fit and that do not
        mid = (lo + hi) / 2
        e = _estimate_entries(mid, n_edges, g, ws)
        if _table_bytes(e, n_edges) <= max_bytes:
            lo, entries = mid, e
        else:
            hi = mid
    return lo, entries


@njit(cache=True, nogil=True)
def _row_lengths(delta, edges, g, ws):  # type: ignore[no-untyped-def]
    """The number of entries of each of ``edges``'s table rows (as :func:`_build_ubodt` fills them)."""
    out = np.zeros(len(edges), dtype=np.int64)
    for k in range(len(edges)):
        nt = _search(edges[k], 0.0, delta, int64(-1), g, ws)  # -1: no targets
        for i in range(nt):
            f = ws.touched[i]
            if ws.done[f] and ws.dist[f] <= delta:
                out[k] += 1
        _reset(nt, ws)
    return out


@njit(cache=True, nogil=True)
def _build_ubodt(  # type: ignore[no-untyped-def]
    delta,
    n_edges,
    g,
    ws,
    cap,
):
    """The table's rows, one search each: ``(ptr, tgt, dist, pred_pos)``, each row sorted by
    target, then each entry's predecessor edge found as a place in its row (three arrays of
    ``cap`` entries, grown where the estimate was low)."""
    dist, pred, done, touched = ws.dist, ws.pred, ws.done, ws.touched
    ptr = np.zeros(n_edges + 1, dtype=np.int64)
    out_t = np.empty(cap, dtype=np.int32)
    out_d = np.empty(cap)
    out_q = np.empty(cap, dtype=np.int32)
    m = 0
    for e in range(n_edges):
        nt = _search(e, 0.0, delta, int64(-1), g, ws)
        if m + nt > cap:
            cap = 2 * (m + nt)
            t2 = np.empty(cap, dtype=np.int32)
            t2[:m] = out_t[:m]
            d2 = np.empty(cap)
            d2[:m] = out_d[:m]
            q2 = np.empty(cap, dtype=np.int32)
            q2[:m] = out_q[:m]
            out_t, out_d, out_q = t2, d2, q2
        start = m
        for i in range(nt):
            f = touched[i]
            if done[f] and dist[f] <= delta:
                out_t[m] = f
                out_d[m] = dist[f]
                out_q[m] = pred[f]  # the predecessor edge, until its place is known
                m += 1
        order = np.argsort(out_t[start:m])
        st = out_t[start:m][order].copy()
        sd = out_d[start:m][order].copy()
        sp = out_q[start:m][order].copy()
        out_t[start:m] = st
        out_d[start:m] = sd
        # each entry's predecessor as a place in its row (-1: the row's own edge)
        for k in range(m - start):
            out_q[start + k] = -1
            p = sp[k]
            if p != e:
                q = np.searchsorted(st, p)
                if q < m - start and st[q] == p:
                    out_q[start + k] = q
        ptr[e + 1] = m
        _reset(nt, ws)
    if 4 * cap <= 5 * m:  # within a quarter of the size: keep the arrays rather than copy them
        return ptr, out_t[:m], out_d[:m], out_q[:m]
    return ptr, out_t[:m].copy(), out_d[:m].copy(), out_q[:m].copy()


@njit(cache=True, nogil=True, inline="always")
def _row_place(table, e: int, f: int) -> int:  # type: ignore[no-untyped-def]
    """The place of ``f`` in the table's row of ``e``, -1 when not in it: a binary search over
    the row's block heads (``table.head``), then over one block."""
    ptr, tgt, head = table.ptr, table.tgt, table.head
    a = ptr[e]
    b = ptr[e + 1]
    if a >= b:
        return -1
    # the blocks that start inside the row after its first entry: ka .. kb - 1
    ka = a // TABLE_BLOCK + 1
    kb = (b - 1) // TABLE_BLOCK + 1
    lo = ka
    hi = kb
    while lo < hi:  # the first of them whose head is beyond f
        mid = (lo + hi) >> 1
        if head[mid] <= f:
            lo = mid + 1
        else:
            hi = mid
    # f can only be in the block before it (or the row's first part)
    if lo == ka:
        lo = a
        hi = min(b, ka * TABLE_BLOCK)
    else:
        hi = min(b, lo * TABLE_BLOCK)
        lo = (lo - 1) * TABLE_BLOCK
    while lo < hi:
        mid = (lo + hi) >> 1
        if tgt[mid] < f:
            lo = mid + 1
        else:
            hi = mid
    if lo < b and tgt[lo] == f:
        return lo
    return -1


@njit(cache=True, nogil=True, inline="always")
def ubodt_lookup(table, e: int, f: int) -> float:  # type: ignore[no-untyped-def]
    """Distance (with turn costs) from the end of ``e`` to the start of ``f`` if within the table,
    else inf."""
    k = _row_place(table, e, f)
    return table.dist[k] if k >= 0 else INF


@njit(cache=True, nogil=True, inline="always")
def path_place(table, src: int, dst: int):  # type: ignore[no-untyped-def]
    """The place of ``dst`` in the table's row of ``src`` and the number of edges strictly
    between them on its path: ``(place, count)``, ``(-1, -1)`` when not in the table."""
    lo = _row_place(table, src, dst)
    if lo < 0:
        return -1, -1
    pos = table.pred_pos
    a = table.ptr[src]
    m = 0
    k = pos[lo]
    while k >= 0:
        m += 1
        k = pos[a + k]
    return lo, m


@njit(cache=True, nogil=True, inline="always")
def path_into(table, src: int, place: int, m: int, out, n: int) -> None:  # type: ignore[no-untyped-def]
    """The ``m`` edges of the path to ``place`` in the row of ``src`` (:func:`path_place`),
    written to ``out[n : n + m]`` in driving order."""
    pos, tgt = table.pred_pos, table.tgt
    a = table.ptr[src]
    k = pos[place]
    while k >= 0:
        m -= 1
        out[n + m] = tgt[a + k]
        k = pos[a + k]
