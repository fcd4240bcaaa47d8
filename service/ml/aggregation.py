"""Aggregate a set of local descriptors into one L2-normalised vector (the paper's D)."""

from __future__ import annotations

import numpy as np


def l2_normalize(x: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """Rows divided by their L2 norm; all-zero rows stay zero (never NaN)."""
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    unit: np.ndarray = (x / np.maximum(norm, eps)).astype(np.float32, copy=False)
    return unit


def aggregate_descriptors(descriptors: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Score-weighted mean of L2-normalised descriptors, signed-square-rooted, L2-normalised.

    The signed square root (power normalisation, as in VLAD/Fisher vectors) damps the few
    dimensions that repeated texture makes bursty. A frame without keypoints gives the zero
    vector: it matches nothing through this branch, and never produces NaN.
    """
    dim = descriptors.shape[1]
    if len(descriptors) == 0:
        return np.zeros(dim, np.float32)
    weights = np.clip(scores.astype(np.float64), 0.0, None)
    if weights.sum() <= 0:
        weights = np.ones_like(weights)
    mean = (weights[:, None] * descriptors.astype(np.float64)).sum(0) / weights.sum()
    powered = np.sign(mean) * np.sqrt(np.abs(mean))
    return l2_normalize(powered.astype(np.float32))
