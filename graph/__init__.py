"""Building, storing and loading road graphs."""

from graph.errors import ArtifactError, GraphError, InputError
from graph.road_graph import RoadGraph

__all__ = ["ArtifactError", "GraphError", "InputError", "RoadGraph"]
