"""The compiled match's answer in one array (:func:`pack`), and its one reading as a typed
record (:func:`decode`, a :class:`TrackResult`).

Each array a compiled call hands back to Python costs about a microsecond, ten of them a good
part of a small track's call, so the kernel returns one int64 array (any process can ship it as
it is). Its layout, in int64 words (the float part's words are float64 bits):

- header (:data:`HEADER` words): ``n`` points, ``ns`` splits, ``ne`` route edges, ``nseg``
  pieces, ``nxy`` route geometry points;
- integers: ``p_edge[n]``, ``status[n]``, ``splits[ns]``, ``route_e[ne]``,
  ``route_ptr[nseg + 1]``, ``rxy_ptr[nseg + 1]``;
- floats: ``p_off[n]``, ``p_xy[n, 2]``, ``p_dist[n]``, ``xy_all[nxy, 2]``, ``length``,
  ``confidence``.

Nothing else reads the array: readers take the :class:`TrackResult`'s fields.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit

Packed = NDArray[np.int64]
"""What the kernels return: the assembly packed by :func:`pack`."""

_I8 = NDArray[np.int64]
_F8 = NDArray[np.float64]
PointArrays = tuple[_I8, _I8, _F8, _F8, _F8]
"""Per point ``status, edge, offset, xy, dist``."""

HEADER = 5
"""Words before the integer part: ``n, ns, ne, nseg, nxy``."""


@njit(cache=True, nogil=True)
def pack(a):  # type: ignore[no-untyped-def]
    """The :class:`~mapmatch.batch.arrays.Assembly` ``a`` in one array, laid out as this
    module says."""
    n = len(a.p_edge)
    ns = len(a.splits)
    ne = len(a.route_e)
    nseg = len(a.route_ptr) - 1
    nxy = len(a.xy_all)
    ni = HEADER + 2 * n + ns + ne + 2 * (nseg + 1)
    out = np.empty(ni + 4 * n + 2 * nxy + 2, dtype=np.int64)
    ints = out[:ni]
    ints[0], ints[1], ints[2], ints[3], ints[4] = n, ns, ne, nseg, nxy
    ints[HEADER : HEADER + n] = a.p_edge
    for i in range(n):
        ints[HEADER + n + i] = a.status[i]
    k = HEADER + 2 * n
    for arr in (a.splits, a.route_e, a.route_ptr, a.rxy_ptr):
        ints[k : k + len(arr)] = arr
        k += len(arr)
    floats = out[ni:].view(np.float64)
    floats[:n] = a.p_off
    for i in range(n):
        floats[n + 2 * i] = a.p_xy[i, 0]
        floats[n + 2 * i + 1] = a.p_xy[i, 1]
    floats[3 * n : 4 * n] = a.p_dist
    for i in range(nxy):
        floats[4 * n + 2 * i] = a.xy_all[i, 0]
        floats[4 * n + 2 * i + 1] = a.xy_all[i, 1]
    floats[4 * n + 2 * nxy] = a.length
    floats[4 * n + 2 * nxy + 1] = a.conf
    return out


class TrackResult(NamedTuple):
    """One track's compiled answer (:func:`decode`), read by name: the counts of the header, and
    every part of the answer as a property, a view into ``packed`` made where it is read (a
    call whose answer is not read pays for none of them)."""

    packed: Packed
    n: int
    """Input points."""
    n_splits: int
    n_route_edges: int
    n_pieces: int
    """Connected pieces of the route."""
    n_route_xy: int
    """Points of the route's geometry."""

    def _at(self) -> tuple[int, int, int, int, int]:
        """Where the splits, the route edges, the route pointers, the geometry pointers and the
        float part start."""
        k = HEADER + 2 * self.n
        e = k + self.n_splits
        r = e + self.n_route_edges
        x = r + self.n_pieces + 1
        return k, e, r, x, x + self.n_pieces + 1

    @property
    def point_edge(self) -> _I8:
        """Per input point, the matched edge (-1: none)."""
        return self.packed[HEADER : HEADER + self.n]

    @property
    def status(self) -> _I8:
        """Per input point: 0 unmatched, 1 matched, 2 interpolated."""
        return self.packed[HEADER + self.n : HEADER + 2 * self.n]

    @property
    def splits(self) -> _I8:
        """The input points where a new piece of the route starts."""
        k, e, _, _, _ = self._at()
        return self.packed[k:e]

    @property
    def route_edges(self) -> _I8:
        """Every piece's edges, piece ``s`` being ``route_edges[route_ptr[s]:route_ptr[s + 1]]``."""
        _, e, r, _, _ = self._at()
        return self.packed[e:r]

    @property
    def route_ptr(self) -> _I8:
        _, _, r, x, _ = self._at()
        return self.packed[r:x]

    @property
    def route_xy_ptr(self) -> _I8:
        """Piece ``s``'s geometry is ``route_xy[route_xy_ptr[s]:route_xy_ptr[s + 1]]``."""
        _, _, _, x, ni = self._at()
        return self.packed[x:ni]

    @property
    def _floats(self) -> tuple[_F8, int]:
        """The array as float64, and where its float part starts."""
        return self.packed.view(np.float64), self._at()[4]

    @property
    def point_offset(self) -> _F8:
        """Per input point, metres along its edge."""
        floats, ni = self._floats
        return floats[ni : ni + self.n]

    @property
    def point_xy(self) -> _F8:
        """(n, 2): per input point, its place on the road in the map's CRS."""
        floats, ni = self._floats
        return floats[ni + self.n : ni + 3 * self.n].reshape(self.n, 2)

    @property
    def point_dist(self) -> _F8:
        """Per input point, metres from the fix to its place."""
        floats, ni = self._floats
        return floats[ni + 3 * self.n : ni + 4 * self.n]

    @property
    def route_xy(self) -> _F8:
        """(n_route_xy, 2): every piece's geometry in the map's CRS."""
        floats, ni = self._floats
        f = ni + 4 * self.n
        return floats[f : f + 2 * self.n_route_xy].reshape(self.n_route_xy, 2)

    @property
    def length(self) -> float:
        """Metres of route."""
        return float(self.packed.view(np.float64)[-2])

    @property
    def confidence(self) -> float:
        return float(self.packed.view(np.float64)[-1])

    @property
    def placed(self) -> int:
        """How many points have a place on the road."""
        return int(np.count_nonzero(self.point_edge >= 0))

    def routes(self) -> list[list[int]]:
        """Each piece's edges."""
        return self.unpacked()[0]

    def pieces_xy(self) -> list[_F8]:
        """Each piece's geometry (a piece of one point twice: a line has two)."""
        return self.unpacked()[4]

    def unpacked(self) -> tuple[list[list[int]], list[int], float, float, list[_F8], PointArrays]:
        """Every part at once, in one pass, as :class:`~mapmatch.types.TrackMatch` holds them:
        each piece's edges, the splits, the length, the confidence, each piece's geometry (a
        piece of one point twice: a line has two), and :meth:`point_arrays`."""
        n, nseg, nxy = self.n, self.n_pieces, self.n_route_xy
        k, e, r, _, ni = self._at()
        packed = self.packed
        rest = packed[k:ni].tolist()  # splits, route edges, their pointers, the geometry's pointers
        floats = packed.view(np.float64)
        f = ni + 4 * n
        routes = []
        pieces = []
        if nseg:
            edges = rest[e - k : r - k]
            ptr = rest[r - k :]
            xy_all = floats[f : f + 2 * nxy].reshape(nxy, 2)
            for s in range(nseg):
                routes.append(edges[ptr[s] : ptr[s + 1]])
                seg = xy_all[ptr[nseg + 1 + s] : ptr[nseg + 2 + s]]
                pieces.append(np.vstack([seg, seg]) if len(seg) == 1 else seg)
        length, confidence = floats[f + 2 * nxy :].tolist()
        pa = (
            packed[HEADER + n : k],
            packed[HEADER : HEADER + n],
            floats[ni : ni + n],
            floats[ni + n : ni + 3 * n].reshape(n, 2),
            floats[ni + 3 * n : f],
        )
        return routes, rest[: e - k], length, confidence, pieces, pa

    def point_arrays(self) -> PointArrays:
        """Per point ``status, edge, offset, xy, dist``, as
        :attr:`~mapmatch.types.TrackMatch.point_arrays` holds them."""
        return self.status, self.point_edge, self.point_offset, self.point_xy, self.point_dist


def decode(packed: Packed) -> TrackResult:
    """The :class:`TrackResult` of a :func:`pack`\\ ed array (its header read; no copy)."""
    return _new(TrackResult, (packed, *packed[:HEADER].tolist()))


_new = tuple.__new__
"""A named tuple made from its values without :class:`TrackResult`'s keyword handling (a
fraction of a microsecond of every call)."""
