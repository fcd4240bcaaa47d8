"""From decoded frame to stored features and embeddings: the one path the API, CLI, worker and
evaluation harness share."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from service.ml.aggregation import aggregate_descriptors
from service.ml.backbones import GlobalBackbone, build_backbone
from service.ml.features import FrameFeatures
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.local_extractors import LocalExtractor, build_local_extractor
from service.ml.presets import ModelPreset, preset_signature


class FeaturePipeline:
    """Runs the CNNs of a preset once per frame: local extractor + global backbone."""

    def __init__(self, preset: ModelPreset) -> None:
        self.preset = preset
        self.local: LocalExtractor = build_local_extractor(preset.local)
        self.backbone: GlobalBackbone = build_backbone(preset.backbone)

    @property
    def signature(self) -> dict[str, Any]:
        """What the stored features mean; an atlas only accepts features of its signature."""
        return preset_signature(self.preset)

    def heads_config(self) -> HeadsConfig:
        """The untrained heads' config for this pipeline's features and preset."""
        return HeadsConfig(
            local_dim=self.local.descriptor_dim,
            global_dim=self.backbone.dim,
            alpha=self.preset.alpha,
        )

    def extract(self, rgb: np.ndarray) -> FrameFeatures:
        """Local features, their aggregate D and the backbone vector R of one RGB frame."""
        timings: dict[str, float] = {}
        start = time.perf_counter()
        local = self.local.extract(rgb)
        timings["local_features"] = _ms_since(start)
        start = time.perf_counter()
        global_vector = self.backbone.describe(rgb)
        timings["global_features"] = _ms_since(start)
        return FrameFeatures(
            local=local,
            local_vector=aggregate_descriptors(local.descriptors, local.scores),
            global_vector=global_vector,
            image_size=(rgb.shape[1], rgb.shape[0]),
            timings_ms=timings,
        )


@torch.inference_mode()
def embed_vectors(heads: LoopNetHeads, local: np.ndarray, global_: np.ndarray) -> np.ndarray:
    """``N x D`` and ``N x C`` stored vectors -> ``N x fused`` float32 unit embeddings.

    Works from stored features alone: re-embedding an atlas never runs a CNN.
    """
    if len(local) == 0:
        return np.zeros((0, heads.config.fused_dim), np.float32)
    embedded = heads.embed(torch.from_numpy(local), torch.from_numpy(global_))
    return embedded.numpy().astype(np.float32)


def _ms_since(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0
