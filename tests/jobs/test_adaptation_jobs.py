"""Adaptation end to end: pairs ``observe`` verified, operator-labelled pairs (scoped by atlas
and role), an adapt job run by a real worker process, and jobs refused for want of pairs."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from service.api.app import create_app
from service.app.results import Candidate, QueryResult, SubmapGuess
from service.app.revisit_pairs import record_verified
from service.fleet.keys import Role, create_key
from service.jobs.adaptation import TRAINED_PAIRS, id_ranges, in_ranges
from service.jobs.retraining import JobRunner
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.feature_store import load_calibration_inputs
from tests.api.helpers import create_atlas
from tests.conftest import encode, make_settings, wait_ready
from tests.jobs.test_retraining_jobs import (
    cohog,
    start_worker,
    stop_worker,
    wait_for_job,
    worker_env,
)

PLACES = 12  # mapped by r1, then observed again by r2


def dusk(data: bytes) -> bytes:
    """The same view darker and a few pixels off: another condition that still verifies."""
    image = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float32)
    shifted = np.roll(image * 0.55, 3, axis=1).clip(0, 255).astype(np.uint8)
    return encode(shifted)


def map_and_revisit(client: TestClient) -> list[int]:
    """r1 maps ``PLACES`` places; r2 observes each again at dusk. Returns r1's frame ids."""
    create_atlas(client, submaps=("a", "b"))
    mapped = []
    for place in range(PLACES):
        name, data = cohog(place * 3, "ref")
        response = client.post(
            "/v1/atlases/campus/frames",
            data={"submap": "a" if place < PLACES // 2 else "b", "robot_id": "r1"},
            files={"image": (name, data)},
        )
        assert response.status_code == 201, response.text
        mapped.append(response.json()["frame_id"])
    for place in range(PLACES):
        name, data = cohog(place * 3, "ref")
        response = client.post(
            "/v1/atlases/campus/observe",
            data={"submap": "a" if place < PLACES // 2 else "b", "robot_id": "r2", "k": "3"},
            files={"image": ("dusk.png", dusk(data))},
        )
        assert response.status_code == 201, response.text
    return mapped


@pytest.mark.slow
def test_observed_pairs_train_an_adaptation_through_the_worker(
    app_client: TestClient, tmp_path: Path
) -> None:
    client = app_client
    mapped = map_and_revisit(client)
    pairs = client.get("/v1/atlases/campus/pairs", params={"limit": 100}).json()
    # every revisit was verified and kept as a pair with its match
    assert len(pairs) == PLACES
    assert {p["source"] for p in pairs} == {"observe"}
    assert {p["other_frame_id"] for p in pairs} == set(mapped)
    assert all(p["robot_id"] == "r2" and p["other_robot_id"] == "r1" for p in pairs)
    assert all(p["inliers"] is not None and p["inliers"] > 0 for p in pairs)
    assert len(client.get("/v1/atlases/campus/pairs", params={"robot": "r9"}).json()) == 0

    refused = client.post(
        "/v1/atlases/campus/jobs",
        json={"kind": "adapt", "adaptation": {"robots": ["r9"]}},
    )
    assert refused.status_code == 422
    assert refused.json()["detail"].startswith("refused: atlas 'campus' has 0 revisit pair(s)")

    submitted = client.post(
        "/v1/atlases/campus/jobs", json={"kind": "adapt", "adaptation": {"min_pairs": 5}}
    )
    assert submitted.status_code == 202, submitted.text
    worker = start_worker(worker_env(tmp_path / "data"))
    try:
        job, progress = wait_for_job(client, submitted.json()["id"], worker, timeout=600)
    finally:
        log = stop_worker(worker)
    assert job["status"] == "succeeded", (job["error"] or "")[-1500:] + log[-1500:]
    metrics = job["metrics"]
    assert (
        metrics["pairs"] == PLACES
        and metrics["training_pairs"] + metrics["held_out_pairs"] == PLACES
    )
    assert metrics["held_out"]["pairs"] == metrics["held_out_pairs"] > 0
    # the default method: the whitening, then the listwise loss (a trial run chose its length)
    assert metrics["pair_loss_steps_trial"] > 0 and "pair_loss_steps" in metrics
    assert "held-out pairs" in job["message"]
    assert job["message"].startswith("model version 2 ")
    assert progress == sorted(progress)
    versions = client.get("/v1/atlases/campus/models").json()
    assert [v["version"] for v in versions] == [1, 2]
    assert versions[1]["is_active"] == metrics["activated"]
    # the version records the pairs it learned from: a later job never judges it on them
    learned = in_ranges(
        np.array([p["id"] for p in pairs]), versions[1]["config"]["training"][TRAINED_PAIRS]
    )
    assert learned is not None and int(learned.sum()) == metrics["training_pairs"]


def test_a_calibration_takes_the_atlas_revisit_pairs_for_one_place(
    app_client: TestClient,
) -> None:
    """What a calibration (and an adaptation's refit impostor model) reads back: every pair
    observe kept, as positions of its two frames among the inputs, so r2's frames of a place
    r1 mapped are never sampled as that place's impostors."""
    map_and_revisit(app_client)
    service = app_client.app.state.runtime.service  # type: ignore[attr-defined]
    pairs = app_client.get("/v1/atlases/campus/pairs", params={"limit": 100}).json()
    with service.sessions() as session:
        atlas = repo.get_atlas(session, name="campus")
        inputs = load_calibration_inputs(session, atlas.id)
    ids = np.asarray(inputs.order)
    known = {(int(ids[a]), int(ids[b])) for a, b in inputs.same_place}
    assert known == {(p["frame_id"], p["other_frame_id"]) for p in pairs}
    assert len(known) == PLACES


def test_a_versions_training_pairs_are_kept_as_ranges_of_ids() -> None:
    ids = np.array([3, 5, 8, 9, 12])
    ranges = id_ranges(ids, np.array([4, 0, 3, 1]))
    assert ranges == [[3, 5], [9, 12]]
    assert in_ranges(ids, ranges).tolist() == [True, True, False, True, True]
    assert in_ranges(ids, None) is None and id_ranges(ids, np.zeros(0, int)) == []


def test_a_job_without_useful_pairs_is_refused_with_its_reason(app_client: TestClient) -> None:
    """Queued (e.g. automatically) and then left without pairs: the worker refuses it in one
    line and writes no model version."""
    client = app_client
    create_atlas(client, submaps=("a",))
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with transaction(service.sessions) as session:
        atlas_id = repo.get_atlas(session, name="campus").id
        job_id = jobs.create_job(session, atlas_id=atlas_id, kind="adapt", params={}).id
    JobRunner(service.settings, service.sessions).run(job_id)
    job = client.get(f"/v1/atlases/campus/jobs/{job_id}").json()
    assert job["status"] == "failed"
    assert job["message"] == (
        "refused: only 0 usable revisit pair(s) match the job's choice; adaptation needs at "
        "least 10 (closures observe kept: verified or its sequence's loops; or labelled pairs)"
    )
    assert [v["version"] for v in client.get("/v1/atlases/campus/models").json()] == [1]
    unknown = client.post(
        "/v1/atlases/campus/jobs", json={"kind": "adapt", "adaptation": {"method": "magic"}}
    )
    assert unknown.status_code == 422 and "whitening+pairs" in unknown.text


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_operator_labelled_pairs_scoped_by_atlas_and_role(app_client: TestClient) -> None:
    client = app_client
    for atlas in ("campus", "depot"):
        create_atlas(client, atlas=atlas, submaps=("a",))
    frames = {}
    for atlas in ("campus", "depot"):
        for place in (0, 1, 2):
            name, data = cohog(place, "ref")
            response = client.post(
                f"/v1/atlases/{atlas}/frames",
                data={"submap": "a", "robot_id": "r1"},
                files={"image": (name, data)},
            )
            frames.setdefault(atlas, []).append(response.json()["frame_id"])
    sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
    with transaction(sessions) as session:
        ops = create_key(session, name="ops", role=Role.operator, atlases=["campus"]).token
        robot = create_key(session, name="r1", role=Role.robot, atlases=["campus"]).token
    client.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
    a, b, c = frames["campus"]
    url = "/v1/atlases/campus/pairs"

    body = {"frame_id": a, "other_frame_id": b}
    assert client.post(url, json=body, headers=bearer(robot)).status_code == 403
    created = client.post(url, json=body, headers=bearer(ops))
    assert created.status_code == 201, created.text
    pair = created.json()
    assert (pair["frame_id"], pair["other_frame_id"], pair["source"]) == (a, b, "operator")
    assert pair["inliers"] is None and pair["submap"] == "a"
    # the same pair either way round: 409; a frame with itself: 422; another atlas's frame: 404
    again = {"frame_id": b, "other_frame_id": a}
    assert client.post(url, json=again, headers=bearer(ops)).status_code == 409
    itself = {"frame_id": a, "other_frame_id": a}
    assert client.post(url, json=itself, headers=bearer(ops)).status_code == 422
    foreign = {"frame_id": a, "other_frame_id": frames["depot"][0]}
    assert client.post(url, json=foreign, headers=bearer(ops)).status_code == 404
    # another atlas is out of the operator's scope
    depot = {"frame_id": frames["depot"][0], "other_frame_id": frames["depot"][1]}
    assert (
        client.post("/v1/atlases/depot/pairs", json=depot, headers=bearer(ops)).status_code == 403
    )
    assert client.get("/v1/atlases/depot/pairs", headers=bearer(ops)).status_code == 403

    client.post(url, json={"frame_id": b, "other_frame_id": c}, headers=bearer(ops))
    listed = client.get(url, headers=bearer(ops)).json()
    assert [p["frame_id"] for p in listed] == [b, a]  # newest first
    assert client.get(url, headers=bearer(robot)).status_code == 403

    delete = f"{url}/{pair['id']}"
    assert client.delete(delete, headers=bearer(robot)).status_code == 403
    assert client.delete(delete, headers=bearer(ops)).status_code == 204
    assert client.delete(delete, headers=bearer(ops)).status_code == 404
    assert [p["frame_id"] for p in client.get(url, headers=bearer(ops)).json()] == [b]
    # deleting a frame deletes its pairs
    assert client.delete(f"/v1/atlases/campus/frames/{c}", headers=bearer(ops)).status_code == 204
    assert client.get(url, headers=bearer(ops)).json() == []


def test_automatic_adaptation_after_n_new_pairs(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    """With ``adapt_after_pairs`` 2, no job is queued before the atlas has the 10 pairs a job
    needs; the tenth queues one; the eleventh none (a job is queued), but it counts towards the
    next, which the twelfth queues."""
    settings = make_settings(
        tmp_path / "data", calibration_milestones="", adapt_after_pairs=2, sync_seconds=0.2
    )
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client, submaps=("a",))
        ids = []
        for place in range(4):
            name, data = cohog(place, "ref")
            response = client.post(
                "/v1/atlases/campus/frames",
                data={"submap": "a", "robot_id": "r1"},
                files={"image": (name, data)},
            )
            ids.append(response.json()["frame_id"])
        service = client.app.state.runtime.service  # type: ignore[attr-defined]

        def verified(frame: int, match: int) -> None:
            result = QueryResult(
                atlas="campus",
                model_version=1,
                match=Candidate(match, "a", "r1", 0.9, inliers=80, verified=True),
                candidates=[],
                loop_closure=True,
                threshold=0.5,
                predicted_submap=SubmapGuess(available=False),
                keypoints=100,
            )
            assert record_verified(service.sessions, settings, result=result, frame_id=frame)

        def adapt_jobs() -> list[dict]:
            return [j for j in client.get("/v1/atlases/campus/jobs").json() if j["kind"] == "adapt"]

        ordered = [(a, b) for a in range(4) for b in range(4) if a != b]  # 12 distinct pairs
        for a, b in ordered[:9]:
            verified(ids[a], ids[b])
        assert adapt_jobs() == []  # 9 pairs: fewer than a job needs
        verified(*(ids[i] for i in ordered[9]))
        (job,) = adapt_jobs()
        assert job["status"] == "queued" and job["params"]["automatic"] is True
        assert job["params"]["through_pair"] == 10
        verified(*(ids[i] for i in ordered[10]))  # a job is queued: none more
        assert len(adapt_jobs()) == 1
        client.post(f"/v1/atlases/campus/jobs/{job['id']}/cancel")
        verified(*(ids[i] for i in ordered[11]))  # two pairs past the first job's
        latest = adapt_jobs()[0]
        assert len(adapt_jobs()) == 2 and latest["params"]["through_pair"] == 12
