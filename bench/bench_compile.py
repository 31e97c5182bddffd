"""Where a cold compile goes: numba's compile time per kernel, for each kernel group.

Each group (``simulator``, ``online``, ``batch``: :data:`mapmatch.kernels.GROUPS`) is compiled
in a fresh process with an empty cache of its own (``NUMBA_CACHE_DIR`` in a temporary folder),
by the tiny job :func:`mapmatch.kernels.compile_group` runs, while a listener on numba's
``numba:compile`` events times every kernel compiled. A kernel's *own* time leaves out the
kernels it calls that compile separately (those not ``inline="always"``); its *total* includes
them. Prints per group the process's CPU seconds, the compile events' CPU seconds, and the
kernels with the largest own time, with the machine's load average.

    python bench/bench_compile.py                    # every group, 12 kernels each
    python bench/bench_compile.py --groups batch --top 30
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time
from numba.core import event

own, total, count, stack = {}, {}, {}, []


class Timer(event.Listener):
    def on_start(self, ev):
        stack.append([time.process_time(), 0.0])

    def on_end(self, ev):
        t0, inner = stack.pop()
        spent = time.process_time() - t0
        f = ev.data["dispatcher"].py_func
        name = f"{f.__module__}.{f.__qualname__}"
        own[name] = own.get(name, 0.0) + spent - inner
        total[name] = total.get(name, 0.0) + spent
        count[name] = count.get(name, 0) + 1
        if stack:
            stack[-1][1] += spent


event.register("numba:compile", Timer())
from mapmatch.kernels import compile_group

compile_group(sys.argv[1])
print(json.dumps({"own": own, "total": total, "count": count}))
"""


def _load() -> str:
    return "load " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def profile(group: str) -> dict[str, object]:
    """Compile ``group`` cold in a child process; its CPU seconds and per-kernel times."""
    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(ROOT))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        out = subprocess.run(
            [sys.executable, "-c", _CHILD, group],
            env=env,
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        )
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    data = json.loads(out.stdout.strip().splitlines()[-1])
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return {"wall": wall, "cpu": cpu, **data}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--groups", nargs="+", default=["simulator", "online", "batch"])
    ap.add_argument("--top", type=int, default=12, help="kernels listed per group")
    args = ap.parse_args(argv)
    print(f"# machine: {os.cpu_count()} cores; {_load()}")
    for group in args.groups:
        r = profile(group)
        own: dict[str, float] = r["own"]  # type: ignore[assignment]
        total: dict[str, float] = r["total"]  # type: ignore[assignment]
        count: dict[str, int] = r["count"]  # type: ignore[assignment]
        print(
            f"\n## {group}: {r['cpu']:.1f} s CPU, {r['wall']:.1f} s wall, {sum(own.values()):.1f} s in "
            f"{sum(count.values())} compiles of {len(own)} kernels ({_load()})\n"
        )
        print("| kernel | own s | total s | compiles |\n|---|---|---|---|")
        for name in sorted(own, key=own.__getitem__, reverse=True)[: args.top]:
            print(f"| `{name}` | {own[name]:.2f} | {total[name]:.2f} | {count[name]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
