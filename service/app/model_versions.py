"""Where a model version's files live, and loading its heads."""

from __future__ import annotations

import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from service.ml.calibration import Calibration
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.storage.models import ModelVersion


@dataclass(frozen=True)
class VersionConfig:
    """The ``config`` JSON of a model version row, read and written only through here.

    ``heads`` rebuilds the untrained heads; ``training`` and ``job_id`` say how a trained
    version was made. ``calibration``, when the version embeds through one: ``path`` of its
    ``.npz`` (relative to the models directory), ``version`` (the model version whose job
    fitted it; retrained versions keep it) and ``frames_at_fit``.
    """

    heads: HeadsConfig
    trained: bool = False
    training: dict[str, Any] | None = None
    job_id: int | None = None
    calibration: dict[str, Any] | None = None

    @classmethod
    def of(cls, version: ModelVersion) -> VersionConfig:
        raw = version.config
        return cls(
            heads=HeadsConfig(**raw["heads"]),
            trained=bool(raw.get("trained")),
            training=raw.get("training"),
            job_id=raw.get("job_id"),
            calibration=raw.get("calibration"),
        )

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"heads": asdict(self.heads), "trained": self.trained}
        if self.training is not None:
            out["training"] = self.training
        if self.job_id is not None:
            out["job_id"] = self.job_id
        if self.calibration is not None:
            out["calibration"] = self.calibration
        return out


def initial_version_config(heads_config: HeadsConfig) -> dict[str, Any]:
    """The config row of an atlas's untrained first version (its heads rebuild from it)."""
    return VersionConfig(heads_config).to_json()


def index_file(index_dir: Path, atlas_id: int, version: int) -> Path:
    """The FAISS file of an atlas embedded by one model version."""
    return index_dir / f"atlas-{atlas_id}-v{version}.faiss"


def atlas_models_dir(models_dir: Path, atlas_id: int) -> Path:
    """The folder of an atlas's trained weights files."""
    return models_dir / f"atlas-{atlas_id}"


def weights_file(models_dir: Path, atlas_id: int, version: int) -> Path:
    """The heads' weights of a trained version."""
    return atlas_models_dir(models_dir, atlas_id) / f"v{version}.pt"


def row_weights_path(models_dir: Path, atlas_id: int, version: int) -> str:
    """What a version's row records for its weights file: the path under ``models_dir``."""
    return str(weights_file(models_dir, atlas_id, version).relative_to(models_dir))


def weights_of(version: ModelVersion, models_dir: Path) -> Path | None:
    """The weights file a version's row names (relative paths are under ``models_dir``); None
    for an untrained version."""
    if version.weights_path is None:
        return None
    path = Path(version.weights_path)
    return path if path.is_absolute() else models_dir / path


def calibration_file(models_dir: Path, atlas_id: int, version: int) -> Path:
    """The calibration of a model version, beside its weights."""
    return models_dir / f"atlas-{atlas_id}" / f"v{version}-calibration.npz"


def load_calibration(version: ModelVersion, models_dir: Path) -> Calibration | None:
    """The calibration ``version`` embeds through, or None (the uncalibrated blend)."""
    calibration = VersionConfig.of(version).calibration
    if calibration is None:
        return None
    path = Path(calibration["path"])
    return Calibration.load(path if path.is_absolute() else models_dir / path)


def load_heads(version: ModelVersion, models_dir: Path) -> LoopNetHeads:
    """The heads of ``version``: from its weights file, or rebuilt untrained from its config."""
    path = weights_of(version, models_dir)
    if path is None:
        return LoopNetHeads(VersionConfig.of(version).heads).eval()
    return LoopNetHeads.load(path)


def remove_atlas_files(index_dir: Path, models_dir: Path, atlas_id: int) -> None:
    """Delete every index file and weights file of an atlas (its rows are deleted apart)."""
    for path in index_dir.glob(f"atlas-{atlas_id}-*.faiss"):
        path.unlink(missing_ok=True)
    shutil.rmtree(atlas_models_dir(models_dir, atlas_id), ignore_errors=True)
