"""Service configuration, read from the environment (no prefix; each field names its variable)."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Process settings.

    Environment variables: ``TRYON_DATA_DIR``, ``REDIS_URL``, ``TRYON_BODY_MODEL``,
    ``TRYON_MAX_UPLOAD_BYTES``. Fields may also be passed by name (``Settings(data_dir=...)``).
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
        description="Redis URL for the job queue/cache; None runs without Redis.",
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


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings (a FastAPI dependency: ``Depends(get_settings)``)."""
    return Settings()
