"""The worker's job runner in-process: failures and cancellations leave the active version."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from fastapi.testclient import TestClient

from service.jobs.retraining import JobRunner
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night


def atlas_with_two_submaps(client: TestClient) -> None:
    create_atlas(client, submaps=("a", "b"))
    for i in range(4):
        add_frame(client, gardens_point_day_night(i, "ref"), submap="a" if i < 2 else "b")


def submit(client: TestClient, params: dict) -> tuple[JobRunner, int]:
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with transaction(service.sessions) as session:
        atlas = repo.get_atlas(session, name="campus")
        job_id = jobs.create_job(session, atlas_id=atlas.id, kind="retrain", params=params).id
    return JobRunner(service.settings, service.sessions), job_id


def state(client: TestClient, job_id: int) -> tuple[str, str | None, list[tuple[int, bool]]]:
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:
        job = jobs.get_job(session, job_id=job_id)
        versions = [
            (v.version, v.is_active)
            for v in repo.list_model_versions(session, atlas_id=job.atlas_id)
        ]
        return job.status, job.error, versions


def model_files(settings_dir: Path) -> list[Path]:
    return sorted(
        p
        for p in settings_dir.rglob("*")
        if p.suffix in (".pt", ".faiss") and "atlas-1-v1" not in p.name
    )


def test_failed_job_leaves_the_active_version(client: TestClient, settings) -> None:  # type: ignore[no-untyped-def]
    atlas_with_two_submaps(client)
    runner, job_id = submit(client, {"shots": 0})  # rejected by the training config
    runner.run(job_id)
    status, error, versions = state(client, job_id)
    assert status == "failed" and "shots" in (error or "")
    assert versions == [(1, True)]
    assert model_files(settings.data_dir) == []


def test_cancelling_a_running_job(client: TestClient, settings, caplog) -> None:  # type: ignore[no-untyped-def]
    caplog.set_level(logging.INFO, logger="service.jobs.retraining")
    atlas_with_two_submaps(client)
    runner, job_id = submit(client, {"epochs": 2000, "patience": 1000, "embed_dim": 8})  # the most
    thread = threading.Thread(target=runner.run, args=(job_id,))
    thread.start()
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    deadline = time.monotonic() + 60
    while state(client, job_id)[0] != "running":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    response = client.post(f"/v1/atlases/campus/jobs/{job_id}/cancel")
    assert response.status_code == 200 and response.json()["cancel_requested"]
    thread.join(timeout=60)
    status, _, versions = state(client, job_id)
    assert status == "cancelled" and versions == [(1, True)]
    assert model_files(settings.data_dir) == []
    assert f"job {job_id} (atlas 'campus'): cancelled" in caplog.text
    again = client.post(f"/v1/atlases/campus/jobs/{job_id}/cancel")
    assert again.status_code == 409 and "already cancelled" in again.json()["detail"]
    del service


def test_job_api_validation(client: TestClient) -> None:
    create_atlas(client, submaps=("a", "b"))
    add_frame(client, gardens_point_day_night(0, "ref"), submap="a")
    one_submap = client.post("/v1/atlases/campus/jobs", json={"kind": "retrain"})
    assert one_submap.status_code == 422 and "at least two submaps" in one_submap.json()["detail"]
    for body, needle in (
        ({"kind": "retrain", "params": {"shots": 0}}, "shots"),
        ({"kind": "retrain", "params": {"train": ["backbone"]}}, "train"),
        (
            {"kind": "retrain", "params": {"classification_weight": 0, "contrastive_weight": 0}},
            "loss weight",
        ),
        ({"kind": "retrain", "params": {"unknown": 1}}, "unknown"),
        ({"kind": "reindex"}, "kind"),
    ):
        response = client.post("/v1/atlases/campus/jobs", json=body)
        assert response.status_code == 422 and needle in response.text, (body, response.text)
    assert client.get("/v1/atlases/campus/jobs").json() == []
    assert client.get("/v1/atlases/campus/jobs/99").status_code == 404
    assert client.post("/v1/atlases/campus/models/7/activate").status_code == 404
    assert client.post("/v1/atlases/nowhere/jobs", json={"kind": "retrain"}).status_code == 404


def test_the_worker_logs_a_job_cancelled_before_it_ran_as_not_run(
    client: TestClient, settings, caplog
) -> None:  # type: ignore[no-untyped-def]
    from service.runtime.queue import Queue

    caplog.set_level(logging.INFO)
    atlas_with_two_submaps(client)
    _, job_id = submit(client, {"embed_dim": 8})
    assert client.post(f"/v1/atlases/campus/jobs/{job_id}/cancel").status_code == 200
    queue = Queue(settings)
    queue.huey.immediate = True  # Huey runs the task in this process, logging as the worker does
    queue.enqueue(job_id)
    assert state(client, job_id)[0] == "cancelled"
    assert f"job {job_id}: not run, it is cancelled" in caplog.text
    assert "executed" not in caplog.text
