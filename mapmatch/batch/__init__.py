"""Batch map matching of historic tracks: exact Viterbi over the whole track (Newson & Krumm 2009).

The pipeline, one module a stage:

- :mod:`~mapmatch.batch.matcher`: measurements → candidates (one index query) → emissions
  (the shared :mod:`mapmatch.model`);
- :mod:`~mapmatch.batch.lattice`: thinning, pruning, the lattice (compiled);
- :mod:`~mapmatch.batch.viterbi`: the Viterbi search's forward pass and backtrack (compiled), on
  the generic search of :mod:`mapmatch.viterbi`: each step's costs supplied by
  :mod:`~mapmatch.batch.step` (routing between candidates), the pieces split by
  :mod:`~mapmatch.batch.split`, the fixes left out chosen by :mod:`~mapmatch.batch.leave_out`;
- :mod:`~mapmatch.batch.route`: route assembly, the route's edges, geometry and per-point
  results (compiled);
- :mod:`~mapmatch.batch.run`: the compiled stages as one call;
- :mod:`~mapmatch.batch.packed`: the call's answer in one array and its typed reading, a
  :class:`~mapmatch.batch.packed.TrackResult`;
- :mod:`~mapmatch.batch.results`: the :class:`~mapmatch.types.TrackMatch`, way ids and names.

The compiled kernels take the named tuples of :mod:`~mapmatch.batch.arrays`. The matched route
is always connected through the network; it is split only where the track has a time/distance
gap, where no route exists between consecutive points, or where the fixes left out between two
points travel ``off_map_cut`` slowly, or last as long as that takes and travel it with their
legs to those points (the track left the route's roads and came back), or where only a route
more than twice ``off_map_cut`` longer than the path through such a run would bridge it;
splits are reported.
"""

from mapmatch.batch.matcher import BatchMatcher, match_track
from mapmatch.batch.results import fill_route_lonlat, point_ways, route_ways
from mapmatch.config import BATCH_CONFIG

__all__ = ["BATCH_CONFIG", "BatchMatcher", "fill_route_lonlat", "match_track", "point_ways", "route_ways"]
