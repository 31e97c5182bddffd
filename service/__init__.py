"""The gRPC service for fusion nodes: a thin layer over ``mapmatch``."""
