"""``mapmatch serve``: run the gRPC service for fusion nodes."""

from __future__ import annotations

import argparse
from typing import Any

DESCRIPTION = """\
Serve online matching (live streams and single fixes), batch track matching, map management
and session export/import over gRPC (API: proto/mapmatch/v1/mapmatch.proto).

Every flag has a MAPMATCH_* environment variable, and every setting can be given in a TOML
file (--config); flags win over the environment, which wins over the file. See
docs/deployment.md, "Settings". By default the server listens in plain text on
127.0.0.1:50051, refuses a port in use (--reuse-port to share one) and does not load maps
named by clients (--map-dir).
Health checking (grpc.health.v1) reports NOT_SERVING until the maps are loaded and warmed
up; each start-up step is logged, and so is SERVING. SIGTERM or Ctrl-C shuts down
gracefully (in-flight calls get --grace seconds).

exit status: 0 stopped by a signal, 2 bad configuration (flag, file, TLS file, map),
3 cannot serve (address in use or unavailable, a map fails to load)."""

EPILOG = """\
examples:
  mapmatch serve --map helsinki=helsinki.map
  mapmatch serve --map hel=helsinki.map --map mco=monaco.map --address 0.0.0.0:50051 \\
      --tls-cert server.crt --tls-key server.key --client-ca fleet-ca.crt --token-file token.txt
  MAPMATCH_MAPS=hel=helsinki.map MAPMATCH_SESSION_TTL=300 mapmatch serve
  mapmatch serve --config serve.toml --map-dir /srv/maps"""


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
    from mapmatch.cli import CommandError
    from mapmatch.errors import ConfigError
    from service.config import config_from
    from service.server import configure_logging, serve

    try:
        config = config_from(args)
    except ConfigError as exc:
        raise CommandError(str(exc)) from None
    for name, path in config.maps:
        if not path.is_file():
            raise CommandError(f"map {name}: no such file: {path}")
    # lifecycle lines always; access lines (one per call) with -v
    configure_logging(config.log_format, access=getattr(args, "verbose", 0) > 0)
    try:
        return serve(config)
    except ConfigError as exc:
        text = str(exc)
        code = 3 if text.startswith(("cannot listen", "cannot serve")) else 2
        raise CommandError(text, code=code) from None
