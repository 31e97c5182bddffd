"""Can one client stall another? The longest wait of a 50 Hz stream while a client attacks.

A server (``mapmatch serve``, its own process) serves a small grid map from a map file. One
vehicle streams ``StreamFixes`` at ``--rate`` Hz (paced, one client thread sending, one
receiving); after ``--quiet`` seconds another client process imports, ``--imports`` times,
the largest session blob the matcher's caps allow (``tests/stall_util.py``), each followed
by fixes for that vehicle, and also tries a blob over the caps (200,000 heading samples,
refused). Printed: the longest gap between two answers of the 50 Hz stream before and during
the attack, its p99, the import times, the blob sizes, and the machine's load average.

    python bench/bench_attacks.py
    python bench/bench_attacks.py --seconds 20 --imports 20
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import grpc  # noqa: E402
import numpy as np  # noqa: E402
from online_helpers import DriveSpec, drive  # noqa: E402
from service_util import city, requests  # noqa: E402
from stall_util import worst_case_blob  # noqa: E402

from graph.artifact import save_map  # noqa: E402
from mapmatch.config import DEFAULT_CONFIG  # noqa: E402
from mapmatch.online.codec import StateCaps  # noqa: E402
from service.gen import mapmatch_pb2 as pb  # noqa: E402
from service.gen import mapmatch_pb2_grpc as pbg  # noqa: E402

AMAP = city()


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg()) + f" ({os.cpu_count()} cores)"


def start_server(map_path: Path) -> tuple[subprocess.Popen[str], int]:
    cmd = [sys.executable, "-m", "mapmatch", "serve", "--map", f"city={map_path}",
           "--address", "127.0.0.1:0", "--no-reuse-port", "--log-format", "text"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise SystemExit(f"server failed to start: {line!r}")
    # "mapmatch serve: listening on HOST:PORT (N map(s))"
    return proc, int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])


def wait_serving(port: int, timeout: float = 120.0) -> None:
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    ch = grpc.insecure_channel(f"127.0.0.1:{port}")
    h = health_pb2_grpc.HealthStub(ch)
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if (
                h.Check(health_pb2.HealthCheckRequest(), timeout=2).status
                == health_pb2.HealthCheckResponse.SERVING
            ):
                ch.close()
                return
        except grpc.RpcError:
            pass
        time.sleep(0.1)
    raise SystemExit("the server never became SERVING")


def attacker(port: int, start: float, imports: int, out: Any) -> None:
    """Another client: imports the largest allowed blob (and one over the caps), with fixes."""
    ch = grpc.insecure_channel(f"127.0.0.1:{port}", options=[("grpc.max_send_message_length", 64 << 20)])
    api = pbg.MapMatchStub(ch)
    fixes = drive(AMAP, "abefc", DriveSpec(speed=10.0, dt=1.0, noise=1.5, seed=7, sigma=3.0))
    list(api.StreamFixes(iter(requests(fixes[:14], "seed")), timeout=60))
    blob = api.ExportSession(pb.ExportSessionRequest(vehicle_id="seed"), timeout=10)
    worst = worst_case_blob(blob.state, StateCaps.of(DEFAULT_CONFIG), n_edges=AMAP.graph.n_edges)
    d = json.loads(blob.state)
    d["headings"] = [[float(i), 90.0] for i in range(200_000)]
    over = json.dumps(d).encode()
    later = requests(drive(AMAP, "abefc", DriveSpec(speed=10.0, dt=1.0, seed=7, sigma=3.0))[14:24], "big")
    while time.time() < start:
        time.sleep(0.01)
    times, fix_times, refused = [], [], ""
    for k in range(imports):
        s = pb.SessionBlob(map_id=blob.map_id, vehicle_id="big", map_checksum=blob.map_checksum, state=worst)
        t0 = time.perf_counter()
        api.ImportSession(pb.ImportSessionRequest(session=s, replace=True), timeout=60)
        times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        list(api.StreamFixes(iter(later), timeout=60))
        fix_times.append(time.perf_counter() - t0)
        if k == 0:
            s = pb.SessionBlob(
                map_id=blob.map_id, vehicle_id="big2", map_checksum=blob.map_checksum, state=over
            )
            t0 = time.perf_counter()
            try:
                api.ImportSession(pb.ImportSessionRequest(session=s, replace=True), timeout=60)
                refused = "IMPORTED (not refused)"
            except grpc.RpcError as err:
                ms = 1000.0 * (time.perf_counter() - t0)
                refused = f"{err.code().name} in {ms:.1f} ms: {err.details()[:60]}"
    out.put({"import_s": times, "fixes_s": fix_times, "worst_bytes": len(worst), "over_bytes": len(over),
             "refused": refused, "end": time.time()})  # fmt: skip
    ch.close()


def stream_50hz(port: int, rate: float, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Send fixes at ``rate`` Hz for ``seconds``; returns (send times, answer times) (wall clock)."""
    fixes = drive(AMAP, "abcfedghdabcfed", DriveSpec(speed=10.0, dt=1.0 / rate, noise=0.5, seed=3, sigma=3.0))
    n = min(len(fixes), int(rate * seconds))
    reqs = requests(fixes[:n], "steady")
    sent = np.zeros(n)
    ch = grpc.insecure_channel(f"127.0.0.1:{port}")
    api = pbg.MapMatchStub(ch)
    t0 = time.time()

    def gen():
        for i, r in enumerate(reqs):
            wait = t0 + i / rate - time.time()
            if wait > 0:
                time.sleep(wait)
            sent[i] = time.time()
            yield r

    got = []
    for _ in api.StreamFixes(gen(), timeout=seconds + 120):
        got.append(time.time())
    ch.close()
    return sent, np.asarray(got)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rate", type=float, default=50.0)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--quiet", type=float, default=4.0, help="seconds of the stream before the attack")
    ap.add_argument("--imports", type=int, default=10)
    args = ap.parse_args(argv)
    print(f"load average before: {_load()}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "city.map"
        save_map(AMAP.graph, path)
        proc, port = start_server(path)
        try:
            wait_serving(port)
            q: mp.Queue[Any] = mp.get_context("spawn").Queue()
            start = time.time() + args.quiet
            p = mp.get_context("spawn").Process(target=attacker, args=(port, start, args.imports, q))
            p.start()
            res: dict[str, Any] = {}
            got = threading.Thread(target=lambda: res.update(r=stream_50hz(port, args.rate, args.seconds)))
            got.start()
            a = q.get(timeout=args.seconds + 300)
            got.join()
            p.join(10)
        finally:
            proc.terminate()
            proc.wait(10)
    sent, ans = res["r"]
    gaps = np.diff(ans) * 1000.0
    mid = ans[1:]
    before = gaps[mid < start]
    during = gaps[(mid >= start) & (mid <= a["end"])]
    print(f"50 Hz stream: {len(sent)} fixes sent, {len(ans)} answered")
    print(f"attack: {args.imports} imports of the largest blob the caps allow ({a['worst_bytes']} bytes), "
          f"each with {10} fixes for its vehicle")  # fmt: skip
    print(f"blob over the caps ({a['over_bytes']} bytes, 200,000 heading samples): {a['refused']}")
    for what, key in (("import time", "import_s"), ("its 10 fixes", "fixes_s")):
        ms = 1000.0 * np.asarray(a[key])
        print(f"{what:<26} median {np.median(ms):.1f} ms, max {ms.max():.1f} ms")
    for name, g in (("before the attack", before), ("during the attack", during)):
        if len(g):
            print(f"gap between answers {name}: max {g.max():.1f} ms, p99 {np.percentile(g, 99):.1f} ms "
                  f"({len(g)} gaps; 20 ms is the send interval; target max <= 100 ms)")  # fmt: skip
    print(f"load average after: {_load()}")


if __name__ == "__main__":
    main()
