"""The single-frame core of SeqSLAM (Milford & Wyeth, 2012): whole-image matching of small,
patch-normalised grey thumbnails by the sum of absolute differences (SAD).

Thumbnails are made with OpenCV (area resampling), patch normalisation in NumPy, and the
``Q x R`` SAD matrix by scikit-learn's ``pairwise_distances`` (Manhattan). The score is the
negated mean absolute difference, so higher means more similar. The sequence search of full
SeqSLAM is deliberately left out: every method here decides from a single frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class ThumbnailConfig:
    """Attributes: thumbnail width and height (OpenSeqSLAM's 64 x 32) and the side of the
    square patches normalised to zero mean and unit variance (OpenSeqSLAM's 8)."""

    width: int = 64
    height: int = 32
    patch: int = 8


class SadThumbnailBaseline:
    name = "seqslam-sad"
    label = "SeqSLAM single-frame (SAD)"

    def __init__(self, config: ThumbnailConfig) -> None:
        if config.width % config.patch or config.height % config.patch:
            raise ValueError(
                f"thumbnail {config.width}x{config.height} is not a whole number of "
                f"{config.patch}-pixel patches"
            )
        self.config = config
        self._references: np.ndarray | None = None

    def settings(self) -> dict[str, Any]:
        return asdict(self.config)

    def describe(self, rgb: np.ndarray) -> np.ndarray:
        """The patch-normalised thumbnail, flattened: ``width * height`` float32."""
        import cv2

        c = self.config
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        small = cv2.resize(grey, (c.width, c.height), interpolation=cv2.INTER_AREA)
        patches = small.astype(np.float32).reshape(
            c.height // c.patch, c.patch, c.width // c.patch, c.patch
        )
        mean = patches.mean(axis=(1, 3), keepdims=True)
        std = patches.std(axis=(1, 3), keepdims=True)
        normalised = np.where(std > 1e-6, (patches - mean) / np.maximum(std, 1e-6), 0.0)
        return normalised.reshape(-1).astype(np.float32)

    def fit(self, references: list[np.ndarray]) -> None:
        self._references = np.stack(references)

    def score(self, queries: list[np.ndarray]) -> np.ndarray:
        from sklearn.metrics import pairwise_distances

        if self._references is None:
            raise RuntimeError("fit on the reference frames first")
        sad = pairwise_distances(np.stack(queries), self._references, metric="manhattan")
        return (-sad / self._references.shape[1]).astype(np.float32)
