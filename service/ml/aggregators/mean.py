"""The score-weighted mean aggregator (what every frame is stored with), kept for ablation."""

from __future__ import annotations

import numpy as np

from service.ml.aggregation import aggregate_descriptors


class MeanAggregator:
    """Score-weighted mean, signed square root, L2 norm: nothing to learn."""

    name = "mean"

    def __init__(self, descriptor_dim: int) -> None:
        self.descriptor_dim = descriptor_dim

    @property
    def dim(self) -> int:
        return self.descriptor_dim

    def aggregate(self, descriptors: np.ndarray, scores: np.ndarray) -> np.ndarray:
        return aggregate_descriptors(descriptors.astype(np.float32, copy=False), scores)

    def state(self) -> dict[str, np.ndarray]:
        return {"descriptor_dim": np.array(self.descriptor_dim)}
