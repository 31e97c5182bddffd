"""Errors raised by map preparation and loading: one small hierarchy."""


class GraphError(Exception):
    """Base class of every error raised by the ``graph`` package."""


class InputError(GraphError):
    """The road data given cannot be used (missing, unknown format, corrupt, no roads, bad CRS)."""


class ArtifactError(GraphError):
    """A prepared map artifact is missing, of an unsupported version, or fails its checksum."""


class MissingExtraError(GraphError, ImportError):
    """A dependency of map preparation (the ``prep`` extra) is not installed; the message says
    ``pip install 'mapmatch[prep]'``."""
