"""The calibrated loop decision: one setting, the same false-alarm rate on any atlas size."""

from __future__ import annotations

import numpy as np

from service.atlas.query import loop_score_threshold
from service.ml.impostors import ImpostorModel


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
