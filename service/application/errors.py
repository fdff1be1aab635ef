"""What a use case refuses, and why. The routes map each to an HTTP status (``service.api.errors``);
the jobs record the message as the job's or record's one-line ``error``."""
from __future__ import annotations

from typing import Any


class AppError(Exception):
    """Base class: ``message`` is meant for the API's caller."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class NotFound(AppError):
    """An unknown id (404)."""


class Conflict(AppError):
    """The record exists but is not in a state that allows it (409): a customer still being
    fitted, a garment still being built, a record made with another body model."""


class Forbidden(AppError):
    """The caller may not do this to this record (403)."""


class Invalid(AppError):
    """Unusable input (422): ``loc`` as in a 422 detail entry (``("body", "mesh")``)."""

    def __init__(self, loc: tuple[Any, ...], message: str):
        super().__init__(message)
        self.loc = loc


class TooLarge(AppError):
    """The input needs more memory or work than this server allows for one request (413)."""


class TooManyRequests(AppError):
    """The caller went over its rate limit (429); ``retry_after``: seconds until it may retry."""

    def __init__(self, message: str, retry_after: float):
        super().__init__(message)
        self.retry_after = retry_after


class Unavailable(AppError):
    """The service cannot answer now (503): storage unreachable or the server is saturated;
    ``retry_after``: seconds after which a retry is likely to succeed."""

    def __init__(self, message: str, retry_after: float = 1.0):
        super().__init__(message)
        self.retry_after = retry_after
