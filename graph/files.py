"""Atomic file writes (a temporary file beside the target, renamed onto it on success) and
owned read-only descriptors."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def atomic_path(path: str | os.PathLike[str], *, keep_suffix: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` when the block succeeds.

    On any exception the temporary file is removed and ``path`` is left as it was, so a reader
    never sees a half-written file. ``keep_suffix`` keeps the target's suffix on the temporary
    name, for writers that choose their format from it (pyogrio, matplotlib). The file gets
    the permissions a plain ``open`` would give it (the umask's).
    """
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(
        prefix=f".{dest.name}.", suffix=dest.suffix if keep_suffix else ".tmp", dir=dest.parent
    )
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)


class ReadOnlyFile:
    """An open read-only file descriptor, owned: closed by :meth:`close` or when collected.

    Whatever holds it (a loaded map, a batch match in flight) keeps the file it was opened
    on, whatever later happens to the name it was opened by (replaced, re-prepared, removed).

    Parameters
    ----------
    fd
        The descriptor; the object owns it from now on.
    name
        How the file is named in messages (never needed to read it).
    """

    __slots__ = ("_fd", "name")

    def __init__(self, fd: int, *, name: str) -> None:
        self._fd = fd
        self.name = name

    def fileno(self) -> int:
        """The descriptor (ValueError once closed)."""
        if self._fd < 0:
            raise ValueError(f"{self.name}: file closed")
        return self._fd

    @property
    def closed(self) -> bool:
        return self._fd < 0

    def close(self) -> None:
        fd, self._fd = self._fd, -1
        if fd >= 0:
            os.close(fd)

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter exit os may be gone
            self.close()

    def __reduce__(self) -> Any:
        raise TypeError("a ReadOnlyFile is passed to another process as a descriptor, not pickled")

    def __repr__(self) -> str:
        return f"ReadOnlyFile({self.name!r}, fd={self._fd})"
