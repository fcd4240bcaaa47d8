"""``loopnet eval`` on data it has never seen: a place/view/image tree with one broken image,
a wrong layout, a query stride over a warm cache, and a run that stops midway."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from service.cli import main
from service.evaluation.datasets import detect_layout, load_dataset
from tests.conftest import gardens_point_day_night

PLACES = 6
QUICK = [
    "--long-side",
    "256",
    "--extractors",
    "xfeat",
    "--alphas",
    "0,1",
    "--baselines",
    "",
    "--retrain-shots",
    "",
    "--examples",
    "2",
]


@pytest.fixture
def views_tree(tmp_path: Path) -> Path:
    """``p<k>/i0/a.jpg`` (night) and ``p<k>/i1/b.jpg`` (day) per place, one broken image."""
    root = tmp_path / "campus-views"
    for k in range(PLACES):
        for view, side, name in (("i0", "ref", "a.jpg"), ("i1", "query", "b.jpg")):
            (root / f"p{k}" / view).mkdir(parents=True, exist_ok=True)
            (root / f"p{k}" / view / name).write_bytes(gardens_point_day_night(k, side))
    good = gardens_point_day_night(2, "query")
    (root / "p2" / "i1" / "c.jpg").write_bytes(good[: len(good) // 3])  # cut short
    return root


def test_place_view_image_trees_are_places(views_tree: Path) -> None:
    assert detect_layout(views_tree) == "places"
    dataset = load_dataset(views_tree, layout="places")
    assert [r.path.relative_to(views_tree).as_posix() for r in dataset.references][:2] == [
        "p0/i0/a.jpg",
        "p1/i0/a.jpg",
    ]
    assert len(dataset.queries) == PLACES + 1


def test_eval_skips_a_broken_image_reports_as_it_goes_and_reuses_its_cache(
    views_tree: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    out, cache = tmp_path / "all", tmp_path / "cache"
    argv = ["eval", str(views_tree), "--out", str(out), "--cache-dir", str(cache), *QUICK]
    assert main([*argv, "--layout", "places"]) == 0
    report = json.loads((out / "report.json").read_text())
    broken = str(views_tree / "p2" / "i1" / "c.jpg")
    assert list(report["dataset"]["unreadable_images"]) == [broken]
    assert any(broken in line for line in report["dataset"]["excluded"])
    assert report["dataset"]["queries"] == PLACES and report["partial"] is None
    # the long side in use is logged, and no faiss-loader or alembic INFO lines break the bars
    assert "long_side=256" in caplog.text
    noisy = [r for r in caplog.records if r.name.startswith(("faiss", "alembic"))]
    assert [r for r in noisy if r.levelno < logging.WARNING] == []

    # every 2nd query only: the cached CNN pass serves it
    strided = tmp_path / "strided"
    argv[3] = str(strided)
    assert main([*argv, "--query-stride", "2"]) == 0
    report = json.loads((strided / "report.json").read_text())
    service_row = next(m for m in report["methods"] if m["name"] == "loopnet-xfeat-uncalibrated")
    assert service_row["details"]["features_from_cache"] is True
    assert any("every 2nd query" in line for line in report["dataset"]["excluded"])


def test_a_layout_that_does_not_fit_is_one_line(
    views_tree: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["eval", str(views_tree), "--out", str(tmp_path / "r"), "--layout", "vpr-bench"]
    assert main([*argv, *QUICK]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("error: ") and "vpr-bench" in error and "\n" not in error


def test_a_run_stopped_midway_keeps_the_rows_it_finished(views_tree: Path, tmp_path: Path) -> None:
    out = tmp_path / "stopped"
    argv = ["eval", str(views_tree), "--out", str(out), *QUICK]
    argv[argv.index("--baselines") + 1] = "seqslam-sad,no-such-baseline"
    with pytest.raises(ValueError, match="no-such-baseline"):
        main(argv)
    report = json.loads((out / "report.json").read_text())
    assert report["partial"].startswith("stopped before")
    # too few references for a calibration: the uncalibrated rows only
    assert [m["name"] for m in report["methods"]] == [
        "loopnet-xfeat-uncalibrated",
        "xfeat-local-only-uncalibrated",
        "loopnet-xfeat-served",
        "global-only-uncalibrated",
        "seqslam-sad",
    ]
    assert "a calibration needs" in report["skipped"]["calibration"]
    assert "**Partial report**" in (out / "report.md").read_text()
