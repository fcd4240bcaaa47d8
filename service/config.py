"""Settings from ``LOOPNET_*`` environment variables (pydantic-settings), built on demand."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import model_validator
from pydantic_settings import SettingsConfigDict

from service.config_boundary import (
    AccessSettings,
    BoundarySettings,
    InferenceSettings,
    LimitSettings,
)
from service.config_sections import (
    DecisionSettings,
    JobSettings,
    ModelSettings,
    SequenceSettings,
    StorageSettings,
)
from service.domain.limits import ArchiveLimits
from service.ml.image_limits import ImageLimits

if TYPE_CHECKING:  # the ML modules import torch; the keys and snapshot commands must not
    from service.ml.presets import ModelPreset


class Settings(
    StorageSettings,
    ModelSettings,
    DecisionSettings,
    SequenceSettings,
    JobSettings,
    InferenceSettings,
    LimitSettings,
    AccessSettings,
    BoundarySettings,
):
    """Everything configurable; the defaults run a single-machine service with no set-up."""

    model_config = SettingsConfigDict(env_prefix="LOOPNET_", env_file=None, extra="ignore")

    @model_validator(mode="after")
    def _workers_fill_batches(self) -> Settings:
        if self.inference_workers is None and self.batch_window_ms > 0 and self.max_batch > 1:
            from service.concurrency import default_workers

            self.inference_workers = min(256, default_workers(self.torch_threads) * self.max_batch)
        return self

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'loopnet.sqlite3').resolve()}"

    @property
    def milestones(self) -> tuple[int, ...]:
        """The calibration milestones, ascending (empty: automatic calibration off)."""
        text = self.calibration_milestones.strip()
        return tuple(sorted({int(v) for v in text.split(",")})) if text else ()

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
    def host_names(self) -> tuple[str, ...]:
        """The Host names the API answers to (see ``allowed_hosts``), lower case."""
        names = {"localhost", "127.0.0.1", "::1"}
        if self.host not in ("0.0.0.0", "::", ""):
            names.add(self.host.lower())
        names.update(n.strip().lower() for n in self.allowed_hosts.split(",") if n.strip())
        return tuple(sorted(names))

    @property
    def proxies(self) -> list[str]:
        """The trusted proxies as a list (empty: none)."""
        return [p.strip() for p in self.trusted_proxies.split(",") if p.strip()]

    @property
    def image_limits(self) -> ImageLimits:
        return ImageLimits(max_bytes=self.max_upload_bytes, max_pixels=self.max_image_pixels)

    @property
    def snapshot_limits(self) -> ArchiveLimits:
        return ArchiveLimits(self.snapshot_max_member_bytes, self.snapshot_max_total_bytes)

    def pipeline_options(self) -> tuple[str, float, int, Literal["auto", "on", "off"]]:
        """FeaturePipeline's precision, batch_window_ms, max_batch and parallel_branches."""
        return self.precision, self.batch_window_ms, self.max_batch, self.parallel_branches

    def preset(self) -> ModelPreset:
        from service.ml.presets import resolve_preset

        return resolve_preset(
            self.model_preset,
            backbone=self.backbone,
            long_side=self.long_side,
            max_keypoints=self.max_keypoints,
            alpha=self.alpha,
        )
