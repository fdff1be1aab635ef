"""Who may open a customer: the holder of the customer's token (``Authorization: Bearer
<token>``, given once, by ``POST /v1/customers``; only its hash is stored) or the retailer the
customer belongs to (its ``X-API-Key``). Everyone else gets the answer an unknown id gets (404),
so customer ids cannot be probed."""
from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass

from service.records import Customer

TOKEN_BYTES = 32  # 256 random bits, URL-safe base64 (43 characters)


@dataclass(frozen=True)
class Credentials:
    """What a request presents: a customer token and/or the retailer of a valid API key."""

    token: str | None = None
    retailer: str | None = None


ANONYMOUS = Credentials()


def new_token() -> tuple[str, str]:
    """A fresh customer token and the hash that is stored in its place."""
    token = secrets.token_urlsafe(TOKEN_BYTES)
    return token, token_hash(token)


def token_hash(token: str) -> str:
    """SHA-256 of the token (hex): random 256-bit tokens need no salt or slow hash."""
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()


def may_open(record: Customer, creds: Credentials) -> bool:
    """Whether ``creds`` open ``record``: its token, or its owner's API key."""
    if creds.retailer is not None and record.owner is not None and hmac.compare_digest(
            creds.retailer.encode(), record.owner.encode()):
        return True
    if creds.token and record.token_hash:
        return hmac.compare_digest(token_hash(creds.token), record.token_hash)
    return False
