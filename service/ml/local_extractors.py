"""Local keypoint extractors behind one interface (DISK now; XFeat joins the same registry).

Every extractor takes a decoded RGB frame and returns :class:`LocalFeatures` in the decoded
image's pixel coordinates, so stored keypoints serve geometric verification directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from service.ml import weights
from service.ml.features import LocalFeatures
from service.ml.images import resize_long_side, to_tensor


@dataclass(frozen=True)
class LocalExtractorConfig:
    """How a local extractor runs.

    Attributes:
        name: registry key ("disk").
        long_side: the image is resized (up or down) to this long side before extraction.
        max_keypoints: the strongest keypoints kept per frame.
        nms_window: non-maximum suppression window (the paper's 5).
    """

    name: str = "disk"
    long_side: int = 512
    max_keypoints: int = 1024
    nms_window: int = 5


class LocalExtractor(Protocol):
    config: LocalExtractorConfig
    descriptor_dim: int

    def extract(self, rgb: np.ndarray) -> LocalFeatures: ...


class DiskExtractor:
    """DISK (kornia, pretrained ``depth`` weights) at a configurable long side."""

    descriptor_dim = 128

    def __init__(self, config: LocalExtractorConfig) -> None:
        from kornia.feature import DISK

        self.config = config
        self.model = DISK()
        checkpoint: dict[str, Any] = weights.load_checkpoint(weights.DISK_DEPTH)
        self.model.load_state_dict(checkpoint["extractor"])
        self.model.eval()

    @torch.inference_mode()
    def extract(self, rgb: np.ndarray) -> LocalFeatures:
        height, width = rgb.shape[:2]
        image = resize_long_side(to_tensor(rgb), self.config.long_side)
        scale_y, scale_x = height / image.shape[-2], width / image.shape[-1]
        (found,) = self.model(
            image,
            n=self.config.max_keypoints,
            window_size=self.config.nms_window,
            pad_if_not_divisible=True,
        )
        if len(found.keypoints) == 0:
            return LocalFeatures.empty(self.descriptor_dim)
        keypoints = found.keypoints.numpy().astype(np.float32)
        keypoints[:, 0] = (keypoints[:, 0] + 0.5) * scale_x - 0.5
        keypoints[:, 1] = (keypoints[:, 1] + 0.5) * scale_y - 0.5
        descriptors = torch.nn.functional.normalize(found.descriptors, dim=-1).numpy()
        return LocalFeatures(
            keypoints=keypoints,
            descriptors=descriptors.astype(np.float32),
            scores=found.detection_scores.numpy().astype(np.float32),
        )


LOCAL_EXTRACTORS: dict[str, type[DiskExtractor]] = {"disk": DiskExtractor}


def build_local_extractor(config: LocalExtractorConfig) -> LocalExtractor:
    """Instantiate the extractor ``config.name`` with its pretrained weights."""
    try:
        cls = LOCAL_EXTRACTORS[config.name]
    except KeyError:
        raise ValueError(
            f"unknown local extractor {config.name!r}; choose one of {sorted(LOCAL_EXTRACTORS)}"
        ) from None
    return cls(config)
