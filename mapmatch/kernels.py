"""The compiled (numba) kernels: which a job needs, whether they are compiled yet, and compiling them.

Kernels compile on first use and are cached on disk (``__pycache__`` next to the source, or
``NUMBA_CACHE_DIR``), so only the first run on a machine pays for it. Commands call
:func:`announce` before work that needs a group, which prints one line when the group is not
cached yet. The online matcher has no compiled kernels; ``simulate`` needs the fusion filter,
``match`` (and the service's ``MatchTrack``) the batch matcher.

``python -m mapmatch.kernels [GROUP...]`` compiles groups ahead of time (a container build
does it, so a container's first start is warm).
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from typing import Any, TextIO

GROUPS: dict[str, tuple[str, ...]] = {
    "simulator": ("mapmatch.sim.kalman", "mapmatch.sim.profile"),
    "batch": (
        "mapmatch.batch.lattice",
        "mapmatch.batch.viterbi",
        "mapmatch.batch.route",
        "mapmatch.batch.run",
        "mapmatch.routing",
        "mapmatch.gridindex",
        "mapmatch.model",
    ),
}
"""Kernel groups: the modules whose compiled functions a kind of job uses."""

COMPILE_SECONDS: dict[str, float] = {"simulator": 10.0, "batch": 60.0}
"""About how long (CPU seconds) a group takes to compile on the 2-core development machine."""

_announced: set[str] = set()


def dispatchers(group: str) -> list[Any]:
    """The group's numba dispatchers (the jitted functions in its modules)."""
    from numba.core.registry import CPUDispatcher

    out = []
    for name in GROUPS[group]:
        mod = importlib.import_module(name)
        out += [v for v in vars(mod).values() if isinstance(v, CPUDispatcher) and v.__module__ == name]
    return out


def is_cached(group: str) -> bool:
    """Whether every kernel of the group has an on-disk cache index (compiled before)."""
    for d in dispatchers(group):
        try:
            index = d._cache._cache_file._index_path  # numba's cache locator
        except AttributeError:
            return True  # unknown numba internals: do not claim anything
        if not os.path.exists(index):
            return False
    return True


def announce(group: str, *, stream: TextIO | None = None) -> bool:
    """Print "preparing compiled kernels, once, about N s" when the group is not compiled yet.

    Returns whether it was not cached (a compile follows). Printed once per group and process.
    """
    if group in _announced:
        return False
    _announced.add(group)
    if is_cached(group):
        return False
    print(
        f"preparing compiled kernels ({group}), once, about {COMPILE_SECONDS[group]:.0f} s",
        file=stream or sys.stderr,
        flush=True,
    )
    return True


def compile_group(group: str) -> float:
    """Compile (or load from the cache) a group's kernels by running a tiny job; seconds taken."""
    import numpy as np

    from mapmatch.graph.ascii import parse_ascii_map

    t0 = time.perf_counter()
    m = parse_ascii_map("a-----------b-----------c\n|           |\nd-----------e", scale=10)
    g = m.graph
    if group == "batch":
        from mapmatch.batch import BatchMatcher
        from mapmatch.types import Track

        x0, y0 = m.xy("a")
        x1, _ = m.xy("c")
        xs = np.linspace(x0 + 5, x1 - 5, 8)
        ll = np.array([m.lonlat(x, y0 + 1.0) for x in xs])
        t = np.arange(len(xs), dtype=np.float64) * 2.0
        BatchMatcher(g).match(Track("warm", t, ll[:, 1].astype(np.float64), ll[:, 0].astype(np.float64)))
    elif group == "simulator":
        from mapmatch.sim.drive import simulate_drive
        from mapmatch.sim.routes import random_route

        route = random_route(g, length_m=150.0, rng=np.random.default_rng(0))
        simulate_drive(g, route, rate=1.0, outages="none", seed=0)
    else:
        raise KeyError(group)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    groups = (argv if argv is not None else sys.argv[1:]) or list(GROUPS)
    for group in groups:
        if group not in GROUPS:
            print(f"unknown kernel group {group!r} (groups: {', '.join(GROUPS)})", file=sys.stderr)
            return 2
        announce(group)
        print(f"{group}: ready in {compile_group(group):.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
