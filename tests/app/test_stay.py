"""A robot's current stay: a robot standing still does not close a loop with itself; one that
left and came back does."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.app.stay import BREAK, current_stay
from service.evaluation.served_pass import run_job_now
from tests.api.helpers import create_atlas
from tests.conftest import make_settings, wait_ready
from tests.jobs.test_retraining_jobs import cohog

# ----- the walk, on vectors whose likeness to the query is known -----------------------------


def walk(alike: list[bool], first_block: int | None = None) -> list[int]:
    """The stay over a robot whose frames newest first are ids 100, 99, ... and resemble the
    query as ``alike`` says (cosine 1 or 0 against the query)."""
    ids = np.arange(100, 100 - len(alike), -1, dtype=np.int64)
    cosine = dict(zip(ids.tolist(), alike, strict=True))

    def own_frames(offset: int, limit: int) -> np.ndarray:
        return ids[offset : offset + limit]

    def vectors(frame_ids: np.ndarray) -> np.ndarray:
        return np.array([[1.0, 0.0] if cosine[i] else [0.0, 1.0] for i in frame_ids.tolist()])

    stay = current_stay(
        own_frames=own_frames,
        query=np.array([1.0, 0.0], np.float32),
        vectors=vectors,
        resembles=lambda similarities: similarities > 0.5,
    )
    return stay.tolist()


def test_a_stay_ends_where_the_robot_was_elsewhere() -> None:
    assert walk([True, True, True, False, False, True, True]) == [100, 99, 98]
    assert walk([False, False, True]) == []  # the robot has just arrived: no stay
    assert walk([]) == []


def test_one_odd_frame_does_not_end_a_stay() -> None:
    """A person passing in front of the camera: one unlike frame between alike ones belongs to
    the stay; it takes BREAK unlike frames in a row to end it, and none is kept at its end."""
    assert BREAK == 2
    assert walk([True, False, True, True, False, False, True]) == [100, 99, 98, 97]
    assert walk([True, True, False]) == [100, 99]


def test_a_long_stay_is_read_across_blocks() -> None:
    """A robot parked for 300 frames: read in blocks (32, 64, ...) until the robot was
    elsewhere."""
    alike = [True] * 300 + [False, False] + [True] * 10
    assert walk(alike) == list(range(100, 100 - 300, -1))


# ----- the service: a calibrated atlas, a robot that stops, leaves and comes back -----------


@pytest.fixture
def calibrated(tmp_path: Path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """16 places of Gardens Point (every tenth, reference panels) mapped by robot r0, and the atlas calibrated at its
    first milestone (the job run in this process with the worker's code)."""
    settings = make_settings(
        tmp_path / "data",
        calibration_milestones="16, 100000",
        exclude_recent_frames=2,
        exclude_recent_seconds=0.0,
    )
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client, "campus", ("day", "walk"))
        for place in range(16):
            name, data = cohog(place * 10, "ref")
            response = client.post(
                "/v1/atlases/campus/frames",
                data={"submap": "day", "robot_id": "r0"},
                files={"image": (name, data)},
            )
            assert response.status_code == 201, response.text
        [job] = client.get("/v1/atlases/campus/jobs").json()
        service = client.app.state.runtime.service  # type: ignore[attr-defined]
        assert run_job_now(service, job["id"]).status == "succeeded"
        yield client


def observe(client: TestClient, place: int) -> dict:
    """Robot r1 observes Gardens Point place ``place`` (the query panel: the other side of the
    walkway from r0's reference panels)."""
    name, data = cohog(place, "query")
    response = client.post(
        "/v1/atlases/campus/observe",
        data={"submap": "walk", "robot_id": "r1"},
        files={"image": (name, data)},
    )
    assert response.status_code == 201, response.text
    return response.json()


def test_a_robot_standing_still_does_not_close_a_loop_with_itself(
    calibrated: TestClient,
) -> None:
    """r1 stands at place 155 for 6 frames (2 are its recent-frame exclusion): its earlier
    frames there are its current stay, never a candidate. It then drives through two other
    places and comes back: its first frames at 155 are a revisit, and match."""
    answers = [observe(calibrated, 155) for _ in range(6)]
    first_frames = {a["frame_id"] for a in answers}
    assert answers[-1]["model_version"] == 2  # calibrated: the stay has its bar
    for answer in answers[3:]:
        assert answer["stay_frames"] >= 3
        assert not first_frames & {c["frame_id"] for c in answer["candidates"]}
        assert answer["status"] != "loop" or answer["match"]["robot_id"] != "r1"

    for place in (5, 75, 35):  # elsewhere: the stay at 155 is over
        observe(calibrated, place)
    back = observe(calibrated, 155)
    assert back["stay_frames"] == 0
    assert back["match"]["frame_id"] in first_frames  # its own earlier frames may match now
