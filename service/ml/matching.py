"""Local-feature matchers behind one interface: LightGlue (DISK) and mutual nearest neighbours.

A matcher takes two frames' :class:`LocalFeatures` (keypoints in decoded-image pixels, the
layout the feature store keeps) with their image sizes and returns index pairs into them.
``mnn`` works for any descriptor (DISK 128-d, XFeat 64-d); ``lightglue`` is LightGlue with
the DISK weights (128-d descriptors only).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol

import numpy as np
import torch

from service.ml import weights
from service.ml.features import LocalFeatures


@dataclass(frozen=True)
class Matches:
    """Tentative correspondences between two frames.

    Attributes:
        pairs: ``K x 2`` int64, (index in frame A, index in frame B).
        scores: ``K`` float32 match confidences (higher is better).
    """

    pairs: np.ndarray
    scores: np.ndarray

    @property
    def count(self) -> int:
        return len(self.pairs)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros((0, 2), np.int64), np.zeros(0, np.float32))


class Matcher(Protocol):
    name: str

    def match(
        self,
        a: LocalFeatures,
        size_a: tuple[int, int],
        b: LocalFeatures,
        size_b: tuple[int, int],
    ) -> Matches: ...

    def match_many(
        self,
        a: LocalFeatures,
        size_a: tuple[int, int],
        candidates: Sequence[tuple[LocalFeatures, tuple[int, int]]],
    ) -> list[Matches]:
        """``a`` matched with each ``(features, image size)`` candidate, in order."""
        ...


class MutualNearestNeighbours:
    """Mutual nearest neighbours on cosine similarity with Lowe's ratio test.

    A pair (i, j) is kept when j is i's nearest neighbour and i is j's, and the distance to j is
    below ``ratio`` times the distance to i's second-nearest neighbour (L2 distance of unit
    descriptors). Works for every descriptor size; descriptors are re-normalised (the store
    keeps them as float16).
    """

    name = "mnn"

    def __init__(self, ratio: float = 0.9) -> None:
        if not 0.0 < ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        self.ratio = ratio

    def match(
        self,
        a: LocalFeatures,
        size_a: tuple[int, int],
        b: LocalFeatures,
        size_b: tuple[int, int],
    ) -> Matches:
        return self.match_many(a, size_a, [(b, size_b)])[0]

    def match_many(
        self,
        a: LocalFeatures,
        size_a: tuple[int, int],
        candidates: Sequence[tuple[LocalFeatures, tuple[int, int]]],
    ) -> list[Matches]:
        """``a`` matched with each candidate, from one product of ``a``'s descriptors with all
        the candidates' stacked (one matrix product instead of one per candidate); image
        sizes do not matter to MNN."""
        return self._match_descriptors(a, [b for b, _ in candidates])

    def _match_descriptors(
        self, a: LocalFeatures, candidates: Sequence[LocalFeatures]
    ) -> list[Matches]:
        for b in candidates:
            if b.count and a.count and a.descriptors.shape[1] != b.descriptors.shape[1]:
                raise ValueError(
                    f"descriptor sizes differ: {a.descriptors.shape[1]} vs {b.descriptors.shape[1]}"
                )
        found = [Matches.empty() for _ in candidates]
        present = [i for i, b in enumerate(candidates) if b.count > 0]
        if a.count == 0 or not present:
            return found
        da = _unit(a.descriptors)
        counts = [candidates[i].count for i in present]
        stacked = _unit(np.concatenate([candidates[i].descriptors for i in present]))
        product = torch.from_numpy(da) @ torch.from_numpy(stacked).T
        similarity = product.numpy()  # M x (all candidates' keypoints)
        # Per stacked column its best similarity: a column-wise max runs at memory speed where
        # a column-wise argmax (torch's or numpy's) is an order of magnitude slower; a row is
        # mutual when its best reaches its column's.
        column_best = product.amax(dim=0).numpy()
        # Each candidate's columns side by side in one M x K x Nmax block, so the row-wise
        # best and second best of every candidate come from one pass each: a view when all
        # candidates have as many keypoints (the usual case), else padded with -inf.
        rows = np.arange(len(da))
        starts = np.cumsum([0, *counts])
        if len(set(counts)) == 1:
            block = similarity.reshape(len(da), len(present), counts[0])
        else:
            block = np.full((len(da), len(present), max(counts)), -np.inf, np.float32)
            for k, (start, end) in enumerate(itertools.pairwise(starts)):
                block[:, k, : end - start] = similarity[:, start:end]
        nearest_ab = block.argmax(axis=2)  # M x K, column within the candidate
        best = np.take_along_axis(block, nearest_ab[..., None], axis=2)[..., 0]
        mutual = best == column_best[starts[:-1][None, :] + nearest_ab]
        mutual = _first_row_per_column(mutual, nearest_ab)
        np.put_along_axis(block, nearest_ab[..., None], -np.inf, axis=2)  # may write similarity
        second = block.max(axis=2)
        distance = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0))
        second_distance = np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))
        single = np.array(counts) == 1  # no second neighbour: no ratio test
        passes = (distance < self.ratio * second_distance) | single[None, :]
        for k, i in enumerate(present):
            keep = mutual[:, k] & passes[:, k]
            pairs = np.stack([rows[keep], nearest_ab[keep, k]], axis=1).astype(np.int64)
            found[i] = Matches(pairs, best[keep, k].astype(np.float32))
        return found


class LightGlueMatcher:
    """LightGlue (kornia) with the DISK weights, loaded from the weights cache only."""

    name = "lightglue"
    descriptor_dim = 128

    def __init__(self, filter_threshold: float = 0.1) -> None:
        from kornia.feature import LightGlue

        # Raises WeightsUnavailable (offline, file missing) before kornia could try a download;
        # kornia then finds the file in the same hub cache.
        weights.ensure_weights(weights.LIGHTGLUE_DISK)
        self.model = LightGlue("disk", filter_threshold=filter_threshold).eval()

    @torch.inference_mode()
    def match(
        self,
        a: LocalFeatures,
        size_a: tuple[int, int],
        b: LocalFeatures,
        size_b: tuple[int, int],
    ) -> Matches:
        for features in (a, b):
            if features.count and features.descriptors.shape[1] != self.descriptor_dim:
                raise ValueError(
                    f"LightGlue-DISK needs {self.descriptor_dim}-d descriptors, got "
                    f"{features.descriptors.shape[1]}-d; use the 'mnn' matcher for this extractor"
                )
        if a.count < 2 or b.count < 2:
            return Matches.empty()
        data: dict[str, Any] = {
            "image0": _lightglue_input(a, size_a),
            "image1": _lightglue_input(b, size_b),
        }
        out = self.model(data)
        pairs = out["matches"][0].numpy().astype(np.int64).reshape(-1, 2)
        scores = out["scores"][0].float().numpy().astype(np.float32).reshape(-1)
        return Matches(pairs, scores)

    def match_many(
        self,
        a: LocalFeatures,
        size_a: tuple[int, int],
        candidates: Sequence[tuple[LocalFeatures, tuple[int, int]]],
    ) -> list[Matches]:
        """One LightGlue pass per candidate (the network attends across each pair)."""
        return [self.match(a, size_a, b, size_b) for b, size_b in candidates]


def _first_row_per_column(mutual: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """``mutual`` (M x K) keeping, of the rows that claim one column of a candidate, only the
    first, as a column-wise argmax picks it: two rows reach a column's best exactly only when
    their descriptors are equal (duplicated keypoints)."""
    kept = np.zeros_like(mutual)
    for k in range(mutual.shape[1]):
        rows = np.flatnonzero(mutual[:, k])
        _, first = np.unique(nearest[rows, k], return_index=True)
        kept[rows[first], k] = True
    return kept


def _unit(descriptors: np.ndarray) -> np.ndarray:
    d = descriptors.astype(np.float32)
    unit: np.ndarray = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return unit


def _lightglue_input(features: LocalFeatures, size: tuple[int, int]) -> dict[str, torch.Tensor]:
    # LightGlue normalises keypoints by the image size and refuses any outside the image:
    # clip the sub-pixel overshoot that mapping back to decoded pixels can give at the border.
    width, height = size
    keypoints = np.clip(features.keypoints, 0.0, [width - 1.0, height - 1.0]).astype(np.float32)
    return {
        "keypoints": torch.from_numpy(keypoints)[None],
        "descriptors": torch.from_numpy(_unit(features.descriptors))[None],
        "image_size": torch.tensor([[float(width), float(height)]]),
    }


MATCHERS = ("lightglue", "mnn")


def resolve_matcher_name(name: str, extractor: str) -> str:
    """The matcher a setting means for an extractor: ``auto`` is LightGlue for DISK, MNN else.

    Raises:
        ValueError: an unknown name, or LightGlue asked for with a non-DISK extractor.
    """
    if name == "auto":
        return "lightglue" if extractor == "disk" else "mnn"
    if name not in MATCHERS:
        raise ValueError(f"unknown matcher {name!r}; choose one of auto, {', '.join(MATCHERS)}")
    if name == "lightglue" and extractor != "disk":
        raise ValueError(
            f"the LightGlue weights here are for DISK; the {extractor!r} extractor needs "
            "matcher 'mnn' (or 'auto')"
        )
    return name


@lru_cache(maxsize=4)
def build_matcher(name: str, ratio: float = 0.9) -> Matcher:
    """A matcher by name, built once per process (LightGlue's weights are 45 MB)."""
    if name == "lightglue":
        return LightGlueMatcher()
    if name == "mnn":
        return MutualNearestNeighbours(ratio)
    raise ValueError(f"unknown matcher {name!r}; choose one of {', '.join(MATCHERS)}")
