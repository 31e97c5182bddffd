"""Benchmark figures into the documentation site: markdown fragments under ``docs/benchmarks/``.

A benchmark run with ``--docs`` writes its table as ``docs/benchmarks/<name>.md``; the
benchmarks page (``docs/benchmarks/index.md``) includes each fragment with
``pymdownx.snippets``, so ``mkdocs build`` shows the figures of the last run written. Every
fragment starts with the run's date, command, machine and load average, as figures from a
shared machine mean little without them.

    from report import capture, fenced, run_header, write_fragment

    with capture() as out:
        summarise(...)                       # prints as always
    write_fragment("batch", run_header() + fenced(out.getvalue()))
"""

from __future__ import annotations

import contextlib
import datetime
import io
import os
import platform
import re
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FRAGMENTS = ROOT / "docs" / "benchmarks"
_NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")


def fragment_path(name: str) -> Path:
    """Where the fragment ``name`` lives: ``docs/benchmarks/<name>.md``."""
    if not _NAME.fullmatch(name) or name == "index":
        raise ValueError(f"fragment name {name!r}: lower-case letters, digits, '_' and '-' only, not 'index'")
    return FRAGMENTS / f"{name}.md"


def write_fragment(name: str, markdown: str) -> Path:
    """Write ``markdown`` as the fragment ``name`` (atomically: a temporary file renamed) and
    return its path. The page that includes it gives the heading; a fragment holds no links."""
    path = fragment_path(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(markdown.rstrip("\n") + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path


def cpu_model() -> str:
    """The processor's model name (Linux ``/proc/cpuinfo``), else the platform's word for it."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine() -> str:
    """Cores, memory and processor of this machine, one line."""
    mem = ""
    with contextlib.suppress(OSError, ValueError, IndexError):
        kb = next(ln for ln in Path("/proc/meminfo").read_text().splitlines() if ln.startswith("MemTotal"))
        mem = f", {int(kb.split()[1]) / 1024**2:.0f} GiB"
    return f"{os.cpu_count()} cores{mem}, {cpu_model()}, Python {platform.python_version()}"


def run_header(*, command: str | None = None) -> str:
    """The lines every fragment starts with: date, command, machine, load average now."""
    cmd = command if command is not None else " ".join(["python", *sys.argv])
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    today = datetime.date.today().isoformat()
    return f"Run of {today}: `{cmd}`. Machine: {machine()}; load average at the end {load}.\n\n"


def fenced(text: str) -> str:
    """``text`` as a fenced block, shown as printed."""
    return f"```text\n{text.strip()}\n```\n"


class _Tee(io.StringIO):
    """Keeps what is written and passes it on to ``out``."""

    def __init__(self, out: object) -> None:
        super().__init__()
        self._out = out

    def write(self, s: str) -> int:
        self._out.write(s)  # type: ignore[attr-defined]
        return super().write(s)


@contextlib.contextmanager
def capture() -> Iterator[io.StringIO]:
    """Standard output inside the block is printed as usual and also kept (``.getvalue()``)."""
    tee = _Tee(sys.stdout)
    with contextlib.redirect_stdout(tee):
        yield tee
