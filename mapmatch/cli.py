"""The ``mapmatch`` command: one entry point, one module per subcommand in ``mapmatch.commands``.

Every subcommand module defines ``register(subparsers)``, which adds its parser and sets
``func(args) -> int``. Errors from the documented hierarchies become a one-line message and a
non-zero exit, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from graph.errors import GraphError
from mapmatch.errors import MatchError

SUBCOMMANDS = ("prep", "export", "info", "replay", "match", "serve", "send", "simulate", "eval", "demo")


class CommandError(Exception):
    """A subcommand's user-facing failure: printed as one line, exit status ``code``."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mapmatch",
        description="Map preparation, online and batch map matching, and the gRPC service.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        try:
            mod = importlib.import_module(f"mapmatch.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"mapmatch.commands.{name}":
                raise
            continue
        mod.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except CommandError as exc:
        print(f"mapmatch {args.command}: error: {exc}", file=sys.stderr)
        return exc.code
    except (GraphError, MatchError) as exc:
        print(f"mapmatch {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"mapmatch {args.command}: error: no such file: {exc.filename}", file=sys.stderr)
        return 2
    except (PermissionError, IsADirectoryError) as exc:
        print(f"mapmatch {args.command}: error: {exc.strerror}: {exc.filename}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mapmatch {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
