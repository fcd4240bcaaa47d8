"""Feature containers shared by every extractor, backbone and the feature store."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LocalFeatures:
    """Keypoints of one image, in the pixel coordinates of the image as uploaded (a large
    upload the service decoded shrunk has them mapped back).

    Attributes:
        keypoints: ``N x 2`` float32, (x, y).
        descriptors: ``N x D`` float32, each row L2-normalised.
        scores: ``N`` float32 detection scores.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.keypoints)
        if (
            self.keypoints.shape != (n, 2)
            or len(self.descriptors) != n
            or self.scores.shape != (n,)
        ):
            raise ValueError(
                f"inconsistent local features: keypoints {self.keypoints.shape}, "
                f"descriptors {self.descriptors.shape}, scores {self.scores.shape}"
            )

    @property
    def count(self) -> int:
        return len(self.keypoints)

    @classmethod
    def empty(cls, descriptor_dim: int) -> LocalFeatures:
        return cls(
            keypoints=np.zeros((0, 2), np.float32),
            descriptors=np.zeros((0, descriptor_dim), np.float32),
            scores=np.zeros((0,), np.float32),
        )


@dataclass
class FrameFeatures:
    """Everything LoopNet keeps of a frame, computed once by the CNNs.

    Attributes:
        local: the extractor's keypoints (kept for geometric verification).
        local_vector: ``D`` float32, the aggregated, L2-normalised local descriptor.
        global_vector: ``C`` float32, the L2-normalised backbone vector.
        image_size: (width, height) of the image as uploaded.
        thumbnail: a small JPEG of the image (service/ml/thumbnails.py), when made at decode.
    """

    local: LocalFeatures
    local_vector: np.ndarray
    global_vector: np.ndarray
    image_size: tuple[int, int]
    timings_ms: dict[str, float] = field(default_factory=dict)
    thumbnail: bytes | None = None

    def __post_init__(self) -> None:
        # What the feature store keeps (float16 descriptors and R): a frame embedded as it
        # arrives and the same frame re-embedded from the store give the same vector.
        self.global_vector = as_stored(self.global_vector)
        self.local = LocalFeatures(
            self.local.keypoints, as_stored(self.local.descriptors), self.local.scores
        )


def as_stored(values: np.ndarray) -> np.ndarray:
    """float32 values rounded to float16 precision, as the feature store keeps them."""
    return np.asarray(values, np.float32).astype(np.float16).astype(np.float32)
