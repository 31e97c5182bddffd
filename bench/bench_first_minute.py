"""A user's first minute: README's first command (the demo) and `serve` to SERVING, cold and warm.

Cold = no compiled-kernel cache (a fresh NUMBA_CACHE_DIR, as on a fresh clone); warm = the
same cache again. Each step runs as its own process, one after the other. Prints wall and CPU
seconds and the machine's load average, which decides the wall times on a shared machine.

    python bench/bench_first_minute.py [--monaco PATH.osm.pbf] [--skip-demo]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MONACO = ROOT.parent / "shared" / "data" / "osm" / "monaco.osm.pbf"


def _env(cache: Path) -> dict[str, str]:
    return dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def demo(cache: Path, out: Path) -> tuple[float, float]:
    """Seconds (wall, CPU) of `mapmatch demo` until its table is printed."""
    c0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "mapmatch", "demo", "--out", str(out)],
        env=_env(cache), capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert "route mismatch fraction" in proc.stdout, proc.stdout
    return time.perf_counter() - t0, _children_cpu() - c0


def serve(cache: Path, map_path: Path) -> tuple[float, float]:
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
        env=_env(cache), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
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
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="first-minute-") as tmp:
        work = Path(tmp)
        rows = []
        if not args.skip_demo:
            cache = work / "numba-demo"
            for label in ("cold", "warm"):
                out = work / f"demo-{label}"  # a fresh folder: the map is prepared again each time
                load = _load()
                wall, cpu = demo(cache, out)
                rows.append((f"mapmatch demo, {label}", wall, cpu, load))
                print(f"{rows[-1][0]:50s} {wall:6.1f} s wall {cpu:6.1f} s CPU  (load {load})", flush=True)
        if args.skip_serve:
            pass
        elif args.monaco.is_file():
            map_path = work / "monaco.map"
            subprocess.run(
                [sys.executable, "-m", "mapmatch", "prep", str(args.monaco), "-o", str(map_path), "-q"],
                env=_env(work / "numba-prep"), check=True, stdout=subprocess.DEVNULL,
            )  # fmt: skip
            cache = work / "numba-serve"
            for label in ("cold", "warm", "warm, batch kernels compiled"):
                if label.endswith("compiled"):  # a machine that has matched tracks before
                    cache = ROOT / ".bench-numba-cache"
                    subprocess.run(
                        [sys.executable, "-m", "mapmatch.kernels", "batch"], env=_env(cache), check=True
                    )
                load = _load()
                wall, cpu = serve(cache, map_path)
                rows.append((f"serve Monaco to SERVING, {label}", wall, cpu, load))
                print(f"{rows[-1][0]:50s} {wall:6.1f} s wall {cpu:6.1f} s CPU  (load {load})", flush=True)
        else:
            print(f"no {args.monaco}: serve not measured")
    print(f"targets: demo cold <= 20 s; serve cold <= 10 s, warm <= 2 s; {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
