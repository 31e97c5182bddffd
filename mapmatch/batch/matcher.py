"""The batch matcher: the fixes projected to the map's CRS, then one compiled call per track.

The call (:func:`mapmatch.batch.run.run_track_in`) does every step: validity and thinning, the
batch rules on the fixes (jumps, the direction of travel), the grid candidate search,
emissions and transitions of the shared :mod:`mapmatch.model` (its scalar functions,
compiled), route distances from bounded edge-based search or the route table
(:mod:`mapmatch.routing`), lattice (:mod:`~mapmatch.batch.lattice`), Viterbi
(:mod:`~mapmatch.batch.viterbi`) and route assembly (:mod:`~mapmatch.batch.route`).
The answers' reference is the digests of ``bench/hash_batch.py``, the peers' cases and the
ASCII-map tests.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer
from pyproj.enums import TransformDirection

from graph.index import EdgeIndex
from graph.jit import read_only
from graph.road_graph import RoadGraph
from mapmatch import model
from mapmatch.arena import Arena
from mapmatch.batch.arrays import EdgeGeometry, KernelParams, kernel_params
from mapmatch.batch.context import Context, new_context
from mapmatch.batch.lattice import (
    along_lengths,
    segment_bearings,
    segment_lengths,
)
from mapmatch.batch.packed import Packed, TrackResult, decode
from mapmatch.batch.results import fill_route_lonlat, track_match
from mapmatch.batch.run import (
    CompiledRun,
    MatchInputs,
    QueryParams,
    RoadArrays,
    RuleParams,
    TrackInput,
    fresh,
    run_track_in,
)
from mapmatch.config import BATCH_CONFIG, MatchConfig
from mapmatch.gridindex import GridIndex, GridScratch
from mapmatch.route_table import Ubodt
from mapmatch.routing import NO_TABLE, RouteGraph, Router, RouteTable, Workspace, route_graph
from mapmatch.types import Track, TrackMatch

F8, I8 = np.float64, np.int64
NO_ODO = np.zeros(0)
"""The odometer readings of a track without them (read-only use)."""
NO_COLUMN = np.zeros(0)
"""An optional per-fix column the track does not have (read-only use)."""
ARENA_ITEMS = 1 << 14
"""Items per buffer of a thread's first arena (grown as tracks need)."""


class _ThreadState(NamedTuple):
    """One thread's scratch for one matcher: the route workspace, the grid marks, the kernels'
    arena, the transformer to the map's CRS (pyproj transformers are not shared across
    threads) and the compiled call's contexts by config."""

    router: Router
    grid: GridScratch
    arena: Arena
    """Grown after a call that needed more (:meth:`mapmatch.arena.Arena.grown`)."""
    to_map: Callable[[NDArray[np.float64]], None]
    """Projects rows 2 and 3 (lon, lat) of a (4, n) buffer to the map's CRS in place
    (:func:`_projector`)."""
    contexts: dict[tuple[int, bool], tuple[MatchConfig, Context]]
    """By ``id`` of the config: the config and its :class:`~mapmatch.batch.context.Context`
    with this thread's scratch (the arena's growth starts a new dict)."""


class _Settings(NamedTuple):
    """What a config turns into for the kernels (built once per config object)."""

    config: MatchConfig
    params: KernelParams
    query: QueryParams
    sigma: float
    track_rules: RuleParams


class BatchMatcher:
    """Matches whole tracks against one road graph (read-only, reusable, thread-safe).

    Parameters
    ----------
    graph
        The road graph.
    index
        Its spatial index; built when omitted.
    config
        Default parameters (:data:`BATCH_CONFIG` when omitted); :meth:`match` takes a per-call
        override.
    ubodt
        Optional precomputed route table (:class:`mapmatch.route_table.Ubodt`); routes within its
        bound are looked up instead of searched, for configs with the ``turn_cost`` it was built
        with. Without it every route is a bounded search.
    """

    def __init__(
        self,
        graph: RoadGraph,
        index: EdgeIndex | None = None,
        config: MatchConfig | None = None,
        *,
        ubodt: Ubodt | None = None,
    ) -> None:
        self.graph = graph
        self.ubodt = ubodt
        self._table = ubodt.table if ubodt is not None else NO_TABLE
        self.index = index or EdgeIndex(graph)
        self.config = config or BATCH_CONFIG
        self._grid = GridIndex(self.index, cell=self.config.model.search_radius)
        self._rg = route_graph(graph, uturns="dead_end", turn_cost=self.config.batch.route.turn_cost)
        self._rg_by_cost: dict[float, RouteGraph] = {float(self.config.batch.route.turn_cost): self._rg}
        seg_xy = read_only(graph.seg_xy, F8)
        seg_ptr = read_only(graph.edge_seg_ptr, I8)
        self._geom = EdgeGeometry(seg_xy, seg_ptr, read_only(segment_lengths(seg_xy, seg_ptr), F8))
        self._seg_end = read_only(along_lengths(seg_xy, seg_ptr), F8)
        self._roads = RoadArrays(self._seg_end, read_only(segment_bearings(seg_xy, seg_ptr), F8))
        self._run_track = CompiledRun(run_track_in)
        self._local = threading.local()
        self._settings: dict[tuple[int, bool], _Settings] = {}
        self._joining_cfg: dict[int, tuple[MatchConfig, MatchConfig]] = {}

    def _state(self) -> _ThreadState:
        """This thread's scratch (built once per thread, so one matcher serves many threads)."""
        st: _ThreadState | None = getattr(self._local, "state", None)
        if st is None:
            router = Router(self._rg, Workspace.new(self.graph.n_edges), self._table_for(self.config))
            to_map = _projector(Transformer.from_crs("EPSG:4326", self.graph.crs, always_xy=True))
            st = self._local.state = _ThreadState(
                router, self._grid.scratch(), Arena.new(ARENA_ITEMS), to_map, {}
            )
        return st

    def _table_for(self, cfg: MatchConfig) -> RouteTable:
        """The route table if it was built with ``cfg``'s turn cost, else none (every route searched)."""
        if self.ubodt is not None and self.ubodt.turn_cost == cfg.batch.route.turn_cost:
            return self._table
        return NO_TABLE

    def _router_for(self, st: _ThreadState, cfg: MatchConfig) -> Router:
        """This thread's router for ``cfg``'s turn cost (the moves' costs are the graph's)."""
        rg = self._rg_by_cost.get(float(cfg.batch.route.turn_cost))
        if rg is None:
            if len(self._rg_by_cost) >= 8:
                self._rg_by_cost = {float(self.config.batch.route.turn_cost): self._rg}
            rg = self._rg_by_cost[float(cfg.batch.route.turn_cost)] = route_graph(
                self.graph, uturns="dead_end", turn_cost=cfg.batch.route.turn_cost
            )
        if rg is st.router.g:
            return st.router
        return Router(rg, st.router.ws, self._table_for(cfg))

    def _settings_for(self, cfg: MatchConfig, joining: bool = False) -> _Settings:
        """The kernels' parameters of ``cfg`` (a config is immutable: cached by identity); with
        ``joining``, without the detour limit (:meth:`_joining`)."""
        st = self._settings.get((id(cfg), joining))
        if st is None or st.config is not cfg:
            sigma = float(model.position_sigma(np.nan, cfg))
            query = QueryParams(
                radius=float(cfg.model.search_radius), outlier=float(cfg.batch.outliers.outlier_distance),
                k=int(cfg.model.max_candidates), min_dist=sigma,  # fixes within one σ tell nothing new
            )  # fmt: skip
            track_rules = RuleParams(
                gps_sigma=sigma, spike_sigmas=float(cfg.batch.outliers.off_map_sigmas),  # one limit in σ
                spike_speed=float(cfg.batch.outliers.spike_speed),
                spike_max_time=float(cfg.batch.outliers.spike_max_time),
                motion_sigma=float(cfg.model.straight_max_deg),  # legs turning by that much
                motion_min_distance=sigma,  # a leg of one σ tells the direction
                motion_end_leg_max=float(cfg.batch.track.motion_end_leg_max),
                straight_max_deg=float(cfg.model.straight_max_deg),
                heading_sigma=float(cfg.model.heading_sigma),
                heading_min_speed=float(cfg.model.heading_min_speed),
                track_sigma_max=float(cfg.batch.track.track_sigma_max),
                sigma_min_fixes=int(cfg.batch.track.track_sigma_min_fixes),
                thin_sigmas=float(cfg.batch.track.thin_sigmas),
                pos_sigma_floor=float(cfg.batch.track.track_pos_sigma_floor),
                heading_sigma_floor=float(cfg.batch.track.track_heading_sigma_floor_deg),
            )  # fmt: skip
            params = kernel_params(cfg, sigma)
            if joining:
                params = params._replace(detour_cost_max=0.0)
            st = _Settings(cfg, params, query, sigma, track_rules)
            if len(self._settings) >= 64:
                self._settings.clear()
            self._settings[(id(cfg), joining)] = st
        return st

    def match(self, track: Track, config: MatchConfig | None = None, *, lonlat: bool = True) -> TrackMatch:
        """Match one track; bad points become unmatched, never an exception for the track.

        With ``lonlat=False`` the route geometry is left in the map's CRS (``route_xy``) and the
        per-point results in arrays (``point_arrays``); :func:`fill_route_lonlat` later fills
        ``route_lonlat`` and ``points`` from them.
        """
        cfg = config or self.config
        res = self._match_compiled(track, cfg)
        if lonlat:
            fill_route_lonlat(res, self.graph.crs)
        return res

    def _context(self, st: _ThreadState, cfg: MatchConfig, joining: bool = False) -> Context:
        """This thread's :class:`~mapmatch.batch.context.Context` for ``cfg`` (built once); with
        ``joining``, without the detour limit."""
        got = st.contexts.get((id(cfg), joining))
        if got is not None and got[0] is cfg:
            return got[1]
        s = self._settings_for(cfg, joining)
        ctx = new_context(
            MatchInputs(
                s.query, s.track_rules, s.params, self._geom, self._roads, self._router_for(st, cfg),
                self._grid.arrays, st.grid, st.arena,
            )
        )  # fmt: skip
        if len(st.contexts) >= 64:
            st.contexts.clear()
        st.contexts[(id(cfg), joining)] = (cfg, ctx)
        return ctx

    def _match_compiled(self, track: Track, cfg: MatchConfig) -> TrackMatch:
        """The projection, then one compiled call (:func:`run_track_in`)."""
        st = self._state()
        lat, lon = track.lat, track.lon
        if not isinstance(lat, np.ndarray) or not isinstance(lon, np.ndarray):
            lat, lon = np.asarray(lat, dtype=F8), np.asarray(lon, dtype=F8)
        if lat.ndim != 1 or lon.shape != lat.shape:
            raise ValueError(f"the track's lat and lon have shapes {lat.shape} and {lon.shape}, not one (n,)")
        n = len(lat)
        pos = np.array((lon, lat, lon, lat), dtype=F8)
        st.to_map(pos)
        ti = TrackInput(
            pos, _column(track.time, n, "time", np.nan),
            NO_ODO if track.distance is None else _odometer(_column(track.distance, n, "distance")),
            _column(track.pos_sigma, n, "pos_sigma"), _column(track.heading, n, "heading"),
            _column(track.speed, n, "speed"),
        )  # fmt: skip
        res = decode(self._call(ti, cfg, st))
        if n > 1 and res.length == 0.0:  # no route
            joining = self._joining(cfg)
            res = _joined(res, lambda: decode(self._call(ti, joining, self._state(), joining=True)))
        return track_match(str(track.track_id), res)

    def _call(self, ti: TrackInput, cfg: MatchConfig, st: _ThreadState, joining: bool = False) -> Packed:
        """One compiled call with this thread's scratch ``st`` (``joining``: without the detour
        limit); its arena grown after a call that needed more (``st`` is then this thread's no
        more: :meth:`_state` again)."""
        packed = self._run_track(ti, self._context(st, cfg, joining))
        if max(st.arena.top.tolist()) > len(st.arena.f8):
            self._grow_arena(st)
        return packed  # type: ignore[no-any-return]

    def _joining(self, cfg: MatchConfig) -> MatchConfig:
        """``cfg`` without the rule that leaves fixes out (``outlier_lookahead``), for a track
        it and the detour limit left one fix (the call drops the limit: ``joining``)."""
        got = self._joining_cfg.get(id(cfg))
        if got is None or got[0] is not cfg:
            got = self._joining_cfg[id(cfg)] = (cfg, cfg.replace(outlier_lookahead=0))
        return got[1]

    def _grow_arena(self, st: _ThreadState) -> None:
        """This thread's arena grown to what the last call needed (new contexts with it)."""
        big = st.arena.grown()
        if big is not None:
            self._local.state = st._replace(arena=big, contexts={})


def match_track(
    graph: RoadGraph, track: Track, *, index: EdgeIndex | None = None, config: MatchConfig | None = None
) -> TrackMatch:
    """Match one track (builds a :class:`BatchMatcher`; reuse one for many tracks)."""
    return BatchMatcher(graph, index, config).match(track)


def _projector(tr: Transformer) -> Callable[[NDArray[np.float64]], None]:
    """A function projecting rows 2 and 3 (lon, lat) of a C-contiguous (4, n) float64 buffer in
    place with ``tr``.

    :meth:`Transformer.transform` spends about 7 of its 9 microseconds on a handful of points
    checking and copying its arguments; with pyproj's own buffers the projection is called
    directly (the same PROJ call, so the same numbers), else through the public method.
    """
    core = getattr(tr, "_transformer", None)
    if core is not None and hasattr(core, "_transform"):
        forward = TransformDirection.FORWARD

        def project(buf: NDArray[np.float64]) -> None:
            core._transform(buf[2], buf[3], None, None, forward, False, False)

        return project

    def project_public(buf: NDArray[np.float64]) -> None:
        tr.transform(buf[2], buf[3], inplace=True)

    return project_public


def _odometer(distance: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cumulative odometer distance from per-point distances (NaN where a reading is missing)."""
    d = np.asarray(distance, dtype=F8)
    return np.where(np.isfinite(d), np.cumsum(np.where(np.isfinite(d), d, 0.0)), np.nan)


def _joined(res: TrackResult, again: Callable[[], TrackResult]) -> TrackResult:
    """A match with no route, or, where it places at most one fix, ``again()`` (the match
    without the rules that leave fixes out, :meth:`BatchMatcher._joining`) if that has a route:
    one fix makes no route."""
    if res.placed > 1:
        return res
    other = again()
    return other if other.length > 0.0 else res


def _column(a: ArrayLike | None, n: int, name: str, missing: float | None = None) -> NDArray[np.float64]:
    """An optional per-fix column for the kernel: float64, C-contiguous, ``n`` long; a missing
    one is empty, or ``n`` times ``missing`` when given (the kernel never reads past its end)."""
    if a is None:
        return NO_COLUMN if missing is None else np.full(n, missing)
    out = fresh(a, F8)
    if out.shape != (n,):
        raise ValueError(f"the track's {name} column has shape {out.shape}, not ({n},) as lat")
    return out


def _opt(a: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
    return np.full(n, np.nan) if a is None else np.ascontiguousarray(a, dtype=F8)


__all__ = ["BATCH_CONFIG", "BatchMatcher", "match_track"]
