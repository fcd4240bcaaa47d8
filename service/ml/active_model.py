"""A model version as queries and ingest use it: its heads, and its calibration when it has one.

Uncalibrated, the heads read the stored vectors (D as the score-weighted mean of the local
descriptors, R the backbone vector). Calibrated, they read the calibrated branches (D_w, R_w)
that :class:`~service.ml.calibration.Calibration` computes from the local descriptors and R;
untrained heads over those compute the calibration's fusion exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from service.ml.calibration import Calibration
from service.ml.features import FrameFeatures
from service.ml.heads import LoopNetHeads, SubmapPrediction
from service.ml.pipeline import embed_vectors


@dataclass(frozen=True)
class ActiveModel:
    heads: LoopNetHeads
    calibration: Calibration | None = None

    @property
    def dim(self) -> int:
        return self.heads.config.fused_dim

    def inputs(self, features: FrameFeatures) -> tuple[np.ndarray, np.ndarray]:
        """The heads' ``1 x D`` and ``1 x C`` inputs for one extracted frame."""
        if self.calibration is None:
            return features.local_vector[None], features.global_vector[None]
        return self.calibration.branch_vectors(
            [features.local.descriptors], [features.local.scores], features.global_vector[None]
        )

    def embed(self, features: FrameFeatures) -> np.ndarray:
        """The unit embedding of one extracted frame (ingest and query)."""
        row: np.ndarray = embed_vectors(self.heads, *self.inputs(features))[0]
        return row

    def embed_and_predict(
        self, features: FrameFeatures
    ) -> tuple[np.ndarray, SubmapPrediction | None]:
        """The unit embedding and the classification head's submap (None without one) of a
        query frame, from one computation of the heads' inputs (VLAD and whitenings run once)."""
        local, global_ = self.inputs(features)
        embedding: np.ndarray = embed_vectors(self.heads, local, global_)[0]
        prediction = self.heads.predict_submap(torch.from_numpy(local), torch.from_numpy(global_))
        return embedding, prediction

    @property
    def scores(self) -> bool:
        """Whether the version is calibrated against impostors (:meth:`score` gives scores)."""
        return self.calibration is not None and self.calibration.impostors is not None

    def score(self, similarities: np.ndarray) -> np.ndarray | None:
        """Calibrated scores of cosines; None when the version has no impostor model."""
        if self.calibration is None or not self.scores:
            return None
        return np.asarray(self.calibration.score(similarities), np.float64)
