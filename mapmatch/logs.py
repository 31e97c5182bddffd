"""Log output of the ``mapmatch`` command: human-readable text on a terminal, JSON lines otherwise.

``--log-format auto`` (the default) writes text when standard error is a terminal and one
JSON object per line when it is not (a pipe, a file, a container's log collector);
``text`` and ``json`` force either. JSON records hold ``time``, ``level``, ``logger`` and
``message`` (and ``exc`` with a traceback); python-json-logger formats them when it is
installed, a small formatter of the same fields otherwise.
"""

from __future__ import annotations

import json
import logging
import sys
from typing import Any, TextIO

LOG_FORMATS = ("auto", "text", "json")
"""The values of ``--log-format``."""
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message (and exc)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": self.formatTime(record, "%Y-%m-%dT%H:%M:%S") + f".{int(record.msecs):03d}",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def resolve_format(log_format: str, stream: TextIO | None = None) -> str:
    """``"text"`` or ``"json"``: ``auto`` is text on a terminal, JSON otherwise."""
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {', '.join(LOG_FORMATS)}, got {log_format!r}")
    if log_format != "auto":
        return log_format
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        return "text" if isatty is not None and isatty() else "json"
    except ValueError:  # a closed stream
        return "json"


def formatter(log_format: str, stream: TextIO | None = None) -> logging.Formatter:
    """The formatter of ``log_format`` (``auto``, ``text`` or ``json``) for ``stream``."""
    if resolve_format(log_format, stream) == "text":
        return logging.Formatter(TEXT_FORMAT)
    try:
        from pythonjsonlogger.json import JsonFormatter as Maintained
    except ImportError:
        return JsonFormatter()
    return Maintained(  # type: ignore[no-any-return]
        "%(asctime)s %(levelname)s %(name)s %(message)s",
        rename_fields={"asctime": "time", "levelname": "level", "name": "logger"},
    )


def configure(*, level: int, log_format: str = "auto") -> None:
    """Send the root logger's records at ``level`` and above to standard error in ``log_format``
    (replacing the handler an earlier call added; other handlers, a host's or a test's, stay)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(formatter(log_format, sys.stderr))
    handler.set_name(_HANDLER_NAME)
    root = logging.getLogger()
    for old in list(root.handlers):
        if old.get_name() == _HANDLER_NAME:
            root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level)


_HANDLER_NAME = "mapmatch.stderr"
