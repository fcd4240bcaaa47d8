"""``eval-online``'s served row on real frames: the replay answers as the service at its
defaults, the calibration milestone is reached and run during the replay, and the frames
after it are answered by the calibrated version."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from service.evaluation.datasets import load_dataset
from service.evaluation.feature_cache import cache_path
from service.evaluation.loop_ground_truth import trajectory_from_traversals
from service.evaluation.online import OnlineConfig, run_online
from service.evaluation.online_features import trajectory_cache
from service.evaluation.online_served import SERVED_SWEEP
from service.evaluation.online_service import replay_settings
from service.evaluation.served_pass import PARTS
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import resolve_preset
from tests.conftest import DATA_DIR, TEST_LONG_SIDE


def test_the_served_replay_adapts_as_the_services_default_says(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    """The served row's atlas adapts after the service's LOOPNET_ADAPT_AFTER_PAIRS (what a
    deployment runs), a ``-adaptN`` row after N (0: off); the retrieval rows never adapt."""
    monkeypatch.setenv("LOOPNET_ADAPT_AFTER_PAIRS", "700")

    def adapting(served: bool, pairs: int | None = None) -> int:
        return replay_settings(
            tmp_path, exclude_recent=20, consistency=3, served=served, adapt_after_pairs=pairs
        ).adapt_after_pairs

    assert adapting(served=True) == 700
    assert (adapting(True, 500), adapting(True, 0)) == (500, 0)
    assert adapting(served=False) == 0


def test_a_traversals_trajectory_reads_loopnet_evals_cache_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    dataset = load_dataset(DATA_DIR / "gardenspoint_first10", layout="traversals")
    pipeline = FeaturePipeline(resolve_preset("fast", long_side=TEST_LONG_SIDE))
    trajectory = trajectory_from_traversals(dataset)
    assert trajectory_cache(trajectory, pipeline, tmp_path) == cache_path(
        tmp_path, dataset, pipeline
    )


def test_served_replay_calibrates_at_the_milestone_and_answers_calibrated(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Gardens Point first10 as one robot (10 night frames, then 10 day frames): the 16th
    frame's insert reaches the first milestone (16); the calibration runs before frame 16,
    which model version 2 answers with a calibrated score."""
    dataset = load_dataset(DATA_DIR / "gardenspoint_first10", layout="traversals", tolerance=1)
    trajectory = trajectory_from_traversals(dataset)
    config = OnlineConfig(
        trajectory=trajectory,
        output=tmp_path / "report",
        methods=(("loopnet-xfeat-alpha0.7", "xfeat", 0.7),),
        lengths=(1,),
        served_lengths=(3,),
        preset="fast",
        long_side=TEST_LONG_SIDE,
        cache_dir=tmp_path / "cache",
        exclude_recent=10,
    )
    report = run_online(config)
    retrieval, served = report["rows"]
    assert retrieval["method"] == "loopnet-xfeat-alpha0.7" and "operating_point" not in retrieval
    assert served["method"] == "loopnet-xfeat-served"
    assert served["score"] == SERVED_SWEEP and served["settings"]["length"] == 3

    [job] = served["jobs"]
    assert job["kind"] == "calibrate" and job["milestone"] == 16 and job["frame"] == 15
    assert job["status"] == "succeeded" and job["model_version"] == 2
    assert job["frames_at_fit"] == 16 and job["min_inliers"] >= 1
    frames = served["per_frame"]
    assert frames["model_version"] == [1] * 16 + [2] * 4
    score = PARTS.index("score")
    # the score part exists only once the answering version is calibrated
    with_score = [not math.isnan(p[score]) for p in frames["parts"]]
    assert not any(with_score[:16]) and all(with_score[16:])

    # the operating point is the service's own status, scored against the ground truth
    point = served["operating_point"]
    status = np.array(frames["status"])
    right = np.array(
        [r in loops for r, loops in zip(frames["reference"], trajectory.loops, strict=True)]
    )
    assert frames["right"] == right.astype(int).tolist()
    assert point["loops"] == int((status == "loop").sum())
    assert point["false_loops"] == int(((status == "loop") & ~right).sum()) == 0
    assert point["threshold"] == 0.98
    # every night frame (the first run) has no loop partner: none of them is answered right
    assert not right[:10].any() and served["answerable"] == 9
    sweeps = served["sweeps"]
    assert set(sweeps) == {SERVED_SWEEP, "decision.loop_probability", "decision logit"}
    assert sweeps[SERVED_SWEEP] == served["decisions"]
    # every loop the service closed was closable
    closable = np.array(frames["closable"], bool)
    assert closable[status == "loop"].all()
    # the logit orders the answers as the probability does: the same best matches, both sweeps
    # over every answer
    for k in ("k=1", "k=3"):
        assert (
            sweeps["decision logit"][k]["best_match_right"]
            == served["decisions"][k]["best_match_right"]
        )
    by_logit = np.array(frames["loop_probability"])[np.argsort(frames["logit"], kind="stable")]
    assert np.all(np.diff(by_logit) >= -1e-4)

    written = json.loads((tmp_path / "report" / "online.json").read_text())
    assert written["rows"][1]["jobs"][0]["milestone"] == 16
    markdown = (tmp_path / "report" / "online.md").read_text()
    assert "## At the service's defaults" in markdown and "| calibrate | 16 | 15 |" in markdown


def test_eval_online_command_slices_and_reports_the_served_row(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    """``loopnet eval-online DATASET --limit 20 --served 5``: the first 20 summer frames and
    the winter frames whose revisits lie in them; the first milestone (16) runs in the replay,
    the second (32) once the winter run has made the atlas 32 frames large."""
    from service.cli import main

    out = tmp_path / "out"
    argv = [
        "eval-online",
        str(DATA_DIR / "nordland_64x32"),
        "--tolerance",
        "1",
        "--preset",
        "fast",
        "--long-side",
        str(TEST_LONG_SIDE),
        "--alphas",
        "0.7",
        "--sequence",
        "",
        "--served",
        "5",
        "--limit",
        "20",
        "--exclude-recent",
        "5",
        "--served-adapt-after",
        "2",
        "--cache-dir",
        str(tmp_path / "cache"),
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    report = json.loads((out / "online.json").read_text())
    served, adapting = report["rows"]
    assert served["method"] == "loopnet-xfeat-served" and served["frames"] == 41
    assert [(j["milestone"], j["frame"], j["status"]) for j in served["jobs"]] == [
        (16, 15, "succeeded"),
        (32, 31, "succeeded"),
    ]
    assert "| loopnet-xfeat-served | 5 | 0.98 |" in capsys.readouterr().out
    # the same replay with automatic adaptation after every 2 pairs: the milestones' jobs as
    # before, and no adapt job before the atlas holds the 10 pairs a job needs
    assert adapting["method"] == "loopnet-xfeat-served-adapt2"
    jobs = [(j["kind"], j["milestone"], j["frame"]) for j in adapting["jobs"]]
    assert [j for j in jobs if j[0] == "calibrate"] == [
        ("calibrate", 16, 15),
        ("calibrate", 32, 31),
    ]
    assert all(j["status"] == "succeeded" for j in adapting["jobs"])
    # each job's line to the operator comes with it (an adapt job's: the gate's verdict)
    assert all(
        j["message"].startswith(f"model version {j['model_version']} ") for j in adapting["jobs"]
    )
