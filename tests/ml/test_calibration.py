"""Atlas calibration: VLAD, branch whitening, the impostor score, and the bundle of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.ml import whitening as whitening_module
from service.ml.aggregators import MeanAggregator, VladAggregator, fit_aggregator, fit_vocabulary
from service.ml.calibration import (
    Calibration,
    CalibrationConfig,
    CalibrationInputs,
    aggregate_frames,
)
from service.ml.features import LocalFeatures
from service.ml.heads import LoopNetHeads
from service.ml.impostors import (
    MIN_PAIRS,
    ImpostorModel,
    frames_for_impostor_model,
    impostor_pairs,
)
from service.ml.pipeline import embed_vectors
from service.ml.whitening import Whitening, WhiteningConfig

# ----- VLAD ---------------------------------------------------------------------------------


def test_vlad_of_a_frame_matches_the_hand_computed_vector() -> None:
    vlad = VladAggregator(np.array([[1.0, 0.0], [0.0, 1.0]]))
    descriptors = np.array([[0.8, 0.6], [0.6, 0.8], [1.0, 0.0]], np.float32)
    # x1, x3 -> word 0 (residuals [-0.2, 0.6] and [0, 0]); x2 -> word 1 (residual [0.6, -0.2]).
    # Intra-normalised: [-1, 3]/sqrt(10) and [3, -1]/sqrt(10); signed square roots
    # -0.5623, 0.9740, 0.9740, -0.5623; L2-normalised: -1/(2 sqrt 2), sqrt(6)/4, ...
    expected = np.array(
        [-1 / (2 * np.sqrt(2)), np.sqrt(6) / 4, np.sqrt(6) / 4, -1 / (2 * np.sqrt(2))]
    )
    np.testing.assert_allclose(vlad.aggregate(descriptors), expected, atol=1e-6)
    assert vlad.dim == 4


def test_vlad_leaves_unused_words_zero_and_empty_frames_zero() -> None:
    vlad = VladAggregator(np.array([[1.0, 0.0], [0.0, 1.0]]))
    only_word_one = vlad.aggregate(np.array([[0.1, 0.9], [-0.1, 0.95]], np.float32))
    assert np.all(only_word_one[:2] == 0.0)
    assert np.linalg.norm(only_word_one) == pytest.approx(1.0, abs=1e-6)
    empty = vlad.aggregate(np.zeros((0, 2), np.float32))
    assert empty.shape == (4,) and not empty.any()
    with pytest.raises(ValueError, match="N x 2"):
        vlad.aggregate(np.zeros((3, 5), np.float32))


def _reference_vlad(centroids: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
    """The VLAD formula of the module doc, one dense step at a time (float64)."""
    x, c = descriptors.astype(np.float64), centroids.astype(np.float64)
    words = ((x[:, None] - c[None]) ** 2).sum(2).argmin(1)
    blocks = np.stack([(x[words == k] - c[k]).sum(0) for k in range(len(c))])
    norms = np.linalg.norm(blocks, axis=1, keepdims=True)
    flat = (blocks / np.where(norms > 0, norms, 1.0)).reshape(-1)
    flat = np.sign(flat) * np.sqrt(np.abs(flat))
    return flat / np.linalg.norm(flat)


def test_vlad_of_stored_float16_frames_matches_the_formula() -> None:
    # DISK-sized (128 words of 128-d, 1,024 keypoints), read-only float16 as the store gives
    rng = np.random.default_rng(5)
    centroids = rng.normal(size=(128, 128)).astype(np.float32)
    vlad = VladAggregator(centroids)
    for _ in range(3):
        stored = centroids[rng.integers(0, 128, 1024)] + rng.normal(size=(1024, 128))
        blob = stored.astype(np.float16).tobytes()
        descriptors = np.frombuffer(blob, np.float16).reshape(1024, 128)
        np.testing.assert_allclose(
            vlad.aggregate(descriptors), _reference_vlad(centroids, descriptors), atol=1e-6
        )


def test_aggregate_frames_stacks_each_frames_vector() -> None:
    rng = np.random.default_rng(6)
    vlad = VladAggregator(rng.normal(size=(8, 16)).astype(np.float32))
    frames = [rng.normal(size=(n, 16)).astype(np.float16) for n in (30, 0, 5)]
    scores = [np.ones(len(f), np.float32) for f in frames]
    stacked = aggregate_frames(vlad, frames, scores)
    assert stacked.shape == (3, vlad.dim) and stacked.dtype == np.float32
    for row, frame in zip(stacked, frames, strict=True):
        np.testing.assert_array_equal(row, vlad.aggregate(frame))
    assert aggregate_frames(vlad, [], []).shape == (0, vlad.dim)


def test_vocabulary_is_deterministic_and_finds_separated_clusters() -> None:
    rng = np.random.default_rng(1)
    centres = np.eye(8, 64, dtype=np.float32) * 5
    sample = np.concatenate([c + 0.1 * rng.normal(size=(200, 64)) for c in centres]).astype(
        np.float32
    )
    first = fit_vocabulary(sample, words=16, seed=3)
    np.testing.assert_array_equal(first, fit_vocabulary(sample, words=16, seed=3))
    nearest = np.linalg.norm(first[:, None] - centres[None], axis=2).min(0)
    assert nearest.max() < 0.2  # every true centre has a word next to it
    with pytest.raises(ValueError, match="too few|cannot train"):
        fit_vocabulary(sample[:4], words=8)


def test_aggregator_registry() -> None:
    sample = np.random.default_rng(0).normal(size=(500, 64)).astype(np.float32)
    assert isinstance(fit_aggregator("mean", sample), MeanAggregator)
    vlad = fit_aggregator("vlad", sample, words=16)
    assert isinstance(vlad, VladAggregator) and vlad.dim == 16 * 64  # XFeat-sized
    with pytest.raises(ValueError, match="unknown aggregator"):
        fit_aggregator("netvlad", sample)


# ----- whitening ----------------------------------------------------------------------------


def _known_covariance(
    n: int, eigenvalues: np.ndarray, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rotation, _ = np.linalg.qr(rng.normal(size=(len(eigenvalues), len(eigenvalues))))
    data = (rng.normal(size=(n, len(eigenvalues))) * np.sqrt(eigenvalues)) @ rotation.T
    return (data + 3.0).astype(np.float32), rotation


def test_whitening_gives_identity_covariance_on_the_kept_axes() -> None:
    eigenvalues = np.array([100.0, 25.0, 9.0, 4.0] + [0.01] * 16)
    data, rotation = _known_covariance(40_000, eigenvalues)
    fitted = Whitening.fit(data, WhiteningConfig(max_dims=4, shrinkage=0.0))
    assert fitted.dim == 4
    np.testing.assert_allclose(fitted.eigenvalues, eigenvalues[:4], rtol=0.05)
    projected = fitted.project(data)
    np.testing.assert_allclose(np.cov(projected.T), np.eye(4), atol=0.05)
    # the kept axes span the true leading axes
    overlap = fitted.axes.T @ rotation[:, :4]
    np.testing.assert_allclose(np.linalg.svd(overlap)[1], np.ones(4), atol=0.01)
    assert np.allclose(np.linalg.norm(fitted.transform(data[:10]), axis=1), 1.0, atol=1e-5)


def test_shrinkage_keeps_weak_axes_from_being_blown_up() -> None:
    eigenvalues = np.array([100.0, 10.0, 1.0, 0.1])
    data, _ = _known_covariance(40_000, eigenvalues, seed=2)
    shrink = 1.0
    fitted = Whitening.fit(data, WhiteningConfig(max_dims=4, shrinkage=shrink))
    variances = np.var(fitted.project(data), axis=0)
    expected = eigenvalues / (eigenvalues + shrink * eigenvalues.mean())
    np.testing.assert_allclose(variances, expected, rtol=0.05)
    assert variances[-1] < 0.01  # plain whitening would have made it 1
    unscaled = Whitening.fit(data, WhiteningConfig(max_dims=4, whiten=False))
    np.testing.assert_allclose(np.var(unscaled.project(data), axis=0), eigenvalues, rtol=0.05)


def test_small_atlases_keep_few_axes() -> None:
    data = np.random.default_rng(0).normal(size=(40, 1280)).astype(np.float32)
    assert Whitening.fit(data, WhiteningConfig(max_dims=256, dims_fraction=0.5)).dim == 20
    assert WhiteningConfig(max_dims=256).kept_dims(100_000, 1280) == 256
    with pytest.raises(ValueError, match="at least 2"):
        Whitening.fit(data[:1], WhiteningConfig())
    with pytest.raises(ValueError, match="not all equal"):
        Whitening.fit(np.ones((5, 3), np.float32), WhiteningConfig())


def test_randomised_fit_agrees_with_the_exact_one(monkeypatch: pytest.MonkeyPatch) -> None:
    eigenvalues = np.concatenate([np.geomspace(50, 1, 10), np.full(190, 0.01)])
    data, _ = _known_covariance(3_000, eigenvalues, seed=4)
    config = WhiteningConfig(max_dims=10)
    exact = Whitening.fit(data, config)
    monkeypatch.setattr(whitening_module, "EXACT_LIMIT", 50)
    fast = Whitening.fit(data, config)
    np.testing.assert_allclose(fast.eigenvalues, exact.eigenvalues, rtol=1e-3)
    np.testing.assert_allclose(np.abs(fast.axes.T @ exact.axes), np.eye(10), atol=1e-2)
    np.testing.assert_allclose(fast.scale, exact.scale, rtol=1e-3)


@pytest.mark.filterwarnings("error")  # read-only vectors (as stored) need no copy warning
def test_a_fit_started_from_a_nearby_one_agrees_with_the_exact_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a calibration's full fit, started from its probe's (four fifths of the same vectors)
    eigenvalues = np.concatenate([np.geomspace(50, 1, 10), np.full(190, 0.01)])
    data, _ = _known_covariance(3_000, eigenvalues, seed=4)
    data.flags.writeable = False
    config = WhiteningConfig(max_dims=10)
    exact = Whitening.fit(data, config)
    monkeypatch.setattr(whitening_module, "EXACT_LIMIT", 50)
    warm = Whitening.fit(data, config, near=Whitening.fit(data[:2_400], config))
    np.testing.assert_allclose(warm.eigenvalues, exact.eigenvalues, rtol=1e-3)
    np.testing.assert_allclose(np.abs(warm.axes.T @ exact.axes), np.eye(10), atol=1e-2)
    with pytest.raises(ValueError, match="cannot start"):
        Whitening.fit(data[:, :100], config, near=exact)


# ----- impostor score -----------------------------------------------------------------------


def test_impostor_pairs_skip_neighbours_of_one_robot() -> None:
    robots = ["a"] * 100 + ["b"] * 100
    order = np.concatenate([np.arange(100)[::-1], np.arange(100)])
    first, second = impostor_pairs(robots, order, pairs=5_000, min_gap=10, seed=1)
    same = np.array([robots[i] == robots[j] for i, j in zip(first, second, strict=True)])
    assert same.any() and (~same).any()
    assert np.all(np.abs(order[first[same]] - order[second[same]]) >= 10)
    with pytest.raises(ValueError, match="far enough"):
        impostor_pairs(["a"] * 5, np.arange(5), min_gap=10)


def test_impostor_pairs_leave_out_the_places_of_known_revisits() -> None:
    """Robot b drives robot a's route again (frame i of b is frame i of a): its frames near
    a known revisit pair's are that place, not impostors, whichever side the pair names."""
    robots = ["a"] * 100 + ["b"] * 100
    order = np.concatenate([np.arange(100), np.arange(100)])
    revisits = np.array([[10, 110], [160, 60]])  # a10 ~ b10, b60 ~ a60

    def near_revisit(first: np.ndarray, second: np.ndarray) -> np.ndarray:
        pairs = np.stack([first, second], 1)
        pairs = np.concatenate([pairs, pairs[:, ::-1]])
        a, b = pairs[:, 0], pairs[:, 1]
        return ((a == 10) & (np.abs(b - 110) < 10)) | ((a == 160) & (np.abs(b - 60) < 10))

    plain = impostor_pairs(robots, order, pairs=20_000, min_gap=10, seed=1)
    assert near_revisit(*plain).any()
    first, second = impostor_pairs(
        robots, order, pairs=20_000, min_gap=10, seed=1, same_place=revisits
    )
    assert not near_revisit(first, second).any()
    assert len(first) > 0.99 * len(plain[0])  # only those pairs are left out


def test_impostor_score_is_the_surprise_of_a_cosine() -> None:
    cosines = np.random.default_rng(0).normal(0.2, 0.1, size=100_000)
    model = ImpostorModel.fit(cosines)
    assert model.p_value(np.quantile(cosines, 0.9)) == pytest.approx(0.1, abs=0.005)
    assert model.score(np.quantile(cosines, 0.99)) == pytest.approx(2.0, abs=0.05)
    grid = np.linspace(-1, 1, 401)
    scores = model.score(grid)
    assert np.all(np.diff(scores) >= 0) and scores[0] == 0.0
    assert np.isfinite(scores[-1]) and scores[-1] > scores[-50]  # ordered beyond the sample
    again = ImpostorModel.from_state(model.state())
    np.testing.assert_allclose(again.score(grid), scores)


def test_one_threshold_means_the_same_on_differently_spread_atlases() -> None:
    rng = np.random.default_rng(3)
    tight = ImpostorModel.fit(rng.normal(0.9, 0.01, 50_000))  # squeezed cosines
    wide = ImpostorModel.fit(rng.normal(0.1, 0.2, 50_000))
    # the cosine at which one impostor in 1,000 passes differs; its score does not
    assert tight.score(0.9 + 3.09 * 0.01) == pytest.approx(3.0, abs=0.15)
    assert wide.score(0.1 + 3.09 * 0.2) == pytest.approx(3.0, abs=0.15)


# ----- the calibration bundle ---------------------------------------------------------------


def _synthetic_atlas(n: int = 120, dim: int = 64, seed: int = 0) -> CalibrationInputs:
    rng = np.random.default_rng(seed)
    places = rng.normal(size=(-(-n // 4), 8, dim))  # each place has its own descriptor pattern

    def frame(i: int) -> np.ndarray:
        d = places[i // 4][rng.integers(0, 8, 60)] + 0.3 * rng.normal(size=(60, dim))
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float16)

    descriptors = [frame(i) for i in range(n)]
    descriptors[7] = np.zeros((0, dim), np.float16)  # a frame without keypoints
    return CalibrationInputs(
        descriptors=descriptors,
        scores=[np.ones(len(d), np.float32) for d in descriptors],
        global_vectors=rng.normal(size=(n, 96)).astype(np.float32),
        robots=["r"] * n,
        order=np.arange(n),
    )


def test_calibration_fits_embeds_and_round_trips(tmp_path: Path) -> None:
    inputs = _synthetic_atlas()
    config = CalibrationConfig(words=8, alpha=0.5)
    fitted = Calibration.fit(inputs, config)
    calibration = fitted.calibration
    assert calibration.local_whitening.input_dim == 8 * 64
    assert calibration.local_whitening.dim <= 60 and calibration.global_whitening.dim <= 60
    assert not fitted.local_branch[7].any()  # no keypoints: no local evidence
    embedded = calibration.embed_many(inputs.descriptors, inputs.scores, inputs.global_vectors)
    np.testing.assert_allclose(
        embedded, calibration.fuse(fitted.local_branch, fitted.global_branch), atol=1e-6
    )
    # untrained heads over the calibrated branches compute the same fusion
    heads = LoopNetHeads(calibration.heads_config()).eval()
    np.testing.assert_allclose(
        embed_vectors(heads, fitted.local_branch, fitted.global_branch), embedded, atol=1e-5
    )
    one = LocalFeatures(
        np.zeros((60, 2), np.float32),
        inputs.descriptors[3].astype(np.float32),
        np.ones(60, np.float32),
    )
    np.testing.assert_allclose(
        calibration.embed(one, inputs.global_vectors[3]), embedded[3], atol=1e-6
    )
    # same place (frames of one group of 4) beats other places on the local branch
    same = np.mean([fitted.local_branch[i] @ fitted.local_branch[i + 1] for i in range(0, 100, 4)])
    other = np.mean([fitted.local_branch[i] @ fitted.local_branch[i + 50] for i in range(0, 50, 4)])
    assert same > other + 0.3
    path = tmp_path / "calibration.npz"
    calibration.save(path)
    loaded = Calibration.load(path)
    assert loaded.config == calibration.config
    np.testing.assert_array_equal(
        loaded.embed_many(inputs.descriptors, inputs.scores, inputs.global_vectors), embedded
    )
    np.testing.assert_array_equal(
        loaded.score(np.linspace(0, 1, 11)), calibration.score(np.linspace(0, 1, 11))
    )
    refit = Calibration.fit(inputs, config).calibration  # deterministic per seed
    np.testing.assert_array_equal(
        refit.embed_many(inputs.descriptors, inputs.scores, inputs.global_vectors), embedded
    )


def test_the_impostor_probe_never_starts_from_the_full_fit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the full fit starts from the probe's axes, never the reverse: the probe must not see
    # the frames it holds out, so its score model is the one of a probe fitted on its own
    monkeypatch.setattr(whitening_module, "EXACT_LIMIT", 20)  # the randomised SVD, as at scale
    inputs, config = _synthetic_atlas(), CalibrationConfig(words=8)
    fitted = Calibration.fit(inputs, config).calibration
    fit = Whitening.fit.__func__  # type: ignore[attr-defined]

    def cold(cls: type[Whitening], *args: object, **kwargs: object) -> Whitening:
        return fit(cls, *args, **{**kwargs, "near": None})  # type: ignore[no-any-return]

    monkeypatch.setattr(Whitening, "fit", classmethod(cold))
    unstarted = Calibration.fit(inputs, config).calibration
    assert fitted.spread == unstarted.spread
    assert fitted.impostors is not None and unstarted.impostors is not None
    np.testing.assert_array_equal(fitted.impostors.quantiles, unstarted.impostors.quantiles)


def test_calibration_variants_and_bad_inputs() -> None:
    inputs = _synthetic_atlas()
    mean = Calibration.fit(inputs, CalibrationConfig(aggregator="mean", alpha=0.7)).calibration
    assert mean.local_whitening.input_dim == 64
    local_only = mean.with_alpha(1.0)
    d, _ = local_only.branch_vectors(
        inputs.descriptors[:3], inputs.scores[:3], inputs.global_vectors[:3]
    )
    np.testing.assert_allclose(
        local_only.embed_many(inputs.descriptors[:3], inputs.scores[:3], inputs.global_vectors[:3])[
            :, : d.shape[1]
        ],
        d,
        atol=1e-6,
    )
    with pytest.raises(ValueError, match="frame count"):
        CalibrationInputs(
            inputs.descriptors[:3],
            inputs.scores,
            inputs.global_vectors,
            inputs.robots,
            inputs.order,
        )
    with pytest.raises(ValueError, match="alpha"):
        CalibrationConfig(alpha=1.5)
    with pytest.raises(ValueError, match="too few"):
        Calibration.fit(inputs, CalibrationConfig(words=100_000))


def test_impostor_pairs_can_pair_unseen_frames_with_seen_ones() -> None:
    mask = np.arange(50) < 10
    first, second = impostor_pairs(["r"] * 50, np.arange(50), pairs=500, min_gap=3, first_from=mask)
    assert mask[first].all() and not mask[second].any()


def test_calibrated_score_holds_its_meaning_on_frames_the_fit_never_saw() -> None:
    calibration = Calibration.fit(_synthetic_atlas(n=400), CalibrationConfig(words=8)).calibration
    stored = _synthetic_atlas(n=400)
    unseen = _synthetic_atlas(n=80, seed=9)  # other places: every pair is an impostor
    cosines = (
        calibration.embed_many(unseen.descriptors, unseen.scores, unseen.global_vectors)
        @ calibration.embed_many(stored.descriptors, stored.scores, stored.global_vectors).T
    )
    passing = float(np.mean(calibration.score(cosines) >= 2.0))  # nominally 1 pair in 100
    assert 0.002 <= passing <= 0.05


def test_impostor_pairs_are_distinct_on_a_small_atlas() -> None:
    first, second = impostor_pairs(["r"] * 12, np.arange(12), pairs=10_000, min_gap=5)
    keys = {(min(i, j), max(i, j)) for i, j in zip(first, second, strict=True)}
    assert len(keys) == len(first) == sum(1 for i in range(12) for j in range(i + 5, 12))


def test_the_fewest_frames_for_an_impostor_model_calibrate() -> None:
    """Ten frames of one robot give 15 distinct impostor pairs, too few: the calibration job
    once accepted them and failed inside (and `loopnet eval` of a 10-frame dataset with it)."""
    fewest = frames_for_impostor_model()
    assert fewest == 11
    fitted = Calibration.fit(_synthetic_atlas(n=fewest), CalibrationConfig(words=8))
    assert fitted.calibration.impostors is not None
    assert fitted.calibration.impostors.pairs >= MIN_PAIRS
    with pytest.raises(ValueError, match="at least 20 distinct pairs"):
        Calibration.fit(_synthetic_atlas(n=fewest - 1), CalibrationConfig(words=8))


def test_a_tiny_atlas_gets_a_finite_modest_score() -> None:
    """Ten frames give a few dozen impostor pairs: the tail must not collapse onto them (it
    once did, scoring an ordinary best match in the hundreds of thousands)."""
    fitted = Calibration.fit(_synthetic_atlas(n=12), CalibrationConfig(words=8))
    model = fitted.calibration.impostors
    assert model is not None and model.pairs < 100
    top = float(model.quantiles[-1])
    assert model.score(top + 0.05) < 6.0
    cosines = np.random.default_rng(1).normal(0.0, 0.05, 40)
    few = ImpostorModel.fit(cosines)
    assert few.tail_scale >= 0.5 * 0.05 * 0.3  # about twice the normal excess at its q99
    assert few.score(0.25) < 10.0
