"""The largest session state the matcher's caps allow, for the stall tests and bench."""

from __future__ import annotations

import json
from typing import Any

from mapmatch.online.codec import StateCaps


def worst_case_blob(base: bytes, caps: StateCaps, *, n_edges: int, over: str = "") -> bytes:
    """``base`` (a real session's bytes) as version 2, with every list at its cap; ``over`` names one list
    (``hyps``, ``edges``, ``live``, ``headings``, ``trail``, ``back``) given one item more."""
    d: dict[str, Any] = json.loads(base)
    for key in ("headings_f64", "trail_time_ms", "trail_odo_cm"):  # written as version 2's lists
        d.pop(key, None)
    d["version"] = 2
    t, odo = float(d["time"]), float(d["odo"])

    def n(name: str, cap: int) -> int:
        return cap + 1 if over == name else cap

    m = n("edges", caps.path_edges)
    hyp = dict(d["hyps"][0])
    hyp.update(edges=[i % n_edges for i in range(m)], k=m - 1, enter=[t] * m)
    d["hyps"] = [dict(hyp) for _ in range(n("hyps", caps.hyps))]
    row = [t, 0, float(d["x"]), float(d["y"]), 90.0, 5.0, 1.0, True]
    d["live"] = [list(row) for _ in range(n("live", caps.live))]
    k = n("headings", caps.headings)
    d["headings"] = [[odo - k + i, 90.0] for i in range(k)]
    k = n("trail", caps.trail)
    d["trail"] = [[t - k + i, odo - k + i] for i in range(k)]
    d["back"] = [[i % n_edges, t] for i in range(n("back", caps.path_edges))]
    return json.dumps(d, separators=(",", ":")).encode()
