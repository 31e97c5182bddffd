"""The gRPC service for fusion nodes: a thin layer over ``mapmatch``.

:class:`ServerConfig`, :func:`create_server` (builds), :func:`start_server` (builds and
starts; returns the runtime and its port) and :class:`MapMatchClient` are importable from
``service`` directly (loaded on first use, so ``import service`` stays light).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_API: dict[str, str] = {
    "ServerConfig": "service.config",
    "create_server": "service.server",
    "start_server": "service.server",
    "MapMatchClient": "service.client",
}
__all__ = ["MapMatchClient", "ServerConfig", "create_server", "start_server"]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'service' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


if TYPE_CHECKING:
    from service.client import MapMatchClient
    from service.config import ServerConfig
    from service.server import create_server, start_server
