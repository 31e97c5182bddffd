"""Building, storing and loading road graphs.

:class:`RoadGraph` loads on first use: importing ``graph`` (or a light module of it, as
:mod:`graph.kernel_cache`) defines no compiled kernel, so the kernel mode can still be chosen
(:mod:`mapmatch.kernels`).
"""

from typing import TYPE_CHECKING, Any

from graph.errors import ArtifactError, GraphError, InputError

if TYPE_CHECKING:
    from graph.road_graph import RoadGraph

__all__ = ["ArtifactError", "GraphError", "InputError", "RoadGraph"]


def __getattr__(name: str) -> Any:
    if name == "RoadGraph":
        from graph.road_graph import RoadGraph

        return RoadGraph
    raise AttributeError(f"module 'graph' has no attribute {name!r}")
