from __future__ import annotations

import numpy as np

from service.ml.aggregation import aggregate_descriptors, l2_normalize


def test_no_keypoints_gives_zero_vector_not_nan() -> None:
    vector = aggregate_descriptors(np.zeros((0, 128), np.float32), np.zeros(0, np.float32))
    assert vector.shape == (128,) and np.all(vector == 0) and not np.isnan(vector).any()


def test_result_is_unit_norm_and_weighted_by_score() -> None:
    descriptors = l2_normalize(np.array([[1.0, 0.0], [0.0, 1.0]], np.float32))
    strong_first = aggregate_descriptors(descriptors, np.array([0.9, 0.1], np.float32))
    assert np.isclose(np.linalg.norm(strong_first), 1.0)
    assert strong_first[0] > strong_first[1]


def test_zero_scores_fall_back_to_plain_mean() -> None:
    descriptors = np.array([[1.0, 0.0], [0.0, 1.0]], np.float32)
    vector = aggregate_descriptors(descriptors, np.zeros(2, np.float32))
    assert np.allclose(vector, [np.sqrt(0.5), np.sqrt(0.5)], atol=1e-6)
