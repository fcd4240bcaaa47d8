"""Calibration end to end: Gardens Point frames through the HTTP API, the milestone that
queues the job at ingest, a real worker process, versions, scores and rollback."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.jobs.calibration import MIN_FRAMES
from service.ml.impostors import frames_for_impostor_model
from service.ml.verification import default_min_inliers
from tests.api.helpers import create_atlas
from tests.conftest import make_settings, wait_ready
from tests.jobs.test_retraining_jobs import (
    cohog,
    start_worker,
    stop_worker,
    wait_for_job,
    worker_env,
)

MILESTONE, FRAMES = 60, 100


@pytest.fixture
def client(tmp_path: Path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    settings = make_settings(
        tmp_path / "data", sync_seconds=0.2, calibration_milestones=f"{MILESTONE}, 100000"
    )
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        yield client


def ingest(client: TestClient, places: range) -> dict[int, int]:
    """Reference frames of ``places`` (first half in submap a, second in b): frame id -> place."""
    place_of = {}
    for place in places:
        name, data = cohog(place, "ref")
        response = client.post(
            "/v1/atlases/campus/frames",
            data={"submap": "a" if place < FRAMES // 2 else "b", "robot_id": "r1"},
            files={"image": (name, data)},
        )
        assert response.status_code == 201, response.text
        place_of[response.json()["frame_id"]] = place
    return place_of


def wait_served(client: TestClient, version: int, timeout: float = 20) -> None:
    """Until the app's change-feed follower serves ``version``."""
    deadline = time.monotonic() + timeout
    while query(client, 0)["model_version"] != version:
        assert time.monotonic() < deadline, f"version {version} not served within {timeout} s"
        time.sleep(0.1)


def query(client: TestClient, place: int) -> dict:
    name, data = cohog(place, "query")
    response = client.post(
        "/v1/atlases/campus/query", data={"k": "5"}, files={"image": (name, data)}
    )
    assert response.status_code == 200, response.text
    return response.json()


def jobs(client: TestClient) -> list[dict]:
    return client.get("/v1/atlases/campus/jobs").json()


@pytest.mark.slow
def test_milestone_calibration_through_the_worker(client: TestClient, tmp_path: Path) -> None:
    create_atlas(client, submaps=("a", "b"))
    place_of = ingest(client, range(MILESTONE - 1))
    # below the first milestone: untouched, uncalibrated, no job, cosine decision
    summary = client.get("/v1/atlases/campus").json()
    assert summary["calibration"] == {
        "state": "uncalibrated",
        "version": None,
        "frames_at_fit": None,
    }
    assert jobs(client) == []
    before = query(client, 10)
    assert before["match"]["score"] is None and before["score_threshold"] is None

    place_of |= ingest(client, range(MILESTONE - 1, FRAMES))
    uncalibrated = query(client, 10)
    queued = jobs(client)
    assert [(j["kind"], j["status"], j["params"]) for j in queued] == [
        ("calibrate", "queued", {"milestone": MILESTONE})
    ]  # once: the frames after the milestone queue nothing more

    worker = start_worker(worker_env(tmp_path / "data"))
    try:
        job, _ = wait_for_job(client, queued[0]["id"], worker)
        assert job["status"] == "succeeded", job
        assert job["model_version"] == 2 and job["metrics"]["frames_at_fit"] == FRAMES
        wait_served(client, 2)  # the change-feed follower swaps it in
        summary = client.get("/v1/atlases/campus").json()
        assert summary["active_model_version"] == 2
        assert summary["calibration"] == {
            "state": "calibrated",
            "version": 2,
            "frames_at_fit": FRAMES,
        }
        # verification's minimum inliers, fitted on the atlas's hard impostors
        fitted = job["metrics"]["verification"]
        assert fitted["impostors"] == FRAMES
        assert fitted["min_inliers"] >= 15
        answers = [query(client, place) for place in range(0, FRAMES, 7)]
        for answer in answers:
            assert answer["model_version"] == 2
            assert answer["score_threshold"] == 2.0 + 2.0  # the setting + log10(100 frames)
            assert answer["verification"]["matcher"] == fitted["matcher"]
            assert answer["verification"]["min_inliers"] == fitted["min_inliers"]
            by_similarity = sorted(answer["candidates"], key=lambda c: -c["similarity"])
            scores = [c["score"] for c in by_similarity]
            assert all(s is not None and s >= 0 for s in scores)
            assert scores == sorted(scores, reverse=True)  # monotone in the cosine
        hits = [
            abs(place_of[a["match"]["frame_id"]] - place) <= 2
            for a, place in zip(answers, range(0, FRAMES, 7), strict=True)
        ]
        assert sum(hits) >= 0.8 * len(hits), hits
        # right matches score far above what an impostor pair reaches (median 0.43)
        right = [a["match"]["score"] for a, hit in zip(answers, hits, strict=True) if hit]
        assert float(np.median(right)) > 3.0 and min(right) > 1.5, right

        # an operator's calibration (other parameters) is one more version
        submitted = client.post(
            "/v1/atlases/campus/jobs",
            json={"kind": "calibrate", "calibration": {"words": 16, "alpha": 0.3}},
        )
        assert submitted.status_code == 202, submitted.text
        job, _ = wait_for_job(client, submitted.json()["id"], worker)
        assert job["status"] == "succeeded" and job["model_version"] == 3, job

        # retraining starts from the calibration and says whether it beat the active version
        retrain = {"kind": "retrain", "params": {"shots": 5, "epochs": 20, "embed_dim": 32}}
        submitted = client.post("/v1/atlases/campus/jobs", json=retrain)
        job, _ = wait_for_job(client, submitted.json()["id"], worker)
    finally:
        log = stop_worker(worker)
    assert job["status"] == "succeeded", (job, log)
    held_out = job["metrics"]["held_out"]
    assert held_out["frames"] == FRAMES // 5  # four stretches of 5 frames, out of training
    assert job["metrics"]["activated"] == held_out["not_worse"]
    assert ("was not activated" in job["message"]) != held_out["not_worse"]
    versions = client.get("/v1/atlases/campus/models").json()
    assert [v["version"] for v in versions] == [1, 2, 3, 4]

    # rollback to the uncalibrated version: today's answer again
    assert client.post("/v1/atlases/campus/models/1/activate").status_code == 200
    wait_served(client, 1)
    restored = query(client, 10)
    assert restored["model_version"] == 1 and restored["match"]["score"] is None
    assert restored["verification"]["min_inliers"] == default_min_inliers(fitted["matcher"])
    assert restored["match"]["similarity"] == pytest.approx(
        uncalibrated["match"]["similarity"], abs=1e-5
    )
    assert client.get("/v1/atlases/campus").json()["calibration"]["state"] == "uncalibrated"


def test_job_parameters_of_the_other_kind_are_refused(client: TestClient) -> None:
    create_atlas(client)
    wrong = client.post("/v1/atlases/campus/jobs", json={"kind": "calibrate", "params": {}})
    assert wrong.status_code == 422
    few = client.post("/v1/atlases/campus/jobs", json={"kind": "calibrate"})
    assert few.status_code == 422 and "at least" in few.json()["detail"]
    assert frames_for_impostor_model() <= MIN_FRAMES  # what the job accepts, it can fit
    assert jobs(client) == []
