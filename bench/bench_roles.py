"""The cost of the roles check (:mod:`service.auth`), in microseconds.

Per message of a stream, the servicer asks whether the caller may act for the fix's vehicle
(:meth:`Identity.may_act_for`), and every streamed message passes the interceptor's request
hook; per call, the interceptor finds the caller by its token (SHA-256, a table look-up and
a constant-time comparison) and the method's rule. Each figure is the best of ``--repeats``
runs of ``--n`` calls, with the machine's load average before and after.

    python bench/bench_roles.py
    python bench/bench_roles.py --docs      # also writes docs/benchmarks/roles.md
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from report import capture, fenced, run_header, write_fragment  # noqa: E402

from service.auth import Identity, IdentityTable, Role, hash_token, rule_for  # noqa: E402
from service.gen import mapmatch_pb2 as pb  # noqa: E402
from service.interceptors import AccessSettings, AuthInterceptor, _Access  # noqa: E402

TARGET_US = 5.0


def best_us(fn: Callable[[], object], *, n: int, repeats: int) -> float:
    """The best of ``repeats`` runs of ``n`` calls of ``fn``, in microseconds per call."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / n


def _table(tmp: Path, n_identities: int) -> IdentityTable:
    lines = []
    for i in range(n_identities):
        lines.append(
            f'[[identity]]\nname = "node-{i}"\nrole = "vehicle"\n'
            f'token_sha256 = "{hash_token(f"token-{i}")}"\nvehicle_prefixes = ["node{i}/"]\n'
        )
    path = tmp / "ids.toml"
    path.write_text("".join(lines))
    return IdentityTable(path=path, token=None)


def run(*, n: int, repeats: int, identities: int) -> list[tuple[str, float]]:
    import tempfile

    ids = Identity(name="car", role=Role.VEHICLE, vehicles=frozenset(f"car-{i}" for i in range(64)))
    prefixes = Identity(name="node", role=Role.VEHICLE, vehicle_prefixes=("node1/", "node2/", "node3/"))
    fix = pb.FixRequest(vehicle_id="node3/truck-0042", map_id="hel", seq=1)
    own = pb.FixRequest(vehicle_id="car-42", map_id="hel", seq=1)
    with tempfile.TemporaryDirectory() as tmp:
        table = _table(Path(tmp), identities)
        hook = AuthInterceptor(AccessSettings(table=table, quotas=None)).request
        stream_state = _Access(prefixes, rule_for("/mapmatch.v1.MapMatch/StreamFixes"))
        unary_state = _Access(prefixes, rule_for("/mapmatch.v1.MapMatch/SnapFix"))
        token = f"token-{identities // 2}".encode()
        rows = [
            ("per fix: vehicle ids (64), may_act_for", lambda: ids.may_act_for(own.vehicle_id)),
            ("per fix: id prefixes (3), may_act_for", lambda: prefixes.may_act_for(fix.vehicle_id)),
            ("per streamed message: interceptor hook", lambda: hook(stream_state, fix)),
            ("per unary call: hook with vehicle check", lambda: hook(unary_state, fix)),
            (f"per call: token -> identity ({identities} ids)", lambda: table.by_token(token)),
            ("per call: rule of the method", lambda: rule_for("/mapmatch.v1.MapMatch/SnapFix")),
        ]
        return [(name, best_us(fn, n=n, repeats=repeats)) for name, fn in rows]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000, help="calls per run")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--identities", type=int, default=1000, help="identities in the table")
    ap.add_argument("--docs", action="store_true", help="write docs/benchmarks/roles.md")
    args = ap.parse_args(argv)
    with capture() as out:
        before = os.getloadavg()
        rows = run(n=args.n, repeats=args.repeats, identities=args.identities)
        after = os.getloadavg()
        print(f"{'check':<46} {'us':>8}")
        for name, us in rows:
            print(f"{name:<46} {us:8.3f}")
        per_message = rows[1][1] + rows[2][1]
        verdict = "within" if per_message <= TARGET_US else "OVER"
        print(f"per fix in a stream (prefix check + hook): {per_message:.3f} us, {verdict} {TARGET_US} us")
        print(f"load average before {before[0]:.2f} {before[1]:.2f}, after {after[0]:.2f} {after[1]:.2f}")
    if args.docs:
        write_fragment("roles", run_header() + fenced(out.getvalue()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
