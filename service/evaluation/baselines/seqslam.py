"""The single-frame core of SeqSLAM (Milford & Wyeth, 2012): whole-image matching of small,
patch-normalised grey thumbnails by the sum of absolute differences (SAD).

Thumbnails are made with OpenCV (area resampling), patch normalisation in NumPy, and the
``Q x R`` SAD matrix by scikit-learn's ``pairwise_distances`` (Manhattan). The score is the
negated mean absolute difference, so higher means more similar.

:func:`full_seqslam` adds the rest of SeqSLAM for the sequence rows: local contrast
enhancement of the difference matrix over a window of references, then a search over straight
trajectories through the last L queries at a range of speeds (past queries only, as a robot
would run it online; OpenSeqSLAM centres its window on the query).
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


def contrast_enhanced(difference: np.ndarray, window: int = 10) -> np.ndarray:
    """SeqSLAM's local contrast enhancement of a ``Q x R`` difference matrix: each entry minus
    the mean, over the std, of its query's differences to the ``window`` references around it."""
    d = np.asarray(difference, dtype=np.float64)
    r = d.shape[1]
    half = window // 2
    lo = np.clip(np.arange(r) - half, 0, r)
    hi = np.clip(np.arange(r) + half + 1, 0, r)
    zero = np.zeros((d.shape[0], 1))
    total = np.concatenate([zero, np.cumsum(d, axis=1)], axis=1)
    squares = np.concatenate([zero, np.cumsum(d * d, axis=1)], axis=1)
    count = (hi - lo)[None, :]
    mean = (total[:, hi] - total[:, lo]) / count
    var = np.maximum((squares[:, hi] - squares[:, lo]) / count - mean**2, 0.0)
    return (d - mean) / np.maximum(np.sqrt(var), 1e-6)


def full_seqslam(
    difference: np.ndarray,
    length: int,
    speeds: tuple[float, ...] = (0.8, 0.9, 1.0, 1.1, 1.25),
    *,
    window: int | None = 10,
    query_starts: np.ndarray | None = None,
) -> np.ndarray:
    """``Q x R`` similarity (negated mean enhanced difference along the best straight
    trajectory) of query q's last ``length`` frames ending at reference r.

    Query frame ``q - a`` is aligned with reference ``r - round(a * v)``. Only trajectories
    that stay inside the map count (as OpenSeqSLAM's); a query's run start (``query_starts``)
    shortens its sequence. ``window``
    None skips the contrast enhancement (the sequence search on the raw differences).
    """
    enhanced = (
        np.asarray(difference, dtype=np.float64)
        if window is None
        else contrast_enhanced(difference, window)
    )
    q, r = enhanced.shape
    starts = np.zeros(q, bool) if query_starts is None else np.asarray(query_starts, bool)
    first = np.maximum.accumulate(np.where(starts, np.arange(q), 0))
    best = np.full((q, r), np.inf)
    for v in speeds:
        total = np.zeros((q, r))
        count = np.zeros((q, r))
        for a in range(length):
            s = int(round(a * v))
            if a >= q or s >= r:
                break
            in_run = (np.arange(a, q) - a >= first[a:])[:, None]
            total[a:, s:] += np.where(in_run, enhanced[: q - a, : r - s], 0.0)
            count[a:, s:] += in_run
        whole = count >= np.minimum(length, np.arange(q) - first + 1)[:, None]
        best = np.minimum(best, np.where(whole, total / np.maximum(count, 1), np.inf))
    return (-best).astype(np.float32)
