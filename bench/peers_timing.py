"""Repeated timing of one engine's match call on one prepared Kubicka work dir (run by
``bench_batch.py`` with the engine's own Python, as the peers' harness runs its engines).

    <python> peers_timing.py ENGINE WORKDIR OUT.json --S 1,10,30 --repeat 7

The engine, its map loading, the sub-sampling and the timed call are the harness's own
(``engines_kubicka.py``: ``ENGINES[engine]``, ``subsample``, ``call``); only the timing differs:
one warm-up call per S (not counted), then ``--repeat`` timed calls, of which the least and the
median are written. Every engine is timed by this same loop.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("engine")
    ap.add_argument("work")
    ap.add_argument("out")
    ap.add_argument("--S", default="1,10,30")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--peers", default=os.environ.get("MAPMATCH_PEERS", ""), help="the peers' folder")
    a = ap.parse_args()
    sys.path.insert(0, a.peers)
    import engines_kubicka as ek  # type: ignore[import-not-found]

    engine = ek.ENGINES[a.engine]()
    t, lat, lon = ek.read_track(a.work)
    obj = engine.load(a.work)
    runs = []
    for s in (int(x) for x in a.S.split(",")):
        idx = ek.subsample(len(t), s)
        tt, la, lo = [t[i] for i in idx], [lat[i] for i in idx], [lon[i] for i in idx]
        engine.call(obj, tt, la, lo)  # warm-up, not counted
        times = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            engine.call(obj, tt, la, lo)
            times.append(time.perf_counter() - t0)
        runs.append(
            {
                "S": s,
                "n_points": len(idx),
                "times_s": times,
                "min_s": min(times),
                "median_s": statistics.median(times),
            }
        )
    Path(a.out).write_text(json.dumps({"engine": a.engine, "work": a.work, "repeat": a.repeat, "runs": runs}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
