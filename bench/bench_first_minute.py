"""A user's first minute: README's first command (the demo) and `serve` to SERVING, cold and warm.

Cold = a fresh copy of the source tree (its tracked files as they are now: no ``__pycache__``,
so neither Python bytecode nor compiled kernels, exactly as on a fresh clone), with numba's
default cache (``__pycache__`` in that copy; ``NUMBA_CACHE_DIR`` is unset); warm = the same
copy again. Each step runs as its own process, one after the other. The demo is timed to its
table (the first table line on stdout) and to its exit. Prints wall and CPU seconds and the
machine's load average, which decides the wall times on a shared machine.

    python bench/bench_first_minute.py [--monaco PATH.osm.pbf] [--skip-demo] [--skip-serve] [--skip-batch]
                                       [--repeat N]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MONACO = ROOT.parent / "shared" / "data" / "osm" / "monaco.osm.pbf"


def _env(cache: Path | None, tree: Path = ROOT) -> dict[str, str]:
    """The environment of a step: ``tree`` on the path; numba's cache in ``cache``, or (None)
    numba's default, ``__pycache__`` next to the tree's sources."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("PYTHONPYCACHEPREFIX", None)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def fresh_tree(dst: Path) -> Path:
    """Copy the source tree's tracked files (working-tree contents, links kept) to ``dst``."""
    files = (
        subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
        .stdout.decode()
        .split("\0")
    )
    for name in filter(None, files):
        src, out = ROOT / name, dst / name
        if not src.is_symlink() and not src.exists():
            continue  # deleted in the working tree
        out.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            out.symlink_to(os.readlink(src))
        else:
            shutil.copy2(src, out)
    return dst


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def demo(tree: Path, out: Path) -> tuple[float, float, float]:
    """Seconds (wall to the table, wall to the exit, CPU) of `mapmatch demo` run from ``tree``."""
    c0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapmatch", "demo", "--out", str(out)],
        env=_env(None, tree), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    table = float("nan")
    lines = []
    for line in proc.stdout:
        if line.startswith("---") and table != table:
            table = time.perf_counter() - t0
        lines.append(line)
    if proc.wait() != 0:
        raise RuntimeError(f"mapmatch demo exited with {proc.returncode}")
    assert any("route mismatch fraction" in x for x in lines), "".join(lines)
    return table, time.perf_counter() - t0, _children_cpu() - c0


def serve(cache: Path | None, map_path: Path, tree: Path = ROOT) -> tuple[float, float]:
    """Seconds (wall, CPU so far) from starting `mapmatch serve` to health SERVING."""
    import socket

    from mapmatch.healthcheck import check

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapmatch", "serve", "--map", f"mco={map_path}",
         "--address", f"127.0.0.1:{port}"],
        env=_env(cache, tree), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        while check(f"127.0.0.1:{port}", timeout=0.5)[0] != 0:
            if proc.poll() is not None:
                raise RuntimeError(f"serve exited with {proc.returncode}")
            time.sleep(0.05)
        wall = time.perf_counter() - t0
        cpu = float("nan")
        try:
            with open(f"/proc/{proc.pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            pass
        return wall, cpu
    finally:
        proc.terminate()
        proc.wait(30)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--monaco", type=Path, default=MONACO)
    ap.add_argument("--skip-demo", action="store_true")
    ap.add_argument("--skip-serve", action="store_true")
    ap.add_argument(
        "--skip-batch", action="store_true", help="no serve row with batch kernels compiled (long)"
    )
    ap.add_argument("--repeat", type=int, default=1, help="cold/warm pairs of the demo, each on a fresh copy")
    args = ap.parse_args()

    def row(label: str, load: str, *figures: str) -> None:
        print(f"{label:50s} {'  '.join(figures)}  (load {load})", flush=True)

    with tempfile.TemporaryDirectory(prefix="first-minute-") as tmp:
        work = Path(tmp)
        if not args.skip_demo:
            for i in range(args.repeat):
                tree = fresh_tree(work / f"tree-demo-{i}")
                for label in ("cold", "warm"):
                    out = work / f"demo-{i}-{label}"  # a fresh folder: the map is prepared again each time
                    load = _load()
                    table, wall, cpu = demo(tree, out)
                    figures = f"{table:6.1f} s to the table", f"{wall:6.1f} s to the exit"
                    row(f"mapmatch demo, {label}", load, *figures, f"{cpu:6.1f} s CPU")
        if args.skip_serve:
            pass
        elif args.monaco.is_file():
            map_path = work / "monaco.map"
            subprocess.run(
                [sys.executable, "-m", "mapmatch", "prep", str(args.monaco), "-o", str(map_path), "-q"],
                env=_env(work / "numba-prep"), check=True, stdout=subprocess.DEVNULL,
            )  # fmt: skip
            tree = fresh_tree(work / "tree-serve")
            labels = ("cold", "warm") if args.skip_batch else ("cold", "warm", "warm, batch kernels compiled")
            for label in labels:
                cache = None
                if label.endswith("compiled"):  # a machine that has matched tracks before
                    cache = ROOT / ".bench-numba-cache"
                    subprocess.run(
                        [sys.executable, "-m", "mapmatch.kernels", "batch"], env=_env(cache), check=True
                    )
                load = _load()
                wall, cpu = serve(cache, map_path, tree if cache is None else ROOT)
                row(f"serve Monaco to SERVING, {label}", load, f"{wall:6.1f} s wall", f"{cpu:6.1f} s CPU")
        else:
            print(f"no {args.monaco}: serve not measured")
    print(f"targets: demo cold <= 20 s; serve cold <= 10 s, warm <= 2 s; {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
