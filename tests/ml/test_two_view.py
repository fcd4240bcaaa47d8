"""Two-view geometry recovers known models: a homography warped into a real image, and the
relative pose of two synthetic cameras with known intrinsics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from service.ml.features import LocalFeatures
from service.ml.images import decode_image, to_tensor
from service.ml.matching import MutualNearestNeighbours
from service.ml.two_view import (
    RansacConfig,
    camera_matrix,
    estimate_homography,
    estimate_two_view,
    rotation_to_quaternion,
)
from tests.conftest import gardens_point_day_night

HOMOGRAPHY_TOLERANCE_PX = 2.0  # mean corner transfer error, pixels of the 960x540 image
ROTATION_TOLERANCE_DEG = 0.5
TRANSLATION_TOLERANCE_DEG = 2.0


def rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_homography_warped_into_a_real_image_is_recovered(pipeline) -> None:  # type: ignore[no-untyped-def]
    from kornia.geometry.transform import warp_perspective

    rgb = decode_image(gardens_point_day_night(3, "query"))
    height, width = rgb.shape[:2]
    truth = np.array([[0.9, 0.05, 40.0], [-0.04, 0.95, 25.0], [2e-5, -1e-5, 1.0]])
    warped = warp_perspective(
        to_tensor(rgb), torch.from_numpy(truth).float()[None], (height, width)
    )
    warped_rgb = (warped[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    a = pipeline.local.extract(rgb)
    b = pipeline.local.extract(warped_rgb)
    matches = MutualNearestNeighbours(0.9).match(a, (width, height), b, (width, height))
    found = estimate_homography(a.keypoints[matches.pairs[:, 0]], b.keypoints[matches.pairs[:, 1]])
    assert found.model == "homography" and found.inliers >= 30
    corners = np.array([[0, 0, 1], [width, 0, 1], [width, height, 1], [0, height, 1]], float)

    def transfer(h: np.ndarray) -> np.ndarray:
        p = corners @ h.T
        return p[:, :2] / p[:, 2:]

    error = np.linalg.norm(transfer(found.matrix) - transfer(truth), axis=1).mean()
    assert error < HOMOGRAPHY_TOLERANCE_PX


def synthetic_views(
    outliers: int, noise_px: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points seen by camera A (at the origin) and camera B with ``X_b = R X_a + t``."""
    rng = np.random.default_rng(seed)
    k = camera_matrix(500.0, 510.0, 320.0, 240.0)
    r = rotation(np.array([0.2, 1.0, 0.1]), 8.0)
    t = np.array([0.6, -0.1, 0.2])
    points = np.c_[rng.uniform(-3, 3, 300), rng.uniform(-2, 2, 300), rng.uniform(4, 12, 300)]
    in_b = points @ r.T + t

    def project(p: np.ndarray) -> np.ndarray:
        q = p @ k.T
        return q[:, :2] / q[:, 2:] + rng.normal(0, noise_px, (len(p), 2))

    a, b = project(points), project(in_b)
    a = np.r_[a, rng.uniform([0, 0], [640, 480], (outliers, 2))]
    b = np.r_[b, rng.uniform([0, 0], [640, 480], (outliers, 2))]
    return a, b, k, r, t / np.linalg.norm(t)


def test_relative_pose_of_synthetic_cameras_is_recovered() -> None:
    a, b, k, r, t = synthetic_views(outliers=100, noise_px=0.5)
    found = estimate_two_view(a, b, k, k, RansacConfig(threshold_px=2.0))
    assert found.model == "essential"
    assert found.rotation is not None and found.translation is not None
    assert angle_deg(np.array([1.0, 0, 0]), found.rotation @ r.T @ np.array([1.0, 0, 0])) < 1
    rotation_error = np.degrees(np.arccos(np.clip((np.trace(found.rotation @ r.T) - 1) / 2, -1, 1)))
    assert rotation_error < ROTATION_TOLERANCE_DEG
    assert angle_deg(found.translation, t) < TRANSLATION_TOLERANCE_DEG
    # the 300 true correspondences are inliers, almost none of the 100 random ones
    assert found.inlier_mask[:300].mean() > 0.95 and found.inlier_mask[300:].mean() < 0.1


@pytest.mark.parametrize("backend", ["batched", "kornia"])
def test_fundamental_matrix_of_synthetic_cameras_separates_outliers(backend: str) -> None:
    """Without intrinsics: a fundamental matrix whose inliers are the true correspondences,
    and that satisfies the true geometry (epipolar constraint of the noiseless points)."""
    a, b, k, r, t = synthetic_views(outliers=150, noise_px=0.5, seed=5)
    found = estimate_two_view(a, b, config=RansacConfig(threshold_px=2.0, backend=backend))
    assert found.model == "fundamental" and found.matrix is not None
    assert found.inlier_mask[:300].mean() > 0.95 and found.inlier_mask[300:].mean() < 0.1
    clean_a, clean_b = synthetic_views(outliers=0, noise_px=0.0, seed=5)[:2]
    ha, hb = np.c_[clean_a, np.ones(300)], np.c_[clean_b, np.ones(300)]
    fa, ftb = ha @ found.matrix.T, hb @ found.matrix
    sampson = (hb * fa).sum(1) ** 2 / (fa[:, :2] ** 2 + ftb[:, :2] ** 2).sum(1)
    assert np.sqrt(sampson).mean() < 1.0  # pixels, on the noiseless projections
    assert np.linalg.matrix_rank(found.matrix, tol=1e-9 * np.abs(found.matrix).max()) == 2


@pytest.mark.parametrize("backend", ["batched", "kornia"])
def test_a_frame_against_itself_is_all_inliers(backend: str) -> None:
    """Points that did not move: every 7-point sample is degenerate (F is any skew-symmetric
    matrix), and every correspondence is an inlier."""
    a = synthetic_views(outliers=0, noise_px=0.0)[0][:120]
    found = estimate_two_view(a, a.copy(), config=RansacConfig(backend=backend))
    assert found.model == "fundamental" and found.inliers == 120


def test_batched_ransac_fits_several_sets_as_each_alone() -> None:
    """Several sets in one call: each gets a model of its own geometry; a set too small, or
    pure noise, gets none."""
    from service.ml.batched_ransac import BatchedRansacConfig, fundamental_ransac_many

    good = [synthetic_views(outliers=60, noise_px=0.5, seed=seed)[:2] for seed in (1, 2)]
    rng = np.random.default_rng(9)
    noise = (rng.uniform(0, 640, (40, 2)), rng.uniform(0, 640, (40, 2)))
    tiny = (good[0][0][:7], good[0][1][:7])
    found = fundamental_ransac_many([good[0], tiny, noise, good[1]], BatchedRansacConfig())
    assert found[1] is None
    assert found[2] is None or found[2][1].sum() < 20
    for set_, result in ((good[0], found[0]), (good[1], found[3])):
        assert result is not None
        assert result[1][:300].mean() > 0.95 and result[1][300:].mean() < 0.1
        alone = fundamental_ransac_many([set_], BatchedRansacConfig())[0]
        assert alone is not None and abs(int(alone[1].sum()) - int(result[1].sum())) <= 3


def test_estimates_are_reproducible() -> None:
    a, b, k, _, _ = synthetic_views(outliers=150, noise_px=1.0, seed=3)
    first = estimate_two_view(a, b)
    second = estimate_two_view(a, b)
    assert first.model == "fundamental"
    assert first.inliers > 0
    assert np.array_equal(first.inlier_mask, second.inlier_mask)
    assert np.allclose(first.matrix, second.matrix)


def test_too_few_correspondences_give_no_model() -> None:
    a, b, k, _, _ = synthetic_views(outliers=0, noise_px=0.0)
    found = estimate_two_view(a[:7], b[:7], k, k)
    assert found.model == "none" and found.inliers == 0 and found.rotation is None


def test_quaternion_of_known_rotation() -> None:
    w, x, y, z = rotation_to_quaternion(rotation(np.array([0.0, 0.0, 1.0]), 90.0))
    assert (w, x, y, z) == pytest.approx((np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)), abs=1e-9)
    assert rotation_to_quaternion(np.eye(3)) == pytest.approx((1.0, 0.0, 0.0, 0.0))
    # 180 degrees about x: the trace branch is not taken
    assert rotation_to_quaternion(np.diag([1.0, -1.0, -1.0])) == pytest.approx((0, 1, 0, 0))


def test_mnn_of_many_candidates_is_each_pair_alone() -> None:
    """One product against all candidates stacked gives each candidate its own matches."""
    rng = np.random.default_rng(0)

    def features(count: int) -> LocalFeatures:
        d = rng.standard_normal((count, 16)).astype(np.float32)
        return LocalFeatures(np.zeros((count, 2), np.float32), d, np.ones(count, np.float32))

    query = features(50)
    near = LocalFeatures(
        query.keypoints[:30],
        query.descriptors[:30] + 0.1 * rng.standard_normal((30, 16)).astype(np.float32),
        query.scores[:30],
    )
    candidates = [near, features(40), LocalFeatures.empty(16), features(1), near]
    matcher = MutualNearestNeighbours(0.9)
    together = matcher.match_many(query, (1, 1), [(c, (1, 1)) for c in candidates])
    for candidate, matches in zip(candidates, together, strict=True):
        alone = matcher.match(query, (1, 1), candidate, (1, 1))
        assert np.array_equal(matches.pairs, alone.pairs)
        assert np.allclose(matches.scores, alone.scores)
    assert together[0].count >= 25 and together[2].count == 0


def _mnn_by_definition(a: np.ndarray, b: np.ndarray, ratio: float) -> set[tuple[int, int]]:
    """Mutual nearest neighbours with the ratio test, written out pair by pair (argmax picks the
    first of tied rows or columns)."""
    unit_a = a / np.linalg.norm(a, axis=1, keepdims=True)
    unit_b = b / np.linalg.norm(b, axis=1, keepdims=True)
    similarity = unit_a @ unit_b.T
    found = set()
    for i in range(len(a)):
        j = int(np.argmax(similarity[i]))
        if int(np.argmax(similarity[:, j])) != i:
            continue
        others = np.delete(similarity[i], j)
        if len(others):
            distance, second = (
                np.sqrt(np.maximum(2 - 2 * similarity[i, j], 0)),
                np.sqrt(np.maximum(2 - 2 * others.max(), 0)),
            )
            if not distance < ratio * second:
                continue
        found.add((i, j))
    return found


def test_mnn_matches_the_definition_with_duplicated_descriptors() -> None:
    """The column-wise max shortcut gives exactly the pairs of the definition, also where
    keypoints share a descriptor (exact ties: only the first row of a column is mutual) and
    where candidates have different numbers of keypoints."""
    rng = np.random.default_rng(3)
    query = rng.standard_normal((60, 8)).astype(np.float32)
    query[10] = query[3]  # duplicated keypoints in the query ...
    candidates = []
    for count in (45, 60, 30):
        b = query[rng.permutation(60)[:count]] + 0.2 * rng.standard_normal((count, 8)).astype(
            np.float32
        )
        b[5] = b[2]  # ... and in a candidate
        candidates.append(b)
    matcher = MutualNearestNeighbours(0.95)
    together = matcher.match_many(
        LocalFeatures(np.zeros((60, 2), np.float32), query, np.ones(60, np.float32)),
        (1, 1),
        [
            (
                LocalFeatures(np.zeros((len(b), 2), np.float32), b, np.ones(len(b), np.float32)),
                (1, 1),
            )
            for b in candidates
        ],
    )
    for b, matches in zip(candidates, together, strict=True):
        expected = _mnn_by_definition(query, b, 0.95)
        assert set(map(tuple, matches.pairs.tolist())) == expected
        assert len(expected) >= 10


def test_mnn_keeps_only_mutual_unambiguous_pairs() -> None:
    d = np.eye(4, dtype=np.float32)
    a = LocalFeatures(np.zeros((4, 2), np.float32), d, np.ones(4, np.float32))
    # b: rows 0 and 1 of a, a near-duplicate of row 2 twice (ambiguous), nothing for row 3
    b_desc = np.stack([d[0], d[1], d[2] * 0.99 + d[3] * 0.01, d[2] * 0.99 + d[0] * 0.0101])
    b = LocalFeatures(np.zeros((4, 2), np.float32), b_desc, np.ones(4, np.float32))
    matches = MutualNearestNeighbours(0.9).match(a, (10, 10), b, (10, 10))
    assert sorted(map(tuple, matches.pairs.tolist())) == [(0, 0), (1, 1)]
