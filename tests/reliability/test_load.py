"""The load script's code path at a small scale, against a real server process on loopback."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.load import LiveServer, LoadConfig, run_load
from tests.conftest import DATA_DIR, TEST_LONG_SIDE, TEST_MAX_KEYPOINTS

IMAGES = DATA_DIR / "gardenspoint_cohog200"
SERVER_ENV = {
    "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
    "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
}


@pytest.mark.slow
def test_four_robots_ingest_and_query_without_errors(tmp_path: Path) -> None:
    config = LoadConfig(robots=4, requests=10, duration_s=240, images=IMAGES)
    with LiveServer(tmp_path / "data", SERVER_ENV) as server:
        report = run_load(server.url, config)
    print(report.summary())
    assert report.errors == []
    assert not any(key.endswith((" 500", "transport-error")) for key in report.statuses)
    assert report.count("ingest") == 20 and report.count("query") == 20
    assert report.percentile("ingest", 95) is not None


@pytest.mark.slow
def test_saturated_server_answers_503_with_retry_after_and_robots_get_through(
    tmp_path: Path,
) -> None:
    """One inference slot and no queue: concurrent robots meet 503 + Retry-After (never a
    time-out or a 500), wait as told, and every request gets through in the end."""
    env = {**SERVER_ENV, "LOOPNET_INFERENCE_WORKERS": "1", "LOOPNET_INFERENCE_QUEUE": "0"}
    config = LoadConfig(robots=4, requests=4, duration_s=240, images=IMAGES)
    with LiveServer(tmp_path / "data", env) as server:
        report = run_load(server.url, config)
    print(report.summary())
    assert report.status_count(503) > 0  # saturation happened ...
    assert len(report.retry_after_s) == report.status_count(503)  # ... each with Retry-After
    assert report.errors == []  # no 500, no time-out, no 503 without Retry-After
    assert report.count("ingest") + report.count("query") == 16
