"""The pairs protocol (issue 26) on a real slice of Gardens Point (40 places, DISK at 256):
query-condition frames observed through the service as served, the pairs observe itself
verified given to a real adapt job, the other queries answered before and after; and the
atlas put back as it was for the passes that follow."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.app.catalog import AtlasService
from service.evaluation.datasets import Dataset, load_dataset
from service.evaluation.pairs_pass import (
    ObservedPairs,
    observed_pairs_rows,
    observed_pairs_runs,
)
from service.evaluation.protocol import assign_submaps
from service.evaluation.report import observed_pairs_table
from service.evaluation.runner import EvalConfig, run_evaluation
from service.evaluation.served_pass import PARTS, ServedAnswers
from service.evaluation.service_pass import ATLAS, PassResult, run_service_pass
from service.ml.features import FrameFeatures
from service.storage import repository as repo
from service.storage.models import Frame, RevisitPair, Submap
from tests.conftest import DATA_DIR, TEST_LONG_SIDE, TEST_MAX_KEYPOINTS

PLACES = 40  # 8 submaps of 5: 3 shots a submap give the job enough verified pairs
COHOG = DATA_DIR / "gardenspoint_cohog200"


def _atlas_state(service: AtlasService) -> dict[str, Any]:
    with service.sessions() as session:
        atlas = repo.get_atlas(session, name=ATLAS)
        return {
            "frames": session.query(Frame).filter_by(atlas_id=atlas.id).count(),
            "submaps": session.query(Submap).filter_by(atlas_id=atlas.id).count(),
            "pairs": session.query(RevisitPair).count(),
            "active": repo.active_model_version(session, atlas_id=atlas.id).version,
        }


def _served_pass(  # type: ignore[no-untyped-def]
    pipeline, cache_dir: Path, dataset: Dataset, submap_of: list[int], **options: Any
) -> PassResult:
    """The harness's service pass over the slice, calibrated and served (k = 10)."""
    return run_service_pass(
        dataset,
        submap_of,
        pipeline,
        k=10,
        cache_dir=cache_dir,
        label="disk",
        calibration={},
        serve=True,
        **options,
    )


@pytest.fixture(scope="module")
def feature_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One feature cache for the module's passes: the slice is extracted once."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def protocol_run(pipeline, feature_cache: Path):  # type: ignore[no-untyped-def]
    dataset = load_dataset(COHOG, tolerance=2).head(PLACES)
    submap_of, _ = assign_submaps(dataset, 5)
    states: dict[str, Any] = {}

    def probe(
        service: AtlasService,
        queries: list[FrameFeatures],
        frame_to_reference: dict[int, int],
        served: ServedAnswers,
    ) -> list[Any]:
        states["before"] = _atlas_state(service)

        def protocol(shots: tuple[int, ...], source: str) -> list[ObservedPairs]:
            return observed_pairs_runs(
                service,
                atlas=ATLAS,
                dataset=dataset,
                submap_of=submap_of,
                queries=queries,
                frame_to_reference=frame_to_reference,
                before=served,
                k=10,
                shots=shots,
                source=source,
            )

        runs = protocol((3, 1), "observe")
        states["labelled"] = protocol((3,), "labelled")
        states["stream"] = protocol((50,), "stream")
        states["after"] = _atlas_state(service)
        states["served"] = served
        return list(runs)

    result = _served_pass(pipeline, feature_cache, dataset, submap_of, in_atlas=probe)
    return dataset, submap_of, result, states


@pytest.mark.slow
def test_observe_records_the_pairs_and_a_real_job_learns_from_them(protocol_run) -> None:  # type: ignore[no-untyped-def]
    dataset, submap_of, result, states = protocol_run
    runs: list[ObservedPairs] = result.in_atlas
    assert [run.shots for run in runs] == [3, 1]
    queries = len(dataset.queries)
    for run in runs:  # K observed frames per submap, the others are the test queries
        assert len(run.observed) == run.shots * (PLACES // 5)
        assert sorted([*run.observed, *run.test]) == list(range(queries))
        assert sum(run.statuses.values()) == len(run.observed)
        # the pairs are observe's own: one per verified closure, judged by the ground truth
        assert set(run.pairs[:, 0]) <= set(run.observed) and (run.pairs[:, 1] >= 0).all()
        truth = [ref in dataset.queries[q].positives for q, ref in run.pairs]
        assert run.right.tolist() == truth
        assert run.statuses.get("loop", 0) <= len(run.pairs) <= len(run.observed)
        # before: the pass's served answers to the same test queries
        served = states["served"].subset(run.test)
        assert (run.before.ranking.indices == served.ranking.indices).all()
    many, few = runs
    assert len(many.pairs) >= 10 and len(few.pairs) < 10
    assert many.job["status"] == "succeeded" and many.job["version"] is not None
    assert many.job["message"].startswith(f"model version {many.job['version']} ")
    assert many.after is not None and len(many.after.ranking.indices) == len(many.test)
    # asked anonymously, as before: no robot's sequence enters the decision
    assert np.isnan(many.after.parts[:, PARTS.index("sequence")]).all()
    assert (many.served is many.after) == many.activated
    assert few.job["status"] == "failed" and "usable revisit pair" in few.job["message"]
    assert few.after is None and few.served is few.before
    # the atlas as it was: no observed frame, pair or submap, the starting version active
    assert states["after"] == states["before"] and states["before"]["pairs"] == 0


@pytest.mark.slow
def test_labelled_shots_give_the_job_their_ground_truth_pairs(protocol_run) -> None:  # type: ignore[no-untyped-def]
    # the revisit protocol as served: every shot stored and labelled with its partner
    dataset, submap_of, _, states = protocol_run
    (run,) = states["labelled"]
    assert run.source == "labelled" and run.statuses == {"labelled": len(run.observed)}
    assert len(run.pairs) == len(run.observed) == 3 * (PLACES // 5) and run.right.all()
    assert run.job["status"] == "succeeded" and run.after is not None
    methods, row = observed_pairs_rows(run, dataset, submap_of, "LoopNet DISK")
    assert row["protocol"] == "pairs-labelled" and "labelled from ground truth" in methods[1].label
    assert [m.name for m in methods] == ["pairs-labelled-k3-before", "pairs-labelled-k3-after"]


@pytest.mark.slow
def test_a_drive_gives_the_job_the_closures_observe_kept(protocol_run) -> None:  # type: ignore[no-untyped-def]
    # the first half of the queries driven in order by one robot; the second half is the test
    dataset, submap_of, _, states = protocol_run
    (run,) = states["stream"]
    queries = len(dataset.queries)
    half = queries // 2
    assert run.source == "stream" and run.shots == 50
    assert run.observed.tolist() == list(range(half))
    assert run.test.tolist() == list(range(half, queries))
    assert sum(run.statuses.values()) == half
    # every loop the drive answered is a pair (verified or its sequence's), and every
    # verified closure: one pair an observation at most
    assert run.statuses.get("loop", 0) <= len(run.pairs) <= half
    assert sum(run.sources.values()) == len(run.pairs)
    assert set(run.sources) <= {"observe", "sequence"}
    assert set(run.pairs[:, 0]) <= set(run.observed)
    # the rest of the drive observed by a robot, with the starting version and the job's
    assert run.drive_before is not None and len(run.drive_before.status) == len(run.test)
    assert run.drive_before.sequence_length == 10  # the service's default
    methods, row = observed_pairs_rows(run, dataset, submap_of, "LoopNet DISK")
    assert row["protocol"] == "pairs-stream" and row["pair_sources"] == run.sources
    assert row["loops_drive-before"]["loops"] == run.drive_before.status.count("loop")
    names = [m.name for m in methods]
    assert names[0] == "pairs-stream-k50-before" and "pairs-stream-k50-drive-before" in names
    if run.after is not None:
        assert run.drive_after is not None and len(run.drive_after.status) == len(run.test)
        assert "a drive over the first 50 % of the queries" in methods[1].label
        assert names[-1] == "pairs-stream-k50-drive-after"
    assert states["after"] == states["before"]  # the drive's frames and pairs are gone


@pytest.mark.slow
def test_the_served_drive_adapts_as_the_service_would(  # type: ignore[no-untyped-def]
    pipeline, feature_cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the served row's robot drives the queries at the service's defaults: once its
    # observations have kept LOOPNET_ADAPT_AFTER_PAIRS revisit pairs, the service queues an
    # adaptation job and a worker runs it before the next frame; the row measures that atlas
    monkeypatch.setenv("LOOPNET_ADAPT_AFTER_PAIRS", "10")
    dataset = load_dataset(COHOG, tolerance=2).head(PLACES)
    submap_of, _ = assign_submaps(dataset, 5)
    result = _served_pass(pipeline, feature_cache, dataset, submap_of, serve_sequence=10)
    drive = result.served_sequence
    assert drive is not None and len(drive.status) == len(dataset.queries)
    assert drive.adapt_after_pairs == 10  # the row's label says so
    assert drive.jobs, "the drive kept 10 pairs: the service queued an adaptation"
    first = drive.jobs[0]
    assert first.kind == "adapt" and first.status == "succeeded", first
    assert 0 < first.frame < len(dataset.queries) - 1
    assert first.message.startswith(f"model version {first.model_version} ")
    # the anonymous served row asked before the drive: the atlas's own setting is off
    assert result.served is not None and not result.served.jobs


def test_a_drive_needs_some_queries_left_to_test() -> None:
    from service.evaluation.pairs_pass import _stream

    assert _stream(40, 50).tolist() == list(range(20))
    assert _stream(3, 1).tolist() == [0] and _stream(2, 99).tolist() == [0]
    for percent in (0, 100):
        with pytest.raises(ValueError, match="between 1 and 99"):
            _stream(40, percent)


@pytest.mark.slow
def test_the_rows_report_before_after_and_served(protocol_run) -> None:  # type: ignore[no-untyped-def]
    dataset, submap_of, result, _ = protocol_run
    many = result.in_atlas[0]
    methods, row = observed_pairs_rows(many, dataset, submap_of, "LoopNet DISK")
    assert [m.name for m in methods] == ["pairs-observe-k3-before", "pairs-observe-k3-after"]
    for method in methods:
        assert method.kind == "served" and method.query_ms["n"] == len(many.test)
    assert row["pairs"] == len(many.pairs) and row["pairs_right"] == int(many.right.sum())
    assert row["test_queries"] == len(many.test) and row["observed"] == len(many.observed)
    side = "after" if many.activated else "before"
    assert row["served"] == ("adapted" if many.activated else "starting")
    for key in ("recall@1", "recall_at_100_precision", "wrong_score_median", "right_score_median"):
        assert row[f"{key}_served"] == row[f"{key}_{side}"] or np.isnan(row[f"{key}_served"])
    assert 0.0 <= row["recall@1_after"] <= 1.0 and 0.0 <= row["recall@1_before"] <= 1.0
    # the score's honesty: every test query with every map frame of another place (at least
    # the impostor model's gap, 5 places here, from each right reference)
    assert many.honesty_before, "the pass's atlas is calibrated: its score can be checked"
    gap = max(5, len(dataset.references) // 20)
    impostors = sum(
        sum(
            all(abs(r - p) >= gap for p in dataset.queries[q].positives)
            for r in range(len(dataset.references))
        )
        for q in many.test
    )
    assert row["impostors_impostor_pairs_before"] == impostors
    for side in ("before", "after") if many.after is not None else ("before",):
        at_2, at_3 = row[f"impostors_at_2_{side}"], row[f"impostors_at_3_{side}"]
        assert 0.0 <= at_3 <= at_2 <= 1.0
    table = observed_pairs_table([row])
    assert f"(of {impostors:,})" in table and "impostor pairs scoring ≥ 2 / ≥ 3" in table


@pytest.mark.slow
def test_loopnet_eval_writes_the_pairs_protocol(tmp_path: Path) -> None:
    config = EvalConfig(
        dataset=COHOG,
        output=tmp_path / "report",
        tolerance=2,
        long_side=TEST_LONG_SIDE,
        max_keypoints=TEST_MAX_KEYPOINTS,
        limit=20,
        extractors=("disk",),
        alphas=(),
        baselines=(),
        examples=1,
        adapt_observe_shots=(1,),
    )
    run_evaluation(config)
    report = json.loads((config.output / "report.json").read_text())
    (row,) = report["observed_pairs"]
    assert row["protocol"] == "pairs-observe" and row["shots"] == 1
    assert "pairs-observe-k1-before" in [m["name"] for m in report["methods"]]
    markdown = (config.output / "report.md").read_text()
    assert "## Adaptation from revisit pairs, as served" in markdown
    assert f"| observe | 1 | {row['observed']} (" in markdown


def test_an_impostor_of_the_honesty_check_is_another_place_by_the_models_rule() -> None:
    from service.evaluation.score_honesty import other_places

    references = np.arange(20)
    kept = other_places(references, frozenset({9, 10}), gap=5)
    assert kept.tolist() == [r <= 4 or r >= 15 for r in range(20)]
    assert other_places(references, frozenset(), gap=5).all()
