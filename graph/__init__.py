"""Building, storing and loading road graphs."""

from mapmatch.graph.errors import ArtifactError, GraphError, InputError
from mapmatch.graph.road_graph import RoadGraph

__all__ = ["ArtifactError", "GraphError", "InputError", "RoadGraph"]
