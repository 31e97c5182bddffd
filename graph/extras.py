"""The ``prep`` extra: the libraries that map preparation and GIS files need, checked before use.

Loading a prepared map, matching and serving need none of them, so ``pip install mapmatch``
leaves them out; ``pip install 'mapmatch[prep]'`` adds them.
"""

from __future__ import annotations

import importlib.util

from graph.errors import MissingExtraError

PREP_MODULES = ("osmnx", "networkx", "geopandas", "pyogrio", "osmium", "pandas", "pyarrow")
"""The top-level modules the ``prep`` extra installs."""


def require_prep(*, needed_for: str, modules: tuple[str, ...] = PREP_MODULES) -> None:
    """Raise :class:`MissingExtraError` naming ``pip install 'mapmatch[prep]'`` when one of
    ``modules`` is not installed, without importing any."""
    for module in modules:
        try:
            spec = importlib.util.find_spec(module)
        except ImportError:  # an import hook that refuses the module: not installed here
            spec = None
        if spec is None:
            raise MissingExtraError(
                f"{needed_for} needs {module}, which is not installed: pip install 'mapmatch[prep]'"
            )
