"""Errors raised by the matchers: one small hierarchy."""


class MatchError(Exception):
    """Base class of every error raised by the ``mapmatch`` package."""


class ValidationError(MatchError, ValueError):
    """An input value is invalid. ``field`` names it, as the gRPC status and CLI report it."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.reason = message


class ConfigError(MatchError, ValueError):
    """A matcher configuration value is invalid."""
