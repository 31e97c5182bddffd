"""The ``mapmatch`` command: one entry point, one module per subcommand in ``mapmatch.commands``.

Every subcommand module defines ``register(subparsers)``, which adds its parser and sets
``func(args) -> int``; every subparser then gets the shared ``-q``/``-v`` options
(:func:`add_common_options`) and the exit statuses in its ``--help``. Errors become
a one-line message and one of the documented exit statuses (:data:`EXIT_STATUSES`), never a
traceback. Module-level imports stay light, so ``--help``, ``--version`` and a Ctrl-C during
start-up are instant and clean.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import sys
from collections.abc import Sequence

LOG_FORMATS = ("auto", "text", "json")  # as mapmatch.logs.LOG_FORMATS (--help stays instant)
KERNEL_MODES = ("auto", "compiled", "interpreted")  # as mapmatch.kernels.MODES

SUBCOMMANDS = ("prep", "export", "info", "replay", "match", "serve", "send", "simulate", "eval", "demo")
KERNELS: dict[str, tuple[str, ...]] = {
    "match": ("batch",),
    "simulate": ("simulator",),
    "demo": ("simulator", "online"),
    "replay": ("online",),
    "serve": ("online",),
}
"""The compiled-kernel groups (:mod:`mapmatch.kernels`) each command compiles on a machine's first run."""
TIERED = ("serve",)
"""Commands that, in mode ``auto`` on a cold cache, answer at once with their kernels interpreted
while they compile in the background, then switch (:class:`mapmatch.kernels.TieredGroup`)."""
ITEMS: dict[str, str] = {
    "match": "points",
    "simulate": "s of driving",
    "demo": "s of driving",
    "replay": "fixes",
}
"""What each command's job size (``kernel_items``, for the kernel mode) counts."""

EXIT_OK = 0
"""Everything asked for was done."""
EXIT_PARTIAL = 1
"""Done, with failures: some inputs rejected or unmatched beyond the command's threshold."""
EXIT_USAGE = 2
"""Usage error or bad input (missing file, bad column, corrupt map...); nothing was written."""
EXIT_CONNECT = 3
"""Cannot connect to a server, or cannot serve (port in use, TLS files unusable)."""
EXIT_INTERRUPTED = 130
"""Interrupted by Ctrl-C (SIGINT)."""

EXIT_STATUSES = f"""\
exit status:
  {EXIT_OK}  all done
  {EXIT_PARTIAL}  done with failures: replay, send and simulate when any fix was rejected; match when
     more than --max-unmatched (default 5 %) of the points, or every point of a track, is unmatched
  {EXIT_USAGE}  usage error or bad input (nothing is written)
  {EXIT_CONNECT}  cannot connect to the server, or cannot serve
  {EXIT_INTERRUPTED}  interrupted (Ctrl-C)
  141  standard output closed by its reader (mapmatch ... | head): no message
a failure is summed up in one line on stderr: "mapmatch COMMAND: error: ..." """


class CommandError(Exception):
    """A subcommand's user-facing failure: printed as one line, exit status ``code``."""

    def __init__(self, message: str, code: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.code = code


def version() -> str:
    """The installed distribution's version (``0+unknown`` in a source tree never installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("mapmatch")
    except PackageNotFoundError:
        return "0+unknown"


def add_common_options(p: argparse.ArgumentParser) -> None:
    """Add the options every subcommand takes (``-q``, ``-v``) unless it defines them itself.

    Their defaults are suppressed, so ``mapmatch -v match`` and ``mapmatch match -v`` both work.
    """
    have = p._option_string_actions
    if "-v" not in have:
        p.add_argument(
            "-v", "--verbose", action="count", default=argparse.SUPPRESS, help="more log output (-vv: debug)"
        )
    if "--log-format" not in have:
        p.add_argument(
            "--log-format", choices=LOG_FORMATS, default=argparse.SUPPRESS,
            help="log lines as text or JSON (default auto: text on a terminal, JSON otherwise)",
        )  # fmt: skip
    if "-q" not in have:
        p.add_argument(
            "-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
            help="only warnings and errors: no progress, no summary",
        )  # fmt: skip
    _add_kernel_options(p, default=argparse.SUPPRESS)


KERNELS_HELP = (
    "how the compiled kernels run: compiled (numba, compiled once per machine), interpreted "
    "(plain Python: no compile, slower per fix; the same answers) or auto: interpreted for a "
    "small job whose kernels are not compiled yet (default; env MAPMATCH_KERNELS)"
)
BELOW_HELP = (
    "with --kernels auto: run interpreted when the job has fewer than N fixes or points and its "
    "kernels are not compiled yet (default: when that is estimated to cost less than compiling; "
    "env MAPMATCH_INTERPRETED_BELOW). Speed only, never answers"
)


def _add_kernel_options(p: argparse.ArgumentParser, *, default: object) -> None:
    if "--kernels" not in p._option_string_actions:
        p.add_argument("--kernels", choices=KERNEL_MODES, default=default, help=KERNELS_HELP)
        p.add_argument("--interpreted-below", type=int, default=default, metavar="N", help=BELOW_HELP)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mapmatch",
        description="Map preparation, online and batch map matching, and the gRPC service.",
        epilog=EXIT_STATUSES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mapmatch {version()}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    parser.add_argument("-q", "--quiet", action="store_true", default=False, help="only warnings and errors")
    parser.add_argument(
        "--log-format", choices=LOG_FORMATS, default="auto",
        help="log lines as text or JSON (default auto: text on a terminal, JSON otherwise)",
    )  # fmt: skip
    _add_kernel_options(parser, default=None)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        try:
            mod = importlib.import_module(f"mapmatch.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"mapmatch.commands.{name}":
                raise
            continue
        mod.register(sub)
    for p in sub.choices.values():
        add_common_options(p)
        if p.epilog is None or "exit status:" not in p.epilog:
            p.epilog = (p.epilog + "\n\n" if p.epilog else "") + EXIT_STATUSES
            p.formatter_class = argparse.RawDescriptionHelpFormatter
    return parser


MESSAGE_MAX = 600
"""The longest error message printed (characters); a longer one is cut, saying so."""
EXIT_PIPE = 141
"""Standard output was closed by its reader (``mapmatch ... | head``): 128 + SIGPIPE, no message."""


def _fail(command: str, message: str, code: int) -> int:
    if len(message) > MESSAGE_MAX:
        message = f"{message[:MESSAGE_MAX]}... ({len(message) - MESSAGE_MAX:,} more characters)"
    print(f"mapmatch {command}: error: {message}", file=sys.stderr)
    return code


def _pipe_closed() -> int:
    """Standard output's reader is gone (``| head``): exit quietly, as a killed writer would.

    Standard output is pointed at /dev/null, so the interpreter's final flush finds no pipe.
    """
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return EXIT_PIPE


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``mapmatch`` command on ``argv`` (default: the process's arguments); the exit status."""
    command = "?"
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        command = args.command
        level = logging.WARNING - 10 * min(0 if args.quiet else args.verbose, 2)
        from mapmatch.logs import configure

        configure(level=level, log_format=getattr(args, "log_format", None) or "auto")
        rc = _run(args, entry=argv is None)
        if argv is None:
            sys.stdout.flush()  # a reader gone before the last bytes: a broken pipe here
        return rc
    except KeyboardInterrupt:
        print(f"mapmatch {command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return _pipe_closed()
    finally:
        if argv is None:
            # the process exits next: its teardown would run full garbage collections over
            # every object left (seconds after a demo); frozen objects are not scanned
            gc.freeze()


def _kernel_mode(args: argparse.Namespace, *, entry: bool) -> bool:
    """Choose how this process runs kernels (``--kernels``, else ``MAPMATCH_KERNELS``, else
    auto) and set it before any kernel is defined; whether they run interpreted. ``auto``
    decides only for a process started as the command (``entry``); a caller in process keeps
    its mode. Prints the one-line notice of an automatic choice unless ``--quiet``."""
    import os

    from mapmatch.kernels import BELOW_ENV, MODE_ENV, choose_mode, is_interpreted, set_mode

    mode = args.kernels or os.environ.get(MODE_ENV, "").strip() or "auto"
    if mode not in KERNEL_MODES:
        raise CommandError(f"{MODE_ENV}={mode!r}: must be one of {', '.join(KERNEL_MODES)}")
    below = args.interpreted_below
    if below is None and os.environ.get(BELOW_ENV, "").strip():
        try:
            below = int(os.environ[BELOW_ENV])
        except ValueError:
            raise CommandError(f"{BELOW_ENV}={os.environ[BELOW_ENV]!r}: must be a whole number") from None
    if below is not None and below < 0:
        raise CommandError("--interpreted-below must be >= 0")
    if mode == "auto" and not entry:
        return is_interpreted()
    if entry and args.command in TIERED:
        os.environ[MODE_ENV] = mode  # the server reads it (mapmatch.kernels.tiered_wanted)
    groups = KERNELS.get(args.command, ())
    items_of = getattr(args, "kernel_items", None)
    items = items_of(args) if mode == "auto" and groups and items_of is not None else None
    choice = choose_mode(mode, groups, items, below=below, noun=ITEMS.get(args.command, "items"))
    if not set_mode(interpreted=choice.interpreted):
        other = "compiled" if choice.interpreted else "interpreted"
        raise CommandError(f"--kernels {mode}: kernels already run {other} in this process")
    if choice.notice and not args.quiet:
        print(f"mapmatch {args.command}: {choice.notice}", file=sys.stderr, flush=True)
    return choice.interpreted


def _run(args: argparse.Namespace, *, entry: bool = False) -> int:
    from graph.errors import GraphError
    from mapmatch.errors import MatchError

    cmd = args.command
    try:
        precheck = getattr(args, "precheck", None)
        if precheck is not None:  # cheap input checks before the heavy imports and compiles
            precheck(args)
        interpreted = _kernel_mode(args, entry=entry)
        if not args.quiet and KERNELS.get(cmd) and not interpreted:
            from mapmatch.kernels import announce, tiered_wanted

            for group in KERNELS[cmd]:
                if cmd not in TIERED or not tiered_wanted(group):  # else the server logs it
                    announce(group)
        return int(args.func(args) or 0)
    except CommandError as exc:
        return _fail(cmd, str(exc), exc.code)
    except (GraphError, MatchError) as exc:
        return _fail(cmd, str(exc), EXIT_USAGE)
    except BrokenPipeError:
        raise
    except FileNotFoundError as exc:
        return _fail(cmd, f"no such file: {exc.filename}", EXIT_USAGE)
    except (PermissionError, IsADirectoryError, NotADirectoryError, FileExistsError) as exc:
        where = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
        return _fail(cmd, f"{exc.strerror}: {where}", EXIT_USAGE)
    except OSError as exc:
        return _fail(cmd, f"{exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), EXIT_USAGE)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # a library's error the command did not translate: still one line
        if _interrupted(exc):  # Ctrl-C inside compiled code surfaces as an error caused by it
            raise KeyboardInterrupt from None
        if _caused_by(exc, BrokenPipeError):
            raise BrokenPipeError from None
        logging.getLogger("mapmatch").debug("traceback", exc_info=True)
        kind = type(exc).__name__
        return _fail(
            cmd, f"{kind}: {exc} (a bug unless the input is bad; -vv shows the traceback)", EXIT_USAGE
        )


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` was caused by a KeyboardInterrupt (anywhere in its chain)."""
    return _caused_by(exc, KeyboardInterrupt)


def _caused_by(exc: BaseException, kind: type[BaseException]) -> bool:
    """Whether ``exc`` is or was caused by a ``kind`` (anywhere in its chain)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, kind):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False


if __name__ == "__main__":
    sys.exit(main())
