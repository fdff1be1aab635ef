"""Secrets never reach the logs: query-string parameters that carry credentials (the editing
WebSocket's ``?token=``, any ``key``) are redacted from every record of the server's loggers
(uvicorn's access and error logs, the service's own), whatever handler writes them."""
from __future__ import annotations

import logging
import re

# query parameters whose values are credentials
SECRET_PARAMS = ("token", "access_token", "api_key", "apikey", "key", "x-api-key", "authorization", "password")
REDACTED = "REDACTED"
_SECRET = re.compile(r"(?i)([?&;](?:" + "|".join(re.escape(p) for p in SECRET_PARAMS) + r")=)[^&;\s\"']*")
LOGGERS = ("", "uvicorn", "uvicorn.error", "uvicorn.access", "tryon")


def redact(text: str) -> str:
    """``text`` with the values of secret query parameters replaced by ``REDACTED``."""
    return _SECRET.sub(r"\1" + REDACTED, text)


class RedactSecrets(logging.Filter):
    """Rewrites a record's arguments (uvicorn's access formatter reads them one by one) and, for
    other records, its message, with secrets redacted."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and record.args:
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.msg, str):
            record.msg = redact(record.msg)
        return True


def install_redaction() -> None:
    """Adds :class:`RedactSecrets` to the server's loggers and to their handlers (a handler's
    filter also sees what child loggers propagate to it); idempotent."""
    for name in LOGGERS:
        logger = logging.getLogger(name)
        for target in (logger, *logger.handlers):
            if not any(isinstance(f, RedactSecrets) for f in target.filters):
                target.addFilter(RedactSecrets())
