"""Online per-vehicle matching: the thesis's ambiguous-region algorithm as a small discrete filter.

The filter holds a few *path hypotheses*: short sequences of directed edges the vehicle may be
driving, a position along each and a log-probability. Between intersections there is one
hypothesis on one edge; within the ambiguous-region radius ``r_a`` of its end node it is
extended with every legal move, each fix is scored on every path (emission, transition, turn
evidence), the most probable edge is reported, and once the best hypothesis has left the
region the node is committed, its turn classified and, where the committed path disagrees
with what was reported live, a :class:`~mapmatch.types.Correction` is returned.

Where each mechanism lives:

- :mod:`~mapmatch.online.matcher`: :class:`OnlineMatcher`; ``update`` orchestrates one fix.
- :mod:`~mapmatch.online.step`: the per-fix step (validation, σ floors, drift, the fix in map
  coordinates).
- :mod:`~mapmatch.online.state`: the named records (hypotheses, live fixes, trail points,
  path positions, the fix bias), each mechanism's own record of the session (anchor, bias,
  crossings, region, each written only by its module) and :class:`SessionState`, which
  composes them.
- :mod:`~mapmatch.online.codec`: ``to_bytes``/``from_bytes`` by named keys, validated, with the
  migration from version 1.
- :mod:`~mapmatch.online.filter`: the generic filter step (knows nothing of roads).
- :mod:`~mapmatch.online.road`: the road model: geometry, legal moves (:mod:`graph.rules`) and
  the emission, transition and turn scorers.
- :mod:`~mapmatch.online.hypotheses`: initialise, join alternatives, extend, place.
- :mod:`~mapmatch.online.along`: the position along a path (fix bias and turn anchor fused).
- :mod:`~mapmatch.online.region`: the ambiguous region and its commit.
- :mod:`~mapmatch.online.anchor`: the turn anchor, the odometer scale, re-timed crossings.
- :mod:`~mapmatch.online.bias`: the fix bias, the road residuals, the dead-reckoning drift.
- :mod:`~mapmatch.online.correction`: the fixed-lag smoother and the corrections.
- :mod:`~mapmatch.online.report`: the pure report (a :class:`~mapmatch.types.SnapResult`).

Fixes far off the map are not errors: they return ``State.OFF_ROAD`` with ``edge == -1``.
Invalid input raises :class:`~mapmatch.errors.ValidationError` and leaves the state unchanged.
"""

from mapmatch.online.correction import merge as _merge
from mapmatch.online.matcher import OnlineMatcher
from mapmatch.online.state import Hypothesis, SessionState
from mapmatch.online.step import LIMITS

__all__ = ["LIMITS", "Hypothesis", "OnlineMatcher", "SessionState", "_merge"]
