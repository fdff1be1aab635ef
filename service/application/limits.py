"""Rate limits on the expensive routes (an avatar fit, a new customer, an upload): per client
(its IP address, as the server sees it behind trusted proxies) and, for requests with a valid
``X-API-Key``, per retailer instead. Shared across processes and hosts (Redis counters)."""
from __future__ import annotations

import math

from service.settings import Settings
from service.storage.limits import RateLimiter

from .errors import TooManyRequests

BURST_FACTOR = 2.0  # a client may send this many seconds' worth of requests at once


class Limits:
    def __init__(self, settings: Settings, rate_limiter: RateLimiter):
        self.settings = settings
        self.rate_limiter = rate_limiter

    def check(self, client: str | None, retailer: str | None) -> None:
        """Count one expensive request; :class:`TooManyRequests` (429 + Retry-After) when the
        client's or retailer's budget is spent."""
        s = self.settings
        if retailer is not None:
            bucket, rate, who = f"retailer:{retailer}", s.rate_limit_retailer, f"retailer '{retailer}'"
        else:
            bucket, rate, who = f"client:{client or 'unknown'}", s.rate_limit_client, "this client"
        if rate <= 0:
            return
        wait = self.rate_limiter.hit(bucket, rate, max(BURST_FACTOR * rate, 1.0))
        if wait > 0:
            raise TooManyRequests(f"rate limit of {rate:g} requests/s for {who} on this route reached; retry in "
                                  f"{math.ceil(wait)} s", retry_after=wait)
