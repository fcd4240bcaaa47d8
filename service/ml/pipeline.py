"""From decoded frame to stored features and embeddings: the one path the API, CLI, worker and
evaluation harness share."""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Literal, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from service.ml.aggregation import aggregate_descriptors
from service.ml.backbones import GlobalBackbone, build_backbone
from service.ml.batching import MicroBatcher
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.fusion import weighted_branches
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.local_extractors import LocalExtractor, build_local_extractor
from service.ml.precision import Precision, resolve_precision
from service.ml.presets import FeatureSignature, ModelPreset


class FeaturePipeline:
    """Runs the CNNs of a preset once per frame: local extractor + global backbone.

    ``precision`` is "auto" (bf16 where the CPU computes it natively), "fp32" or "bf16"; it is
    not part of the signature: bf16 features stay within the accuracy guard of fp32 ones, so an
    atlas mixes them. With ``batch_window_ms`` > 0, concurrent :meth:`extract` calls arriving
    within that window run as one batch of up to ``max_batch`` frames. With
    ``parallel_branches`` on, the global backbone runs in a second thread while the local
    extractor runs (see :func:`branches_in_parallel`).
    """

    def __init__(
        self,
        preset: ModelPreset,
        precision: str = "fp32",
        batch_window_ms: float = 0.0,
        max_batch: int = 8,
        parallel_branches: ParallelBranches = "auto",
    ) -> None:
        self.preset = preset
        self.precision: Precision = resolve_precision(precision)
        self.local: LocalExtractor = build_local_extractor(preset.local, self.precision)
        self.backbone: GlobalBackbone = build_backbone(preset.backbone, self.precision)
        self.batcher: MicroBatcher[np.ndarray, FrameFeatures] = MicroBatcher(
            self.extract_batch, batch_window_ms / 1000.0, max_batch
        )
        self._branch_pool = (
            ThreadPoolExecutor(1, thread_name_prefix="loopnet-global-branch")
            if branches_in_parallel(parallel_branches)
            else None
        )
        # Side by side only while this is the one frame being extracted: under load every core
        # already runs a frame, and a second thread per frame only adds hand-offs (measured
        # with 8 robots ingesting: benchmarks/RESULTS.md).
        self._running = 0
        self._running_lock = threading.Lock()

    @property
    def parallel_branches(self) -> bool:
        """Whether the two CNNs of a frame run side by side."""
        return self._branch_pool is not None

    @property
    def signature(self) -> FeatureSignature:
        """What the stored features mean; an atlas only accepts features of its signature."""
        return self.preset.signature

    @property
    def working_side(self) -> int:
        """The longest side either network resizes a frame to: a larger upload is decoded
        shrunk (see :func:`service.ml.images.decode_frame`)."""
        return max(self.preset.local.long_side, self.preset.backbone.input_size)

    def heads_config(self) -> HeadsConfig:
        """The untrained heads' config for this pipeline's features and preset."""
        return HeadsConfig(
            local_dim=self.local.descriptor_dim,
            global_dim=self.backbone.dim,
            alpha=self.preset.alpha,
        )

    def extract(self, rgb: np.ndarray) -> FrameFeatures:
        """Local features, their aggregate D and the backbone vector R of one RGB frame
        (batched with concurrent calls when batching is on)."""
        return self.batcher.submit(rgb)

    def extract_batch(self, rgbs: list[np.ndarray]) -> list[FrameFeatures]:
        """:meth:`extract` of several frames, each network run once per batch (frames of
        different sizes are grouped by working size). Timings are the whole batch's."""
        with self._running_lock:
            self._running += 1
            side_by_side = self._branch_pool is not None and self._running == 1
        try:
            if side_by_side:
                assert self._branch_pool is not None
                described = self._branch_pool.submit(
                    self._describe_in_branch_thread, rgbs, torch.get_num_threads()
                )
                local, local_ms = self._extract_timed(rgbs)
                global_vectors, global_ms = described.result()
            else:
                local, local_ms = self._extract_timed(rgbs)
                global_vectors, global_ms = self._describe_timed(rgbs)
        finally:
            with self._running_lock:
                self._running -= 1
        timings = {"local_features": local_ms, "global_features": global_ms}
        return [
            FrameFeatures(
                local=one,
                local_vector=aggregate_descriptors(one.descriptors, one.scores),
                global_vector=vector,
                image_size=(rgb.shape[1], rgb.shape[0]),
                timings_ms=dict(timings),
            )
            for rgb, one, vector in zip(rgbs, local, global_vectors, strict=True)
        ]

    def _extract_timed(self, rgbs: list[np.ndarray]) -> tuple[list[LocalFeatures], float]:
        start = time.perf_counter()
        return self.local.extract_batch(rgbs), _ms_since(start)

    def _describe_in_branch_thread(
        self, rgbs: list[np.ndarray], threads: int
    ) -> tuple[np.ndarray, float]:
        """The backbone in the side-by-side thread, with the caller's intra-op threads: a new
        thread's OpenMP team otherwise takes every core (oneDNN reads the thread's own count),
        oversubscribing them and rounding differently from the caller's thread."""
        torch.set_num_threads(threads)
        return self._describe_timed(rgbs)

    def _describe_timed(self, rgbs: list[np.ndarray]) -> tuple[np.ndarray, float]:
        start = time.perf_counter()
        return self.backbone.describe_batch(rgbs), _ms_since(start)


ParallelBranches = Literal["auto", "on", "off"]


def branches_in_parallel(setting: ParallelBranches) -> bool:
    """Whether a frame's local extractor and global backbone run side by side, each in its
    own thread: "auto" = when the intra-op threads of both leave no core idle beside the other
    and oversubscribe none (torch threads x 2 <= cores), e.g. one torch thread on 2 cores,
    where a fast-preset query's CNNs then take the longer branch's time instead of the sum."""
    if setting != "auto":
        return setting == "on"
    return torch.get_num_threads() * 2 <= (os.cpu_count() or 1)


@torch.inference_mode()
def embed_vectors(
    heads: LoopNetHeads, local: np.ndarray, global_: np.ndarray, precision: Precision = "fp32"
) -> np.ndarray:
    """``N x D`` and ``N x C`` stored vectors -> ``N x fused`` float32 unit embeddings.

    Works from stored features alone: re-embedding an atlas never runs a CNN. In bf16 only the
    matrix products run in bf16 (:func:`embed_bf16`); the element-wise work stays float32.
    """
    if len(local) == 0:
        return np.zeros((0, heads.config.fused_dim), np.float32)
    if precision == "bf16":
        return embed_bf16(heads, torch.from_numpy(local), torch.from_numpy(global_)).numpy()
    embedded = heads.embed(torch.from_numpy(local), torch.from_numpy(global_))
    return embedded.numpy().astype(np.float32)


# Rows embedded at a time in bf16: a block's converted inputs and products stay in the cache
# (1M frames at embed_dim 256: 3.4 CPU s in blocks of 2,048 rows, 5.9 s in chunks of 100k).
EMBED_BLOCK = 2048


def embed_bf16(heads: LoopNetHeads, local: torch.Tensor, global_: torch.Tensor) -> torch.Tensor:
    """``heads.embed`` with its matrix products in bf16 (float32 accumulation and element-wise
    steps): bf16 element-wise arithmetic on the CPU is slower than the products it saves.

    Block by block (:data:`EMBED_BLOCK` rows), D and R are converted side by side into one bf16
    block and fused by one product with the stacked, alpha-weighted projections."""
    fused_weight, first, last, bias = _bf16_weights(heads)
    out = torch.empty((len(local), heads.config.fused_dim), dtype=torch.float32)
    block = torch.empty((min(EMBED_BLOCK, len(local)), fused_weight.shape[0]), dtype=torch.bfloat16)
    split = local.shape[1]
    for start in range(0, len(local), EMBED_BLOCK):
        stop = min(start + EMBED_BLOCK, len(local))
        inputs = block[: stop - start]
        inputs[:, :split].copy_(local[start:stop])
        inputs[:, split:].copy_(global_[start:stop])
        fused = torch.mm(inputs, fused_weight).float().add_(bias)
        hidden = torch.mm(fused.bfloat16(), first.weight).float().add_(first.bias).relu_()
        fused += torch.mm(hidden.bfloat16(), last.weight).float().add_(last.bias)
        out[start:stop] = F.normalize(fused, dim=-1)
    return out


class _Bf16Linear(NamedTuple):
    weight: torch.Tensor  # in x out, bf16
    bias: torch.Tensor  # float32


def _bf16_weights(
    heads: LoopNetHeads,
) -> tuple[torch.Tensor, _Bf16Linear, _Bf16Linear, torch.Tensor]:
    """The heads' products as :func:`embed_bf16` runs them: ``[alpha P_D, (1 - alpha) P_R]``
    stacked (``local + global x fused``), the similarity MLP's two layers, the fusion bias."""
    fusion, mlp = heads.fusion, heads.similarity.mlp
    first, last = mlp[0], mlp[2]
    assert isinstance(first, nn.Linear) and isinstance(last, nn.Linear)
    stacked = weighted_branches(
        fusion.project_local.weight, fusion.project_global.weight, fusion.alpha
    )

    def layer(linear: nn.Linear) -> _Bf16Linear:
        return _Bf16Linear(linear.weight.t().bfloat16().contiguous(), linear.bias.float())

    return stacked.t().bfloat16().contiguous(), layer(first), layer(last), fusion.bias.float()


def _ms_since(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0
