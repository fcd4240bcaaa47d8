"""The classical baselines on real Gardens Point frames."""

from __future__ import annotations

import numpy as np

from service.evaluation.baselines import build_baseline
from service.evaluation.datasets import load_dataset
from service.evaluation.metrics import rank_by_similarity, recall_at_k
from service.ml.images import decode_image
from tests.conftest import DATA_DIR


def frames(count: int) -> tuple[list[np.ndarray], list[np.ndarray], list[frozenset[int]]]:
    dataset = load_dataset(DATA_DIR / "gardenspoint_cohog200", tolerance=2).head(count)
    decode = [decode_image(f.path.read_bytes()) for f in dataset.references]
    queries = [decode_image(q.path.read_bytes()) for q in dataset.queries]
    return decode, queries, [q.positives for q in dataset.queries]


def test_sad_thumbnails_ignore_brightness_and_find_their_own_frame() -> None:
    baseline = build_baseline("seqslam-sad", long_side=256)
    refs, _, _ = frames(10)
    described = [baseline.describe(r) for r in refs]
    assert described[0].shape == (64 * 32,)
    darker = (refs[3] * 0.5).astype(np.uint8)  # patch normalisation removes a global gain
    baseline.fit(described)
    scores = baseline.score([baseline.describe(darker)])
    assert scores.shape == (1, 10) and int(scores.argmax()) == 3


def test_bag_of_orb_words_learns_on_references_and_recognises_places() -> None:
    baseline = build_baseline("bow-orb", long_side=256)
    refs, queries, positives = frames(30)
    baseline.fit([baseline.describe(r) for r in refs])
    assert baseline.settings()["vocabulary_learned"] is not None
    scores = baseline.score([baseline.describe(q) for q in queries])
    assert scores.shape == (len(queries), 30)
    assert np.isfinite(scores).all() and scores.max() <= 1.0 + 1e-5
    # other-camera queries of the same route: far better than chance (~5/30 within ±2)
    assert recall_at_k(rank_by_similarity(scores, 5), positives, (1,))[1] >= 0.4


def test_a_frame_without_orb_features_scores_zero_everywhere() -> None:
    baseline = build_baseline("bow-orb", long_side=256)
    refs, _, _ = frames(8)
    baseline.fit([baseline.describe(r) for r in refs])
    blank = baseline.describe(np.full((56, 99, 3), 128, np.uint8))
    assert len(blank) == 0
    assert (baseline.score([blank]) == 0).all()
