"""Robust two-view geometry with kornia: RANSAC for a fundamental matrix, an essential matrix
and the relative pose when both cameras' intrinsics are known, or a homography.

Conventions: points ``a`` are in the first image (the query), ``b`` in the second (the
reference); a fundamental or essential matrix satisfies ``b^T M a = 0``; the relative pose
``(R, t)`` maps a point from camera A's frame to camera B's: ``X_b = R X_a + t`` with
``|t| = 1`` (the scale is unobservable from two views). Every estimate is seeded, so the same
input gives the same answer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from service.ml.batched_ransac import BatchedRansacConfig, fundamental_ransac_many

# Fewer correspondences than this make every estimate meaningless (7-point F needs 7 plus one
# to check); below it the answer is "no model, no inliers".
MIN_CORRESPONDENCES = 8


@dataclass(frozen=True)
class RansacConfig:
    """How RANSAC runs.

    Attributes:
        threshold_px: inlier threshold in pixels (Sampson distance for F and E, transfer error
            for H); for E it is divided by the mean focal length of the two cameras.
        confidence: early-stopping confidence.
        max_iter: batches of hypotheses at most (kornia's ``auto`` batch size, 2048 each).
        seed: the private generator's seed (results are reproducible, global RNG untouched).
        backend: who fits fundamental matrices: "batched" (service.ml.batched_ransac: every
            candidate's hypotheses vectorised together, several times faster) or "kornia"
            (kornia's RANSAC, one pair at a time). Essential matrices and homographies always
            use kornia.
    """

    threshold_px: float = 3.0
    confidence: float = 0.999
    max_iter: int = 5
    seed: int = 0
    backend: str = "batched"

    def __post_init__(self) -> None:
        if self.backend not in RANSAC_BACKENDS:
            raise ValueError(f"unknown RANSAC backend {self.backend!r}; choose {RANSAC_BACKENDS}")


RANSAC_BACKENDS = ("batched", "kornia")


@dataclass(frozen=True)
class TwoViewGeometry:
    """What RANSAC found for one pair.

    Attributes:
        model: "fundamental", "essential", "homography" or "none" (too few correspondences
            or no consensus).
        matrix: the 3x3 model (None when ``model`` is "none").
        inlier_mask: ``K`` bool over the correspondences given.
        rotation: 3x3 R of ``X_b = R X_a + t`` (essential only).
        translation: unit t (essential only).
        cheirality: correspondences in front of both cameras for the chosen (R, t).
    """

    model: str
    matrix: np.ndarray | None
    inlier_mask: np.ndarray
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    cheirality: int = 0

    @property
    def inliers(self) -> int:
        return int(self.inlier_mask.sum())


def _none(count: int) -> TwoViewGeometry:
    return TwoViewGeometry("none", None, np.zeros(count, bool))


def _ransac(model: str, threshold: float, config: RansacConfig) -> object:
    from kornia.geometry.ransac import RANSAC

    return RANSAC(
        model_type=model,
        inl_th=threshold,
        confidence=config.confidence,
        max_iter=config.max_iter,
        seed=config.seed,
    )


def _run(
    model: str, a: np.ndarray, b: np.ndarray, threshold: float, config: RansacConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """(3x3 model, inlier mask) or None when RANSAC found no consensus."""
    ransac = _ransac(model, threshold, config)
    pa = torch.from_numpy(np.ascontiguousarray(a, np.float64))
    pb = torch.from_numpy(np.ascontiguousarray(b, np.float64))
    with torch.inference_mode():
        matrix, mask = ransac(pa, pb)  # type: ignore[operator]
    mask_np = mask.numpy().astype(bool).reshape(-1)
    if not mask_np.any():
        return None
    return matrix.numpy().astype(np.float64), mask_np


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def estimate_two_view(
    a: np.ndarray,
    b: np.ndarray,
    k_a: np.ndarray | None = None,
    k_b: np.ndarray | None = None,
    config: RansacConfig | None = None,
) -> TwoViewGeometry:
    """Epipolar geometry of ``K x 2`` pixel correspondences ``a`` <-> ``b``.

    With both camera matrices, an essential matrix on calibrated coordinates (5-point RANSAC)
    and the relative pose chosen by cheirality; otherwise a fundamental matrix (7-point
    RANSAC) and no pose.
    """
    return estimate_two_view_many([(a, b, k_a, k_b)], config)[0]


def estimate_two_view_many(
    pairs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]],
    config: RansacConfig | None = None,
) -> list[TwoViewGeometry]:
    """:func:`estimate_two_view` of each ``(a, b, k_a, k_b)``; with the batched backend the
    fundamental matrices of all pairs are fitted together."""
    config = config or RansacConfig()
    out: list[TwoViewGeometry | None] = [None] * len(pairs)
    fundamental: list[int] = []
    for i, (a, b, k_a, k_b) in enumerate(pairs):
        if len(a) < MIN_CORRESPONDENCES:
            out[i] = _none(len(a))
        elif k_a is None or k_b is None:
            fundamental.append(i)
        else:
            out[i] = _essential(a, b, k_a, k_b, config)
    if config.backend == "batched":
        found = fundamental_ransac_many(
            [(pairs[i][0], pairs[i][1]) for i in fundamental],
            BatchedRansacConfig(
                threshold_px=config.threshold_px, confidence=config.confidence, seed=config.seed
            ),
        )
    else:
        found = [
            _run("fundamental", pairs[i][0], pairs[i][1], config.threshold_px, config)
            for i in fundamental
        ]
    for i, result in zip(fundamental, found, strict=True):
        out[i] = (
            _none(len(pairs[i][0]))
            if result is None
            else TwoViewGeometry("fundamental", result[0], result[1])
        )
    return [g for g in out if g is not None]


def _essential(
    a: np.ndarray, b: np.ndarray, k_a: np.ndarray, k_b: np.ndarray, config: RansacConfig
) -> TwoViewGeometry:
    """Essential matrix (kornia's 5-point RANSAC) and the pose that passes cheirality."""
    na, nb = _calibrate(a, k_a), _calibrate(b, k_b)
    focal = float(np.mean([k_a[0, 0], k_a[1, 1], k_b[0, 0], k_b[1, 1]]))
    found = _run("essential", na, nb, config.threshold_px / focal, config)
    if found is None:
        return _none(len(a))
    essential, mask = found
    rotation, translation, in_front = _pose_from_essential(essential, na, nb, mask)
    return TwoViewGeometry("essential", essential, mask, rotation, translation, in_front)


def estimate_homography(
    a: np.ndarray, b: np.ndarray, config: RansacConfig | None = None
) -> TwoViewGeometry:
    """A homography ``b ~ H a`` of pixel correspondences (planar scenes, pure rotation)."""
    config = config or RansacConfig()
    if len(a) < MIN_CORRESPONDENCES:
        return _none(len(a))
    found = _run("homography", a, b, config.threshold_px, config)
    if found is None:
        return _none(len(a))
    matrix = found[0] / found[0][2, 2] if abs(found[0][2, 2]) > 1e-12 else found[0]
    return TwoViewGeometry("homography", matrix, found[1])


def _calibrate(points: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixels -> normalised image coordinates ``K^-1 [x, y, 1]``."""
    homogeneous = np.c_[points.astype(np.float64), np.ones(len(points))]
    return (np.linalg.solve(k, homogeneous.T).T)[:, :2]


def _pose_from_essential(
    essential: np.ndarray, na: np.ndarray, nb: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """(R, unit t, points in front of both cameras) of the decomposition that sees the inliers
    in front of both cameras (kornia's cheirality check, on calibrated points)."""
    from kornia.geometry.epipolar import motion_from_essential_choose_solution

    eye = torch.eye(3, dtype=torch.float64)
    with torch.inference_mode():
        rotation, translation, _, in_front = motion_from_essential_choose_solution(
            torch.from_numpy(essential),
            eye,
            eye,
            torch.from_numpy(na),
            torch.from_numpy(nb),
            mask=torch.from_numpy(mask),
        )
    t = translation.numpy().reshape(3)
    norm = float(np.linalg.norm(t))
    return rotation.numpy(), (t / norm if norm > 0 else t), int(in_front)


def rotation_to_quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """3x3 rotation -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    m = np.asarray(rotation, np.float64)
    trace = float(np.trace(m))
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-12))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    quaternion = np.array(q) / np.linalg.norm(q)
    if quaternion[0] < 0:
        quaternion = -quaternion
    w, x, y, z = (float(v) for v in quaternion)
    return w, x, y, z
