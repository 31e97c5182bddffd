"""``mapmatch send``: stream a file of fused fixes to a server and write its answers."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Stream fused fixes to a running `mapmatch serve` (all vehicles on one stream, merged by
time, as a fusion node sends them) and write one result row per fix, with the same input
and output columns as `mapmatch replay`. A fix the server rejects gets a row with state
"rejected" and the reason in "error", and the run exits 1. "-" reads the fixes from standard
input, "-o -" writes the results to standard output. A server that cannot be reached (or
fails the stream) exits 3.

The server keeps each vehicle's session between runs (until it has been idle for its session
timeout): sending the same drive again has every fix rejected, its time not after the session's
last. --new-session ends each vehicle's session first; --vehicle-id sends under another name."""

EPILOG = """\
examples:
  mapmatch send --server 127.0.0.1:50051 drive.csv -o snapped.csv
  mapmatch send --server maps.example.org:443 --tls-ca ca.crt --token-file token.txt fleet.csv -o out.csv"""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "send",
        help="stream a CSV of fused fixes to a server; write its answers",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from mapmatch.commands._fixio import add_fix_options

    add_fix_options(p)
    p.add_argument(
        "--new-session", action="store_true",
        help="end each vehicle's session on the server first (sending the same drive again)",
    )  # fmt: skip
    p.add_argument(
        "--server", default="127.0.0.1:50051", metavar="HOST:PORT", help="server (127.0.0.1:50051)"
    )
    p.add_argument("--map-id", default="", help="map to use (needed when the server holds several)")
    p.add_argument("--tls-ca", type=Path, metavar="FILE", help="PEM CA of the server's certificate: use TLS")
    p.add_argument("--client-cert", type=Path, metavar="FILE", help="PEM client certificate (mutual TLS)")
    p.add_argument("--client-key", type=Path, metavar="FILE", help="PEM client key (mutual TLS)")
    p.add_argument("--token", help="bearer token [MAPMATCH_TOKEN]")
    p.add_argument("--token-file", type=Path, metavar="FILE", help="file holding the bearer token")
    p.add_argument(
        "--timeout", type=float, default=600.0, metavar="S", help="deadline of the whole stream (600)"
    )
    from mapmatch.commands._fixio import precheck_fixes

    p.set_defaults(func=run_send, precheck=precheck_fixes)


def run_send(args: argparse.Namespace) -> int:
    import os

    import grpc

    from mapmatch.cli import EXIT_CONNECT, EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, CommandError
    from mapmatch.commands._fixio import output_path, read_fixes_arg, rejected_failure, summary_stream
    from mapmatch.fixes import write_results_csv
    from service.client import MapMatchClient, interleave_by_time

    try:
        token = args.token or (args.token_file.read_text().strip() if args.token_file else None)
    except OSError as exc:
        raise CommandError(f"cannot read {exc.filename}: {exc.strerror}") from None
    token = token or os.environ.get("MAPMATCH_TOKEN") or None
    vehicles = read_fixes_arg(args)
    t0 = time.perf_counter()
    answers: dict[str, list[Any]] = {vid: [] for vid in vehicles}
    counts: dict[str, int] = {}
    first_error = ""
    try:
        with MapMatchClient(
            args.server,
            tls_ca=args.tls_ca,
            client_cert=args.client_cert,
            client_key=args.client_key,
            token=token,
        ) as client:
            if args.new_session:
                _end_sessions(client, vehicles, map_id=args.map_id)
            started: set[str] = set()
            for a in client.stream(interleave_by_time(vehicles), map_id=args.map_id, timeout=args.timeout):
                first_of_vehicle = a.vehicle_id not in started
                started.add(a.vehicle_id)
                if a.error is not None:
                    counts["rejected"] = counts.get("rejected", 0) + 1
                    # same wording as `mapmatch replay` (fields relative to the fix)
                    msg = a.error.message.removeprefix("fix.")
                    if not first_error:
                        hint = _time_hint(msg, first_of_vehicle=first_of_vehicle)
                        first_error = f"vehicle {a.vehicle_id} at time {a.fix.time!r}: {msg}{hint}"
                    answers[a.vehicle_id].append((a.vehicle_id, a.fix, None, msg))
                    if a.error.code is not grpc.StatusCode.INVALID_ARGUMENT:
                        raise CommandError(f"server: {a.error.code.name}: {a.error.message}", EXIT_CONNECT)
                else:
                    assert a.result is not None
                    counts[str(a.result.state)] = counts.get(str(a.result.state), 0) + 1
                    answers[a.vehicle_id].append((a.vehicle_id, a.fix, a.result))
    except grpc.RpcError as exc:
        code = exc.code()
        # a request the server refuses as such (bad token, unknown map...) is bad input, not a
        # connection failure
        usage = code in (
            grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND, grpc.StatusCode.UNAUTHENTICATED,
            grpc.StatusCode.PERMISSION_DENIED, grpc.StatusCode.FAILED_PRECONDITION,
        )  # fmt: skip
        raise CommandError(
            f"{args.server}: {code.name}: {exc.details()}", EXIT_USAGE if usage else EXIT_CONNECT
        ) from None
    except OSError as exc:
        raise CommandError(f"cannot read {exc.filename}: {exc.strerror}") from None
    with output_path(args.output) as out:
        n = write_results_csv(out, (row for rows in answers.values() for row in rows))
    dt = time.perf_counter() - t0
    summary = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    where = f"{len(vehicles)} vehicle(s) matched by {args.server} in {dt:.2f} s"
    if not getattr(args, "quiet", False):
        print(f"{n} fixes of {where} -> {args.output} ({summary})", file=summary_stream(args))
    failed = rejected_failure(counts, n, first_error)
    if failed:
        print(f"mapmatch send: error: {failed}", file=sys.stderr)
        return EXIT_PARTIAL
    return EXIT_OK


def _end_sessions(client: Any, vehicles: dict[str, list[Any]], *, map_id: str) -> None:
    """End each vehicle's session on the server (``--new-session``)."""
    from service.gen import mapmatch_pb2 as pb

    for vid in vehicles:
        req = pb.EndSessionRequest(map_id=map_id, vehicle_id=vid)
        client.stub.EndSession(req, timeout=10.0, metadata=client.metadata)


def _time_hint(message: str, *, first_of_vehicle: bool) -> str:
    """What to do about a fix rejected for its time, or "" for another rejection."""
    from mapmatch.commands._fixio import TIME_REJECTED

    if not message.startswith(TIME_REJECTED):
        return ""
    if first_of_vehicle:
        return (
            "; the server still holds this vehicle's session (the drive sent before?): "
            "--new-session ends it first, or --vehicle-id sends under another name"
        )
    return (
        "; the vehicle's times go back in the file (drives joined?): send each drive with its own "
        "--vehicle-id"
    )
