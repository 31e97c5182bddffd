"""The legal moves of a map: for each directed edge, the edges a vehicle may take next.

One table per map and U-turn policy, in CSR form (``ptr`` by edge into ``to``), built from the
graph's out-edges, its turn restrictions (``no_*`` and ``only_*``, at the restriction's via node)
and the policy for turning back:

``"junction"``
    the online matcher's rule: turning back is free at a dead end, costs the U-turn penalty at
    a junction (three or more roads), and is not a move at a node where a road just goes on.
``"never"``
    no move onto the edge's reverse twin (the simulator's legal drives).
``"dead_end"``
    the batch matcher's routes: the reverse twin is a move only at a dead end (no other edge
    leaves the node, whatever the turn restrictions), and then a free one; the out-edges keep
    the graph's order (the compiled searches' tie order).

A move *turns back* onto the edge's reverse twin or, on a one-way without a twin, onto an
edge that returns to the edge's start node with the same length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from graph.road_graph import RESTRICTION_ONLY, RoadGraph

UTurnPolicy = Literal["junction", "never", "dead_end"]


@dataclass(frozen=True)
class LegalMoves:
    """``to[ptr[e]:ptr[e + 1]]`` are the moves after edge ``e`` (straight-ahead ones first, but
    in the graph's order under ``"dead_end"``);
    ``uturn`` marks those that turn back and pay the U-turn penalty."""

    ptr: NDArray[np.int64]
    to: NDArray[np.int32]
    uturn: NDArray[np.bool_]
    policy: UTurnPolicy

    def after(self, e: int) -> list[int]:
        """The edges a vehicle may take after ``e``."""
        return self.to[self.ptr[e] : self.ptr[e + 1]].tolist()  # type: ignore[no-any-return]


def junctions(graph: RoadGraph) -> NDArray[np.bool_]:
    """Nodes where three or more roads meet (a two-way road counts once)."""
    rev = graph.edge_reverse
    road = (rev < 0) | (np.arange(graph.n_edges) < rev)
    deg = np.bincount(graph.edge_u[road], minlength=graph.n_nodes) + np.bincount(
        graph.edge_v[road], minlength=graph.n_nodes
    )
    return deg >= 3  # type: ignore[no-any-return]


def legal_moves(graph: RoadGraph, *, uturns: UTurnPolicy = "junction") -> LegalMoves:
    """The table of legal moves of ``graph`` under the U-turn policy ``uturns``."""
    if uturns not in ("junction", "never", "dead_end"):
        raise ValueError(f"unknown U-turn policy {uturns!r}")
    ev, eu, rev = graph.edge_v.tolist(), graph.edge_u.tolist(), graph.edge_reverse.tolist()
    elen = graph.edge_len.tolist()
    out_ptr, out = graph.out_ptr.tolist(), graph.out_edges
    branching = junctions(graph).tolist()
    restr: dict[int, list[tuple[int, int, int]]] = {}
    for fe, via, te, kind in graph.restrictions.tolist():
        restr.setdefault(int(fe), []).append((int(via), int(te), int(kind)))
    ptr = [0]
    to: list[int] = []
    flag: list[bool] = []
    for e in range(graph.n_edges):
        v = ev[e]
        outs: list[int] = out[out_ptr[v] : out_ptr[v + 1]].tolist()
        r, u = rev[e], eu[e]
        dead_end = all(o == r for o in outs)
        rules = restr.get(e)
        if rules:
            only = {te for via, te, kind in rules if via == v and kind == RESTRICTION_ONLY}
            banned = {te for via, te, kind in rules if via == v and kind != RESTRICTION_ONLY}
            if only:
                outs = [o for o in outs if o in only]
            outs = [o for o in outs if o not in banned]
        is_back = [o == r or (r < 0 and ev[o] == u and elen[o] == elen[e]) for o in outs]
        ahead = [o for o, b in zip(outs, is_back, strict=True) if not b]
        back = [o for o, b in zip(outs, is_back, strict=True) if b]
        if uturns == "never":
            moves = [(o, False) for o in outs if o != r]
        elif uturns == "dead_end":
            moves = [(o, False) for o in outs if o != r or dead_end]
        elif not ahead:
            moves = [(o, False) for o in back]
        elif branching[v]:
            moves = [(o, False) for o in ahead] + [(o, True) for o in back]
        else:
            moves = [(o, False) for o in ahead]
        to += [o for o, _ in moves]
        flag += [f for _, f in moves]
        ptr.append(len(to))
    return LegalMoves(
        ptr=np.asarray(ptr, dtype=np.int64),
        to=np.asarray(to, dtype=np.int32),
        uturn=np.asarray(flag, dtype=np.bool_),
        policy=uturns,
    )


_CACHE: dict[tuple[int, str], tuple[RoadGraph, LegalMoves]] = {}
_CACHE_SIZE = 8


def moves_for(graph: RoadGraph, *, uturns: UTurnPolicy = "junction") -> LegalMoves:
    """:func:`legal_moves`, built once per map and policy (the few most recent maps kept)."""
    key = (id(graph), uturns)
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is graph:
        return hit[1]
    moves = legal_moves(graph, uturns=uturns)
    if len(_CACHE) >= _CACHE_SIZE:
        del _CACHE[next(iter(_CACHE))]
    _CACHE[key] = (graph, moves)
    return moves
