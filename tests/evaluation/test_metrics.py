"""The metric code against cases worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from service.evaluation.metrics import (
    Ranking,
    precision_recall,
    rank_by_similarity,
    recall_at_k,
    submap_accuracy,
)


def single_truth(n: int) -> list[frozenset[int]]:
    return [frozenset({i}) for i in range(n)]


def test_a_perfect_ranking_has_recall_one() -> None:
    similarity = np.eye(4) + 0.01 * np.arange(4)  # the right reference is always the best
    ranking = rank_by_similarity(similarity, k=4)
    assert recall_at_k(ranking, single_truth(4), (1, 5)) == {1: 1.0, 5: 1.0}


def test_a_reversed_ranking_gives_the_known_recalls() -> None:
    # Every query ranks its right reference last of five: R@1 = R@4 = 0, R@5 = 1.
    similarity = 1.0 - np.eye(5)
    ranking = rank_by_similarity(similarity, k=5)
    assert recall_at_k(ranking, single_truth(5), (1, 4, 5)) == {1: 0.0, 4: 0.0, 5: 1.0}


def test_one_fixed_order_for_every_query_gives_rank_by_rank_recall() -> None:
    # All four queries see references in the order 3, 2, 1, 0; query i is right on i only,
    # so query 3 is right at rank 1, query 2 at rank 2, ...: R@k = k / 4.
    order = np.tile([3, 2, 1, 0], (4, 1))
    ranking = Ranking(order, np.tile([0.4, 0.3, 0.2, 0.1], (4, 1)))
    assert recall_at_k(ranking, single_truth(4), (1, 2, 3, 4)) == {
        1: 0.25,
        2: 0.5,
        3: 0.75,
        4: 1.0,
    }


def test_queries_without_a_right_reference_do_not_count_in_recall() -> None:
    ranking = Ranking(np.array([[0], [0]]), np.array([[0.9], [0.8]]))
    assert recall_at_k(ranking, [frozenset({0}), frozenset()], (1,)) == {1: 1.0}


def test_precision_recall_of_a_known_score_list() -> None:
    # best-match similarity and whether the best match is right, 5 answerable queries
    curve = precision_recall(
        np.array([0.6, 0.9, 0.5, 0.8, 0.7]), np.array([True, True, False, True, False]), 5
    )
    # sorted: 0.9 T, 0.8 T, 0.7 F, 0.6 T, 0.5 F
    assert curve.thresholds.tolist() == [0.9, 0.8, 0.7, 0.6, 0.5]
    assert np.allclose(curve.precision, [1, 1, 2 / 3, 3 / 4, 3 / 5])
    assert np.allclose(curve.recall, [0.2, 0.4, 0.4, 0.6, 0.6])
    assert curve.auc == pytest.approx(0.2 * 1 + 0.2 * 1 + 0.2 * 0.75)
    assert curve.recall_at_full_precision == pytest.approx(0.4)
    assert curve.threshold_at_full_precision == pytest.approx(0.8)


def test_tied_scores_are_one_threshold_and_a_first_mistake_leaves_no_full_precision() -> None:
    curve = precision_recall(np.array([0.9, 0.9, 0.5]), np.array([True, False, True]), 3)
    assert curve.thresholds.tolist() == [0.9, 0.5]
    assert np.allclose(curve.precision, [0.5, 2 / 3])
    assert np.allclose(curve.recall, [1 / 3, 2 / 3])
    assert curve.auc == pytest.approx(1 / 3 * 0.5 + 1 / 3 * 2 / 3)
    assert curve.recall_at_full_precision == 0.0
    assert curve.threshold_at_full_precision is None


def test_recall_ends_at_recall_at_1_not_at_one() -> None:
    curve = precision_recall(np.array([0.9, 0.1]), np.array([True, True]), 4)
    assert np.allclose(curve.recall, [0.25, 0.5])
    assert curve.recall_at_full_precision == 0.5 and curve.threshold_at_full_precision == 0.1


def test_average_precision_matches_scikit_learn_when_every_query_is_answerable() -> None:
    from sklearn.metrics import average_precision_score

    rng = np.random.default_rng(0)
    scores = rng.random(200)
    correct = rng.random(200) < scores  # higher scores are right more often
    curve = precision_recall(scores, correct, int(correct.sum()))
    assert curve.auc == pytest.approx(average_precision_score(correct, scores))


def test_submap_accuracy_counts_a_right_submap_with_a_wrong_frame() -> None:
    # references 0, 1 form submap 0 and 2, 3 submap 1; the query is right on reference 1 only
    ranking = Ranking(np.array([[0, 2], [3, 0]]), np.array([[0.9, 0.5], [0.9, 0.1]]))
    positives = [frozenset({1}), frozenset({1})]
    assert recall_at_k(ranking, positives, (1,))[1] == 0.0
    assert submap_accuracy(ranking, positives, [0, 0, 1, 1]) == 0.5
