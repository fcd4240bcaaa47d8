"""Verification's minimum inliers, calibrated per atlas from its own look-alikes.

How many RANSAC inliers a wrong candidate reaches depends on the images (size, texture,
repetitive structure) and on the keypoint budget, so a fixed minimum chosen on one dataset does
not transfer. The atlas's hard impostors are the wrong candidates a query meets: for a sample
of frames, the most similar frame (by the calibrated embedding) that is not the same place by
sequence alone. The minimum is set just above a high quantile of their inliers, never below a
floor where RANSAC agreement happens by chance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from service.ml.impostors import sequence_positions

FLOOR = 15  # fewer inliers can agree on a fundamental matrix by chance
QUANTILE = 0.99  # robust to the few true revisits among far-apart frames


@dataclass(frozen=True)
class InlierThreshold:
    """The calibrated minimum and the operating point it came from."""

    matcher: str
    min_inliers: int
    impostors: int  # hard impostor pairs verified
    impostor_quantile: float  # their inliers at QUANTILE
    impostor_max: int
    accepted_impostors: int  # of them at or above the minimum

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def hard_impostors(
    embeddings: np.ndarray,
    robots: Sequence[str],
    order: np.ndarray,
    *,
    frames: int = 200,
    seed: int = 0,
) -> list[tuple[int, int]]:
    """``(i, j)``: for up to ``frames`` sampled frames ``i``, the most similar frame ``j`` of
    another robot, or of the same robot at least a twentieth of its frames (5 or more) away."""
    n = len(embeddings)
    codes, rank, gap = sequence_positions(robots, np.asarray(order))
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.permutation(n)[:frames])
    pairs = []
    for i in chosen:
        similarity = embeddings @ embeddings[i]
        same_place = (codes == codes[i]) & (np.abs(rank - rank[i]) < gap[i])
        similarity[same_place] = -np.inf
        j = int(np.argmax(similarity))
        if np.isfinite(similarity[j]):
            pairs.append((int(i), j))
    return pairs


def fit_inlier_threshold(matcher: str, inliers: Sequence[int]) -> InlierThreshold:
    """The minimum just above the impostors' high quantile (at least :data:`FLOOR`)."""
    values = np.asarray(inliers, np.int64)
    if len(values) == 0:
        raise ValueError("no impostor pairs to calibrate the minimum inliers on")
    quantile = float(np.quantile(values, QUANTILE))
    minimum = max(FLOOR, int(np.floor(quantile)) + 1)
    return InlierThreshold(
        matcher=matcher,
        min_inliers=minimum,
        impostors=len(values),
        impostor_quantile=round(quantile, 2),
        impostor_max=int(values.max()),
        accepted_impostors=int((values >= minimum).sum()),
    )
