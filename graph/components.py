"""Connected components of a RoadGraph from its arrays (no networkx)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graph.keys import dense_labels, isin, unique
from graph.road_graph import RoadGraph


def union_find(n: int, a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.int64]:
    """Component label (smallest member) of each of ``n`` items linked by pairs ``(a, b)``.

    Hook and compress: each round every link's larger root is hooked onto its smaller one,
    then every item is pointed at its root; the number of roots linked to others at least
    halves per round.
    """
    label = np.arange(n, dtype=np.int64)
    if len(a) == 0:
        return label
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    while True:
        la, lb = label[a], label[b]
        cross = la != lb
        if not cross.any():
            return label
        la, lb = la[cross], lb[cross]
        np.minimum.at(label, np.maximum(la, lb), np.minimum(la, lb))
        while True:  # point every item at its root
            up = label[label]
            if np.array_equal(up, label):
                break
            label = up
        keep = cross  # links inside one component stay so for good
        a, b = a[keep], b[keep]


def weak_components(graph: RoadGraph) -> NDArray[np.int64]:
    """Weakly connected component index ``0..C-1`` of every node, largest component first."""
    lab = union_find(graph.n_nodes, graph.edge_u.astype(np.int64), graph.edge_v.astype(np.int64))
    _, inv = dense_labels(lab, graph.n_nodes)
    counts = np.bincount(inv)
    rank = np.empty(len(counts), dtype=np.int64)
    rank[np.argsort(-counts, kind="stable")] = np.arange(len(counts))
    return rank[inv.ravel()]


def strong_component_count(graph: RoadGraph) -> int:
    """Number of strongly connected components of a RoadGraph."""
    return component_counts(graph.n_nodes, graph.edge_u, graph.edge_v)[1]


def component_counts(n: int, src: NDArray[np.integer], dst: NDArray[np.integer]) -> tuple[int, int]:
    """Numbers of weakly and strongly connected components of ``n`` nodes joined by directed
    edges ``src -> dst``.

    The strong ones: nodes joined by edges both ways are merged first (on a road map that is
    most of them), nodes left without an edge in or out are counted off as their own
    component, and Tarjan's algorithm runs on what remains.
    """
    if n == 0:
        return 0, 0
    a, b = np.asarray(src, dtype=np.int64), np.asarray(dst, dtype=np.int64)
    weak = len(dense_labels(union_find(n, a, b), n)[0])
    key = a * n + b
    two_way = isin(key, b * n + a)
    lab = union_find(n, a[two_way], b[two_way])
    uniq, inv = dense_labels(lab, n)
    del key, two_way, lab
    k = len(uniq)
    ca, cb = inv.ravel()[a], inv.ravel()[b]
    keep = ca != cb
    pair = unique(ca[keep] * k + cb[keep])
    ca, cb = pair // k, pair % k
    alive = np.ones(k, dtype=bool)
    while True:  # a node without an edge in or out (among the living) is a component alone
        live = alive[ca] & alive[cb]
        ca, cb = ca[live], cb[live]
        has = np.zeros(k, dtype=bool)
        has[ca] = True
        has_in = np.zeros(k, dtype=bool)
        has_in[cb] = True
        dead = alive & ~(has & has_in)
        if not dead.any():
            break
        alive &= ~dead
    rest = np.nonzero(alive)[0]
    strong = k - len(rest)
    if len(rest):
        index = np.full(k, -1, dtype=np.int64)
        index[rest] = np.arange(len(rest))
        strong += _tarjan_count(len(rest), index[ca], index[cb])
    return weak, strong


def _tarjan_count(n: int, src: NDArray[np.int64], dst: NDArray[np.int64]) -> int:
    """Number of strongly connected components (iterative Tarjan over a CSR)."""
    order = np.argsort(src, kind="stable")
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(src, minlength=n), out=ptr[1:])
    to = dst[order].tolist()
    start = ptr.tolist()
    index = [-1] * n
    low = [0] * n
    on = [False] * n
    stack: list[int] = []
    count = 0
    nxt = 0
    for root in range(n):
        if index[root] >= 0:
            continue
        work = [(root, start[root])]
        index[root] = low[root] = nxt
        nxt += 1
        stack.append(root)
        on[root] = True
        while work:
            x, i = work[-1]
            if i < start[x + 1]:
                work[-1] = (x, i + 1)
                y = to[i]
                if index[y] < 0:
                    index[y] = low[y] = nxt
                    nxt += 1
                    stack.append(y)
                    on[y] = True
                    work.append((y, start[y]))
                elif on[y] and index[y] < low[x]:
                    low[x] = index[y]
                continue
            work.pop()
            if work:
                p = work[-1][0]
                if low[x] < low[p]:
                    low[p] = low[x]
            if low[x] == index[x]:
                count += 1
                while True:
                    y = stack.pop()
                    on[y] = False
                    if y == x:
                        break
    return count
