"""``mapmatch serve``: run the gRPC service for fusion nodes."""

from __future__ import annotations

import argparse
from typing import Any

DESCRIPTION = """\
Serve online matching (live streams and single fixes), batch track matching, map management
and session export/import over gRPC (API: proto/mapmatch/v1/mapmatch.proto).

Every flag has a MAPMATCH_* environment variable (flags win); see README, "gRPC service".
By default the server listens in plain text on 127.0.0.1:50051. Health checking
(grpc.health.v1) reports NOT_SERVING until the maps are loaded and warmed up; SIGTERM or
Ctrl-C shuts down gracefully (in-flight calls get --grace seconds)."""

EPILOG = """\
examples:
  mapmatch serve --map helsinki=helsinki.map
  mapmatch serve --map hel=helsinki.map --map mco=monaco.map --address 0.0.0.0:50051 \\
      --tls-cert server.crt --tls-key server.key --client-ca fleet-ca.crt --token-file token.txt
  MAPMATCH_MAPS=hel=helsinki.map MAPMATCH_SESSION_TTL=300 mapmatch serve"""


def register(subparsers: Any) -> None:
    from service.config import add_arguments

    p = subparsers.add_parser(
        "serve",
        help="run the gRPC map-matching service",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(p)
    p.set_defaults(func=run_serve)


def run_serve(args: argparse.Namespace) -> int:
    import logging

    from mapmatch.cli import CommandError
    from service.config import config_from
    from service.server import serve

    try:
        config = config_from(args)
    except OSError as exc:
        raise CommandError(f"cannot read {exc.filename}: {exc.strerror}") from None
    for name, path in config.maps:
        if not path.is_file():
            raise CommandError(f"map {name}: no such file: {path}")
    # lifecycle messages always; access logs (one line per call) with -v
    logging.getLogger("mapmatch.service").setLevel(logging.INFO)
    return serve(config)
