"""Child processes that end with the server: the kernel's parent-death signal.

A build child (``LoadMap`` from an OSM/GIS source) and a batch worker process ask the kernel
(``prctl(PR_SET_PDEATHSIG)``) for a signal when the server process ends, however it ends
(SIGKILL included), and exit at once when the server had already ended before they asked.
"""

from __future__ import annotations

import ctypes
import os
import signal

__all__ = ["die_with_parent"]

PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int, *, sig: int = signal.SIGKILL) -> bool:
    """Have the kernel send ``sig`` to this process when its parent ends; end now (``sig``
    to itself) when ``parent`` is no longer the parent. Returns whether the kernel took the
    request (False off Linux: the callers also watch their parent)."""
    ok = False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        ok = libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os.kill(os.getpid(), sig)
    return ok
