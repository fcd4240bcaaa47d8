"""A retrained version's impostor model: its score keeps the calibration's meaning."""

from __future__ import annotations

import numpy as np
import pytest

from service.ml.adaptation import adapt_heads
from service.ml.calibration import Calibration, CalibrationConfig, FittedCalibration
from service.ml.heads import LoopNetHeads
from service.ml.impostors import ImpostorModel
from service.ml.pair_whitening import PairWhiteningConfig
from service.ml.pipeline import embed_vectors
from service.ml.retrained_impostors import retrained_impostor_model
from service.ml.training import TrainingConfig, TrainingData, train_heads
from tests.ml.test_calibration import _synthetic_atlas

STORED = _synthetic_atlas(n=400)
UNSEEN = _synthetic_atlas(
    n=80, seed=9
)  # other places: every pair with a stored frame is an impostor


@pytest.fixture(scope="module")
def fitted() -> FittedCalibration:
    return Calibration.fit(STORED, CalibrationConfig(words=8))


def _passing(fitted: FittedCalibration, heads: LoopNetHeads, model: ImpostorModel) -> float:
    """Share of (unseen, stored) frame pairs scoring 2 or more: nominally 1 in 100."""
    calibration = fitted.calibration
    branches = calibration.branch_vectors(UNSEEN.descriptors, UNSEEN.scores, UNSEEN.global_vectors)
    queries = embed_vectors(heads, *branches)
    stored = embed_vectors(heads, fitted.local_branch, fitted.global_branch)
    return float(np.mean(model.score(queries @ stored.T) >= 2.0))


def _atlas_data(fitted: FittedCalibration) -> TrainingData:
    """The stored frames' calibrated branches as a job reads them, submaps of 20 frames."""
    return TrainingData(
        fitted.local_branch,
        fitted.global_branch,
        np.arange(len(STORED)) // 20,
        np.asarray(STORED.order),
        np.asarray(STORED.robots),
    )


def test_untrained_heads_get_the_calibrations_own_impostor_model(
    fitted: FittedCalibration,
) -> None:
    # the probe's branches are rotated onto the calibration's axes: heads that only fuse them
    # must see the cosines the calibration fitted its model on
    calibration = fitted.calibration
    assert calibration.impostors is not None
    heads = LoopNetHeads(calibration.heads_config()).eval()
    refit = retrained_impostor_model(heads, calibration, STORED)
    grid = np.linspace(-0.2, 0.6, 33)
    np.testing.assert_allclose(refit.score(grid), calibration.impostors.score(grid), atol=0.05)


def test_a_retrained_score_holds_its_meaning_on_frames_never_seen(
    fitted: FittedCalibration,
) -> None:
    # the in-sample refit (pairs of stored frames, all seen by the whitening) passed 5.1% of
    # these pairs at score 2, five times as many as the score says
    calibration = fitted.calibration
    data = _atlas_data(fitted)
    trained = train_heads(data, calibration.heads_config(), TrainingConfig(shots=3, epochs=30))
    assert trained.metrics["best_epoch"] > 0  # the heads did change
    model = retrained_impostor_model(trained.heads, calibration, STORED)
    assert 0.002 <= _passing(fitted, trained.heads, model) <= 0.025


def test_an_adapted_score_holds_its_meaning_on_frames_never_seen(
    fitted: FittedCalibration,
) -> None:
    # an adaptation's learned whitening decorrelates the atlas's own frames; probed with those
    # heads, the probe's held-out frames are in-sample again and wrong matches score as rarer
    # than they are: the impostor model is refitted without them
    calibration = fitted.calibration
    data = _atlas_data(fitted)
    pairs = np.array([[4 * p, 4 * p + 2] for p in range(0, len(STORED) // 4, 2)])
    active = LoopNetHeads(calibration.heads_config()).eval()
    adapted = adapt_heads(data, pairs, active, PairWhiteningConfig(), min_pairs=2)
    model = retrained_impostor_model(adapted.heads, calibration, STORED, adapted.impostor_refit)
    assert 0.002 <= _passing(fitted, adapted.heads, model) <= 0.025
