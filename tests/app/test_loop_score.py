"""The calibrated loop decision: one setting, the same false-alarm rate on any atlas size."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from service.app.sequences import SequenceScorer
from service.app.state import LoadedAtlas
from service.ml.impostors import ImpostorModel, loop_score_threshold
from tests.conftest import make_settings


def test_the_best_of_n_impostors_passes_at_the_set_rate() -> None:
    rng = np.random.default_rng(0)
    model = ImpostorModel.fit(rng.normal(0.1, 0.1, 200_000))
    for frames in (10, 100, 1000):
        threshold = loop_score_threshold(1.0, frames)  # one query in ten may pass
        best = rng.normal(0.1, 0.1, (2000, frames)).max(axis=1)  # queries with no revisit
        passed = float(np.mean(model.score(best) >= threshold))
        # never above the set rate; below it only where the fitted exponential tail is heavier
        # than this Gaussian's (far tails of large atlases): conservative
        assert passed <= 0.14 and passed >= (0.06 if frames <= 100 else 0.02), (frames, passed)
    assert loop_score_threshold(3.0, 100) == 5.0 and loop_score_threshold(3.0, 0) == 3.0


class _Model:
    """A model version's scoring only: calibrated (a fixed score) or not (None)."""

    def __init__(self, score: float | None) -> None:
        self._score = score

    def score(self, cosines: np.ndarray) -> np.ndarray | None:
        return None if self._score is None else np.full(len(cosines), self._score)


def _state(score: float | None, frames: int) -> LoadedAtlas:
    return SimpleNamespace(model=_Model(score), index=SimpleNamespace(size=frames))  # type: ignore[return-value]


def test_consistency_judges_earlier_observations_by_the_querys_own_rule() -> None:
    """A robot's earlier observations count as passed by the rule its query used: the cosine
    threshold on an uncalibrated version, the calibrated score's bar on a calibrated one (whose
    cosines sit far below the cosine threshold even for true revisits)."""
    scorer = SequenceScorer(make_settings(Path("unused"), loop_closure_threshold=0.8))
    assert scorer._passes(_state(None, 100), 0.85)
    assert not scorer._passes(_state(None, 100), 0.5)
    # calibrated, 100 frames: the bar is 2 + log10(100) = 4 whatever the cosine
    assert scorer._passes(_state(4.5, 100), 0.5)
    assert not scorer._passes(_state(3.5, 100), 0.95)
    assert not scorer._passes(_state(4.5, 10_000), 0.5)  # a bigger atlas raises the bar to 6
