"""Connected components of a RoadGraph from its arrays (no networkx)."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch.graph.road_graph import RoadGraph


def union_find(n: int, a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.int64]:
    """Component label (smallest member) of each of ``n`` items linked by pairs ``(a, b)``."""
    label = np.arange(n, dtype=np.int64)
    if len(a) == 0:
        return label
    while True:
        m = np.minimum(label[a], label[b])
        new = label.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        if np.array_equal(new, label):
            return label
        label = new


def weak_components(graph: RoadGraph) -> NDArray[np.int64]:
    """Weakly connected component index ``0..C-1`` of every node, largest component first."""
    lab = union_find(graph.n_nodes, graph.edge_u.astype(np.int64), graph.edge_v.astype(np.int64))
    _, inv, counts = np.unique(lab, return_inverse=True, return_counts=True)
    rank = np.empty(len(counts), dtype=np.int64)
    rank[np.argsort(-counts, kind="stable")] = np.arange(len(counts))
    return rank[inv.ravel()]


def strong_component_count(graph: RoadGraph) -> int:
    """Number of strongly connected components of a RoadGraph."""
    return component_counts(graph.n_nodes, graph.edge_u, graph.edge_v)[1]


def component_counts(n: int, src: NDArray[np.integer], dst: NDArray[np.integer]) -> tuple[int, int]:
    """Numbers of weakly and strongly connected components of ``n`` nodes joined by directed
    edges ``src -> dst`` (an iterative Kosaraju for the strong ones)."""
    if n == 0:
        return 0, 0
    a, b = np.asarray(src, dtype=np.int64), np.asarray(dst, dtype=np.int64)
    weak = len(np.unique(union_find(n, a, b)))
    o_order = np.argsort(a, kind="stable")
    i_order = np.argsort(b, kind="stable")
    o_ptr = np.zeros(n + 1, dtype=np.int64)
    i_ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(a, minlength=n), out=o_ptr[1:])
    np.cumsum(np.bincount(b, minlength=n), out=i_ptr[1:])
    from mapmatch.kernels import for_size

    kosaraju = for_size(_kosaraju, n + len(a))
    return weak, int(kosaraju(n, o_ptr, b[o_order], i_ptr, a[i_order]))


@njit(cache=True)
def _kosaraju(n, out_ptr, out_to, in_ptr, in_from):  # type: ignore[no-untyped-def]
    seen = np.zeros(n, dtype=np.bool_)
    finish = np.empty(n, dtype=np.int64)
    nf = 0
    stack = np.empty(n, dtype=np.int64)
    pos = np.empty(n, dtype=np.int64)
    for s in range(n):
        if seen[s]:
            continue
        top = 0
        stack[0] = s
        pos[0] = out_ptr[s]
        seen[s] = True
        while top >= 0:
            x = stack[top]
            if pos[top] < out_ptr[x + 1]:
                y = out_to[pos[top]]
                pos[top] += 1
                if not seen[y]:
                    seen[y] = True
                    top += 1
                    stack[top] = y
                    pos[top] = out_ptr[y]
            else:
                finish[nf] = x
                nf += 1
                top -= 1
    comp = np.full(n, -1, dtype=np.int64)
    c = 0
    for i in range(n - 1, -1, -1):
        s = finish[i]
        if comp[s] >= 0:
            continue
        top = 0
        stack[0] = s
        comp[s] = c
        while top >= 0:
            x = stack[top]
            top -= 1
            for k in range(in_ptr[x], in_ptr[x + 1]):
                y = in_from[k]
                if comp[y] < 0:
                    comp[y] = c
                    top += 1
                    stack[top] = y
        c += 1
    return c
