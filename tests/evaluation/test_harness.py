"""The evaluation harness end to end on a small real slice of Gardens Point (20 places)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from service.evaluation.runner import EvalConfig, EvalResult, run_evaluation
from tests.conftest import DATA_DIR, TEST_LONG_SIDE, TEST_MAX_KEYPOINTS

PLACES = 20


@pytest.fixture(scope="module")
def slice_run(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    output = tmp_path_factory.mktemp("eval")
    config = EvalConfig(
        dataset=DATA_DIR / "gardenspoint_cohog200",
        output=output,
        tolerance=2,
        long_side=TEST_LONG_SIDE,
        max_keypoints=TEST_MAX_KEYPOINTS,
        limit=PLACES,
        examples=3,
    )
    return config, run_evaluation(config)


@pytest.mark.slow
def test_one_run_writes_every_method_into_the_report(slice_run) -> None:  # type: ignore[no-untyped-def]
    config, result = slice_run
    output: Path = config.output
    for name in ("report.json", "report.md", "pr_curves.png", "examples.png"):
        assert (output / name).stat().st_size > 0, name
    report = json.loads((output / "report.json").read_text())
    names = [m["name"] for m in report["methods"]]
    assert names[0] == "loopnet-disk"  # the calibrated service path, default extractor
    expected = {"loopnet-xfeat", "disk-calibrated-alpha0.7", "disk-calibrated-alpha0.3"}
    expected |= {"disk-local-only", "xfeat-local-only", "global-only", "bow-orb", "seqslam-sad"}
    expected |= {"disk-mean-calibrated", "disk-calibrated-unwhitened"}
    expected |= {"loopnet-disk-uncalibrated", "disk-uncalibrated-alpha0.5"}
    expected |= {"disk-local-only-uncalibrated", "global-only-uncalibrated"}
    assert expected <= set(names)
    assert report["dataset"]["references"] == PLACES and report["dataset"]["queries"] == 22
    assert "99x56 upsampled to 256x145" in report["working_sizes"]["note"]
    for m in report["methods"]:
        assert 0.0 <= m["recall@1"] <= m["recall@5"] <= m["recall@10"] <= 1.0, m["name"]
        assert m["submap_accuracy"] >= m["frame_accuracy"] - 1e-9, m["name"]
        assert 0.0 <= m["auc_pr"] <= m["recall@1"] + 1e-9, m["name"]
        assert m["query_ms"]["n"] == 22
    assert report["target"]["met"] in (True, False) and "margin" in report["target"]["verdict"]
    markdown = (output / "report.md").read_text()
    assert "| LoopNet DISK calibrated α=0.5 (service path) |" in markdown
    assert "±2 frames" in markdown


@pytest.mark.slow
def test_the_served_rows_sweep_the_loop_probability(slice_run) -> None:  # type: ignore[no-untyped-def]
    """One row per extractor answered as the service serves (verification, calibrated score,
    the loop decision at the defaults): its PR sweep is over loop_probability, in [0, 1], and
    its operating point at the default threshold is reported."""
    config, _ = slice_run
    report = json.loads((config.output / "report.json").read_text())
    rows = {m["name"]: m for m in report["methods"]}
    for extractor in ("disk", "xfeat"):
        served = rows[f"loopnet-{extractor}-served"]
        assert served["kind"] == "served"
        thresholds = served["pr_curve"]["threshold"]
        assert thresholds and all(0.0 <= t <= 1.0 for t in thresholds)
        point = served["details"]["operating_point"]
        assert point["threshold"] == 0.98
        assert set(point) >= {"precision", "recall", "false_loops_per_1000"}
        assert 0.0 <= point["recall"] <= served["recall@1"] + 1e-9
        assert len(served["details"]["per_query_parts"]) == 22
        assert served["details"]["verification"]["top"] == 5


@pytest.mark.slow
def test_service_path_and_ablation_path_agree_and_the_branches_are_real(slice_run) -> None:  # type: ignore[no-untyped-def]
    _, result = slice_run
    by_name = {m.name: m for m in result.methods}
    # alpha 0.7 re-embedded from the stored vectors ranks as the service did
    uncalibrated = by_name["loopnet-disk-uncalibrated"]
    assert uncalibrated.details["top1_agreement_with_ablation_path"] == 1.0
    # real pretrained features on a real route: far above chance (about 5 of 20 within ±2)
    assert by_name["global-only-uncalibrated"].recall[1] >= 0.7
    assert by_name["disk-local-only-uncalibrated"].recall[5] >= 0.7
    # the calibration saw the 20 stored references only, and kept few axes for so few
    calibrated = by_name["loopnet-disk"]
    assert calibrated.details["fitted_on"].startswith("stored reference frames only")
    assert calibrated.details["local_dims"] <= 10 and calibrated.details["global_dims"] <= 10
    assert calibrated.recall[5] >= 0.7
    assert by_name["seqslam-sad"].recall[5] >= 0.5


def rerun_from_cache(config: EvalConfig, folder: str, **changes: object) -> EvalResult:
    """The slice again, DISK at alpha 0.7 only, its CNN outputs read from the first run's cache."""
    return run_evaluation(
        replace(
            config,
            output=config.output / folder,
            cache_dir=config.output / "cache",
            extractors=("disk",),
            baselines=(),
            alphas=(0.7,),
            **changes,  # type: ignore[arg-type]
        )
    )


@pytest.mark.slow
def test_a_second_run_reads_the_feature_cache(slice_run) -> None:  # type: ignore[no-untyped-def]
    config, first = slice_run
    second = rerun_from_cache(config, "again")
    again, before = (
        {m.name: m for m in run.methods}["loopnet-disk-uncalibrated"] for run in (second, first)
    )
    assert again.details["features_from_cache"] is True
    assert (again.ranking.indices == before.ranking.indices).all()
    # the descriptors came back from the cache too: the calibrated rows agree
    calibrated = [{m.name: m for m in run.methods}["loopnet-disk"] for run in (second, first)]
    assert (calibrated[0].ranking.indices == calibrated[1].ranking.indices).all()


@pytest.mark.slow
def test_retrained_rows_train_on_shots_and_test_on_the_other_queries(slice_run) -> None:  # type: ignore[no-untyped-def]
    config, first = slice_run
    result = rerun_from_cache(config, "retrained", retrain_shots=(1, 3))
    rows = {(r.protocol, r.shots): r for r in result.retraining}
    assert sorted(rows) == [("map", 1), ("map", 3), ("revisit", 1), ("revisit", 3)]
    queries = len(first.methods[0].ranking.indices)
    submaps = PLACES // config.submap_size
    for (protocol, shots), row in rows.items():
        revisit_shots = 0 if protocol == "map" else queries - row.test_queries
        # map protocol: every query is a test query; revisit: K per submap are training shots
        assert revisit_shots == (0 if protocol == "map" else shots * submaps)
        # map shots come from the submaps outside the job's held-out stretch (one of them)
        assert row.train_frames == shots * (submaps - 1) + revisit_shots
        assert row.gate["frames"] == config.submap_size and row.served in (row.before, row.after)
        assert row.after.query_ms["n"] == row.test_queries == len(row.after.ranking.indices)
        assert row.epochs_run >= 1 and 0 <= row.best_epoch <= row.epochs_run
        assert 0.0 <= row.classifier_submap_accuracy <= 1.0
        for method in (row.before, row.after):
            assert 0.0 <= method.recall[1] <= method.recall[5] <= 1.0
    # the heads start from the calibrated service row, as a job starts from the latest
    # calibration: "before" is its ranking restricted to the same test queries
    calibrated = {m.name: m for m in first.methods}["loopnet-disk"]
    assert rows[("map", 1)].before.recall == calibrated.recall
    assert all(row.calibrated for row in rows.values())
    assert all(
        row.after.label.startswith("LoopNet DISK calibrated, retrained") for row in rows.values()
    )
    spread = rows[("map", 3)].row()["top1_spread"]
    assert set(spread) == {"cosine", "score"} and spread["cosine"]["right"]["n"] >= 1
    report = json.loads((config.output / "retrained" / "report.json").read_text())
    assert [r["protocol"] for r in report["retraining"]] == ["map", "map", "revisit", "revisit"]
    assert "retrained-revisit-k3" in [m["name"] for m in report["methods"]]
    assert "## Retraining" in (config.output / "retrained" / "report.md").read_text()


@pytest.mark.slow
def test_loopnet_eval_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from service.cli import main

    argv = [
        "eval",
        str(DATA_DIR / "gardenspoint_cohog200"),
        "--out",
        str(tmp_path / "report"),
        "--tolerance",
        "2",
        "--long-side",
        "256",
        "--limit",
        "20",  # 10 references give 15 impostor pairs: too few to calibrate (20)
        "--extractors",
        "xfeat",
        "--alphas",
        "0,1",
        "--baselines",
        "seqslam-sad",
        "--retrain-shots",
        "1",
        "--retrain-protocols",
        "map",
        "--retrain-param",
        "positive_window=0",
    ]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| LoopNet XFeat calibrated α=0.5 (service path) |" in printed
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["command"] == "loopnet " + " ".join(argv)  # the command that reproduces it
    assert [m["name"] for m in report["methods"]] == [
        "loopnet-xfeat",
        "xfeat-local-only",
        "xfeat-mean-calibrated",
        "xfeat-calibrated-unwhitened",
        "loopnet-xfeat-uncalibrated",
        "xfeat-local-only-uncalibrated",
        "loopnet-xfeat-served",
        "global-only",
        "global-only-uncalibrated",
        "retrained-map-k1",
        "seqslam-sad",
    ]
    retrained = next(m for m in report["methods"] if m["name"] == "retrained-map-k1")
    assert retrained["details"]["training_config"]["positive_window"] == 0  # --retrain-param
