"""Settings from ``LOOPNET_*`` environment variables (pydantic-settings), built on demand."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.ml.images import ImageLimits
from service.ml.presets import ModelPreset, resolve_preset


class Settings(BaseSettings):
    """Everything configurable; the defaults run a single-machine service with no set-up."""

    model_config = SettingsConfigDict(env_prefix="LOOPNET_", env_file=None, extra="ignore")

    data_dir: Path = Field(Path("./loopnet-data"), description="Database, indexes and models.")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default: a SQLite file in the data directory."
    )
    model_preset: str = Field(
        "default", description="'default' (CPU-sized), 'fast' (XFeat, tens of ms) or 'paper'."
    )
    backbone: str | None = Field(None, description="Override the preset's global backbone.")
    long_side: int | None = Field(None, ge=32, le=4096, description="Override DISK's long side.")
    max_keypoints: int | None = Field(None, ge=16, le=16384, description="Override top-n.")
    alpha: float | None = Field(None, ge=0.0, le=1.0, description="Override the fusion weight.")
    loop_closure_threshold: float = Field(
        0.90, ge=-1.0, le=1.0, description="Cosine similarity at or above which a match is a loop."
    )
    max_upload_bytes: int = Field(20 * 1024 * 1024, ge=1024)
    max_image_pixels: int = Field(40_000_000, ge=1024)
    max_k: int = Field(100, ge=1, le=10_000, description="Largest k a query may ask for.")
    model_poll_seconds: float = Field(
        1.0, ge=0.0, description="How often a process checks for a newly activated model version."
    )
    redis_url: str | None = Field(
        None, description="Redis URL for the job queue; default: a SQLite queue in the data dir."
    )
    queue_name: str = Field("loopnet", description="Queue name (Redis key prefix / SQLite table).")
    torch_threads: int | None = Field(None, ge=1, description="torch intra-op threads.")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'loopnet.sqlite3').resolve()}"

    @property
    def index_dir(self) -> Path:
        return self.data_dir / "indexes"

    @property
    def models_dir(self) -> Path:
        return self.data_dir / "models"

    @property
    def queue_path(self) -> Path:
        return self.data_dir / "queue.sqlite3"

    @property
    def image_limits(self) -> ImageLimits:
        return ImageLimits(max_bytes=self.max_upload_bytes, max_pixels=self.max_image_pixels)

    def preset(self) -> ModelPreset:
        return resolve_preset(
            self.model_preset,
            backbone=self.backbone,
            long_side=self.long_side,
            max_keypoints=self.max_keypoints,
            alpha=self.alpha,
        )
