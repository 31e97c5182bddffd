"""Bounds on text input (CSV files, standard input): checked before any parser sees the text.

A line longer than :data:`MAX_LINE_BYTES` or a header naming more than :data:`MAX_COLUMNS`
columns is refused after reading at most one chunk past the limit, and an error message quotes
at most :data:`MAX_QUOTE` characters of the input. Only numpy is imported, so a command refuses
such input before it loads its heavier modules.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from mapmatch.errors import MatchError

MAX_LINE_BYTES = 1 << 20
"""The longest line a CSV input may hold (1 MiB): a longer one is refused before parsing."""
MAX_COLUMNS = 1000
"""The most columns a CSV header may name."""
MAX_QUOTE = 200
"""The most characters of the input an error message quotes."""
_CHUNK = 1 << 20


class InputTooLargeError(MatchError):
    """A text input holds a line longer than :data:`MAX_LINE_BYTES` or a header with more than
    :data:`MAX_COLUMNS` columns."""


def quote(text: object, limit: int = MAX_QUOTE) -> str:
    """``repr`` of at most ``limit`` characters of ``text``, then how many were left out."""
    s = str(text)
    if len(s) <= limit:
        return repr(s)
    return f"{s[:limit]!r}... ({len(s) - limit:,} more characters)"


def clip(text: str, limit: int = MAX_QUOTE) -> str:
    """``text`` itself when it has at most ``limit`` characters, else its start and a count."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text) - limit:,} more characters)"


class LineBounds:
    """Checks a text stream, chunk by chunk, against :data:`MAX_LINE_BYTES` and :data:`MAX_COLUMNS`.

    Feed it the bytes in order (:meth:`feed`), then call :meth:`close`; both raise
    :class:`InputTooLargeError` as soon as a bound is passed, so a huge line is refused after
    reading at most one chunk beyond the limit.
    """

    def __init__(self, name: str, *, max_line: int = MAX_LINE_BYTES, max_columns: int = MAX_COLUMNS) -> None:
        self.name = name
        self.max_line = max_line
        self.max_columns = max_columns
        self.line = 1  # the line being read, 1-based
        self.current = 0  # its bytes so far
        self.header = bytearray()
        self.header_done = False

    def _too_long(self) -> InputTooLargeError:
        return InputTooLargeError(
            f"{self.name}: line {self.line:,} is longer than {self.max_line:,} bytes, the limit "
            "of a line; refused without reading it (is this a CSV file of tracks or fixes?)"
        )

    def feed(self, chunk: bytes) -> None:
        """Check the next bytes of the stream."""
        nl = np.flatnonzero(np.frombuffer(chunk, dtype=np.uint8) == 10)
        if not self.header_done:
            end = int(nl[0]) if len(nl) else len(chunk)
            self.header += chunk[: min(end, self.max_line + 1)]
            if len(nl):
                self.header_done = True
        if not len(nl):
            self.current += len(chunk)
            if self.current > self.max_line:
                raise self._too_long()
            return
        if self.current + int(nl[0]) > self.max_line:
            raise self._too_long()
        if len(nl) > 1:
            gaps = np.diff(nl) - 1
            k = int(np.argmax(gaps))
            if gaps[k] > self.max_line:
                self.line += k + 1
                raise self._too_long()
        if self.header_done and self.line == 1:
            self._check_header()
        self.line += len(nl)
        self.current = len(chunk) - int(nl[-1]) - 1
        if self.current > self.max_line:
            raise self._too_long()

    def close(self) -> None:
        """The stream ended: check a header that had no line end."""
        if self.line == 1 and self.header:
            self._check_header()

    def _check_header(self) -> None:
        import csv

        text = bytes(self.header).decode("utf-8", errors="replace").rstrip("\r")
        sep = ";" if ";" in text and "," not in text else ","
        if text.count(sep) + 1 <= self.max_columns:
            return
        n = len(next(csv.reader([text], delimiter=sep), []))
        if n > self.max_columns:
            raise InputTooLargeError(
                f"{self.name}: the header names {n:,} columns, more than the limit of "
                f"{self.max_columns:,} (it begins {quote(text)})"
            )


def check_text_input(path: str | os.PathLike[str], *, name: str | None = None) -> None:
    """Refuse a CSV file (plain or ``.gz``) with a line or header beyond the bounds (:class:`LineBounds`).

    Raises
    ------
    InputTooLargeError
        A line is longer than :data:`MAX_LINE_BYTES`, or the header names more than
        :data:`MAX_COLUMNS` columns.
    """
    import gzip

    bounds = LineBounds(name or str(path))
    opener: Any = gzip.open if str(path).lower().endswith(".gz") else open
    with opener(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            bounds.feed(chunk)
    bounds.close()


def spool_stdin(dest: str | os.PathLike[str]) -> None:
    """Copy standard input to the file ``dest``, checking it as :func:`check_text_input` does."""
    import sys

    bounds = LineBounds("standard input")
    with open(dest, "wb") as out:
        while chunk := sys.stdin.buffer.read(_CHUNK):
            bounds.feed(chunk)
            out.write(chunk)
    bounds.close()
