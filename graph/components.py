"""Connected components of a RoadGraph from its arrays (no networkx)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graph.road_graph import RoadGraph


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
