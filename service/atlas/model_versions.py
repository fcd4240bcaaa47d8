"""Where a model version's files live, and loading its heads."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

from service.ml.heads import HeadsConfig, LoopNetHeads
from service.storage.models import ModelVersion


def initial_version_config(heads_config: HeadsConfig) -> dict[str, Any]:
    """The config row of an atlas's untrained first version (its heads rebuild from it)."""
    return {"heads": asdict(heads_config), "trained": False}


def index_file(index_dir: Path, atlas_id: int, version: int) -> Path:
    """The FAISS file of an atlas embedded by one model version."""
    return index_dir / f"atlas-{atlas_id}-v{version}.faiss"


def weights_file(models_dir: Path, atlas_id: int, version: int) -> Path:
    """The heads' weights of a trained version (relative paths in the row are under models_dir)."""
    return models_dir / f"atlas-{atlas_id}" / f"v{version}.pt"


def load_heads(version: ModelVersion, models_dir: Path) -> LoopNetHeads:
    """The heads of ``version``: from its weights file, or rebuilt untrained from its config."""
    if version.weights_path is None:
        return LoopNetHeads(HeadsConfig(**version.config["heads"])).eval()
    path = Path(version.weights_path)
    if not path.is_absolute():
        path = models_dir / path
    return LoopNetHeads.load(path)
