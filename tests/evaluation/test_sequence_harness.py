"""The harness's sequence pieces: FAB-MAP ground-truth files, full SeqSLAM, the ``+seqL`` rows
and the online single-trajectory replay (synthetic, and a small real one)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from service.evaluation.baselines.seqslam import contrast_enhanced, full_seqslam
from service.evaluation.datasets import load_dataset
from service.evaluation.loop_ground_truth import (
    Trajectory,
    loops_from_matrix,
    read_loop_closure_matrix,
    trajectory_from_matrix,
    trajectory_from_traversals,
)
from service.evaluation.online import (
    Observation,
    OnlineSettings,
    replay,
    unit_embeddings,
)
from service.evaluation.online_features import trajectory_vectors
from service.evaluation.online_service import service_observations
from service.evaluation.sequence_pass import sequence_ranking
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import resolve_preset
from service.ml.sequences import SequenceSettings, Trajectories
from tests.conftest import DATA_DIR, TEST_LONG_SIDE


def _fabmap_truth(n: int) -> np.ndarray:
    """Frames 6..9 revisit frames 1..4, filled in the lower triangle only (as FAB-MAP's)."""
    truth = np.zeros((n, n), dtype=np.uint8)
    for later in range(6, min(n, 10)):
        truth[later, later - 5] = 1
    return truth


def test_fabmap_matrix_files_read_alike(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from scipy.io import savemat

    truth = _fabmap_truth(10)
    savemat(tmp_path / "CityCentreGroundTruth.mat", {"truth": truth})
    np.save(tmp_path / "truth.npy", truth)
    np.savetxt(tmp_path / "truth.csv", truth, fmt="%d", delimiter=",")
    read = [
        read_loop_closure_matrix(tmp_path / name)
        for name in ("CityCentreGroundTruth.mat", "truth.npy", "truth.csv")
    ]
    for matrix in read:
        np.testing.assert_array_equal(matrix, read[0])
        assert matrix[6, 1] and matrix[1, 6] and not matrix[5, 0]  # made symmetric
    loops = loops_from_matrix(read[0])
    assert loops[7] == {2} and loops[2] == frozenset() and loops[9] == {4}
    savemat(tmp_path / "two.mat", {"truth": truth, "other": truth})
    with pytest.raises(ValueError, match="name the ground-truth variable"):
        read_loop_closure_matrix(tmp_path / "two.mat")
    assert read_loop_closure_matrix(tmp_path / "two.mat", "other")[6, 1]
    np.save(tmp_path / "bad.npy", np.zeros((3, 4)))
    with pytest.raises(ValueError, match="square"):
        read_loop_closure_matrix(tmp_path / "bad.npy")


def test_a_trajectory_folder_and_its_matrix_must_agree(tmp_path) -> None:  # type: ignore[no-untyped-def]
    images = tmp_path / "Images"
    images.mkdir()
    for i in range(1, 11):  # natural order: 1, 2, ..., 10
        Image.new("RGB", (8, 8), (i, i, i)).save(images / f"{i:d}.jpg")
    np.save(tmp_path / "truth.npy", _fabmap_truth(10))
    trajectory = trajectory_from_matrix(images, tmp_path / "truth.npy")
    assert [p.name for p in trajectory.images][:3] == ["1.jpg", "2.jpg", "3.jpg"]
    assert trajectory.loops[6] == {1}
    np.save(tmp_path / "short.npy", _fabmap_truth(9))
    with pytest.raises(ValueError, match="holds 10 images"):
        trajectory_from_matrix(images, tmp_path / "short.npy")


def test_contrast_enhancement_and_full_seqslam() -> None:
    rng = np.random.default_rng(0)
    difference = rng.uniform(0.5, 1.0, size=(40, 60))
    enhanced = contrast_enhanced(difference, window=10)
    r = 30
    local = difference[7, r - 5 : r + 6]
    assert enhanced[7, r] == pytest.approx((difference[7, r] - local.mean()) / local.std())
    # a straight trajectory of slightly lower differences at speed 1, hidden in noise
    for q in range(40):
        difference[q, q + 10] -= 0.25
    truth = np.arange(10, 50)
    single = np.argmax(-difference, axis=1)
    assert np.mean(single == truth) < 0.8
    for window in (None, 10):
        scores = full_seqslam(difference, 10, speeds=(0.8, 1.0, 1.25), window=window)
        assert np.mean(np.argmax(scores, axis=1)[9:] == truth[9:]) >= 0.95


def _aliased(rng: np.random.Generator, n: int, looks: int = 6, dim: int = 32):
    appearance = rng.normal(size=(looks, dim))
    label = rng.integers(0, looks, size=n)

    def sample(frames: np.ndarray) -> np.ndarray:
        x = appearance[label[frames]] + 0.6 * rng.normal(size=(len(frames), dim))
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    return sample


def test_sequence_rows_beat_single_frames_on_an_aliased_route() -> None:
    rng = np.random.default_rng(1)
    sample = _aliased(rng, 200)
    reference, query = sample(np.arange(200)), sample(np.arange(200))
    starts = np.zeros(200, dtype=bool)
    starts[[0, 100]] = True  # the queries were driven in two runs
    ranking, used, ms = sequence_ranking(
        reference, query, Trajectories.single(200), starts, SequenceSettings(length=8), k=5
    )
    right = np.abs(ranking.indices[:, 0] - np.arange(200)) <= 1
    single = np.abs(np.argmax(query @ reference.T, axis=1) - np.arange(200)) <= 1
    assert right[20:].mean() >= 0.85 > single[20:].mean() + 0.3
    assert used[100] == 1 and used[107] == 8 and used[99] == 8  # the second run starts afresh
    assert len(ms) == 200


def test_online_replay_counts_loops_and_false_alarms() -> None:
    rng = np.random.default_rng(2)
    sample = _aliased(rng, 100)
    # the robot drives the route (frames 0..99), pauses, and drives it again (100..199)
    vectors = np.concatenate([sample(np.arange(100)), sample(np.arange(100))])
    loops = [frozenset()] * 100 + [
        frozenset(j for j in (t - 1, t, t + 1) if 0 <= j < 100) for t in range(100)
    ]
    starts = np.zeros(200, dtype=bool)
    starts[[0, 100]] = True
    trajectory = Trajectory("synthetic", [], loops, starts, "synthetic revisit")
    single = replay(trajectory, vectors, OnlineSettings(length=1, exclude_recent=10))
    sequence = replay(trajectory, vectors, OnlineSettings(length=8, exclude_recent=10))
    assert single["answerable"] == sequence["answerable"] == 100
    assert sequence["decisions"]["k=1"]["best_match_right"] > 0.85
    assert single["decisions"]["k=1"]["best_match_right"] < 0.6
    assert (
        sequence["decisions"]["k=3"]["recall_at_100_precision"]
        > single["decisions"]["k=3"]["recall_at_100_precision"]
    )
    assert sequence["latency_ms"]["n"] == 200


def test_online_replay_on_real_frames_finds_the_hand_checked_loops(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Gardens Point first10: the robot drives the night route (ref/), then the day route
    (query/); day frame i shows night frame i's place (checked by eye, dataset README)."""
    dataset = load_dataset(DATA_DIR / "gardenspoint_first10", layout="traversals", tolerance=1)
    trajectory = trajectory_from_traversals(dataset)
    assert len(trajectory.images) == 20 and trajectory.loops[19] == {8, 9}
    pipeline = FeaturePipeline(resolve_preset("fast", long_side=TEST_LONG_SIDE))
    features = trajectory_vectors(trajectory, pipeline, tmp_path)
    assert list(tmp_path.iterdir())  # cached for the next run
    vectors = unit_embeddings(features, alpha=0.7)

    # the robot's own last 10 frames (its whole day run) never answer: day frame i may close
    # a loop with night frames < i, so with frame i - 1 (its right neighbour) only
    # through the service's observe path (database, index, sequence code)
    def through_service(length: int) -> dict:  # type: ignore[type-arg]
        settings = OnlineSettings(length=length, exclude_recent=10)
        answers = service_observations(
            trajectory,
            features,
            pipeline,
            alpha=0.7,
            length=length,
            exclude_recent=10,
            consistency=3,
        )
        return replay(trajectory, vectors, settings, [Observation(*a) for a in answers])

    sequence, single = through_service(3), through_service(1)
    assert sequence["answerable"] == single["answerable"] == 9
    assert sequence["decisions"]["k=1"]["best_match_right"] >= 7 / 9
    assert single["decisions"]["k=1"]["best_match_right"] < 7 / 9
