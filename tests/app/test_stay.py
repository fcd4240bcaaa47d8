"""A robot's current stay: a robot standing still does not close a loop with itself; one that
left and came back does."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.evaluation.served_jobs import run_job_now
from service.ml.stays import BREAK, FADE, current_stay
from tests.api.helpers import create_atlas
from tests.conftest import make_settings, wait_ready
from tests.jobs.test_retraining_jobs import cohog

# ----- the walk, on vectors whose likeness to the query is known -----------------------------


ALIKE, BETWEEN, ELSEWHERE = 3.0, 1.5, 0.0  # scores: the place, neither, another place


def walk(scores: list[float]) -> list[int]:
    """The stay over a robot whose frames newest first are ids 1000, 999, ... and score
    ``scores`` against the query (loop_score_min 2, another place below 1)."""
    ids = np.arange(1000, 1000 - len(scores), -1, dtype=np.int64)

    def own_frames(offset: int, limit: int) -> np.ndarray:
        return ids[offset : offset + limit]

    def vectors(frame_ids: np.ndarray) -> np.ndarray:  # the query is (1, 0): cosine = score
        return np.array([[scores[1000 - i], 0.0] for i in frame_ids.tolist()])

    stay = current_stay(
        own_frames=own_frames,
        query=np.array([1.0, 0.0], np.float32),
        vectors=vectors,
        scores=lambda similarities: similarities,
        alike=2.0,
        elsewhere=1.0,
    )
    return stay.tolist()


def test_a_stay_ends_where_the_robot_was_elsewhere() -> None:
    assert walk([ALIKE, ALIKE, ALIKE, ELSEWHERE, ELSEWHERE, ALIKE]) == [1000, 999, 998]
    assert walk([ELSEWHERE, ELSEWHERE, ALIKE]) == []  # the robot has just arrived: no stay
    assert walk([]) == []


def test_one_odd_frame_does_not_end_a_stay() -> None:
    """A person passing in front of the camera: one frame of "another place" between frames of
    the place belongs to the stay; it takes BREAK in a row to end it, and the stay ends at the
    oldest frame that showed the place."""
    assert BREAK == 2
    assert walk([ALIKE, ELSEWHERE, ALIKE, ALIKE, ELSEWHERE, ELSEWHERE, ALIKE]) == [
        1000,
        999,
        998,
        997,
    ]
    assert walk([ALIKE, ALIKE, ELSEWHERE]) == [1000, 999]


def test_frames_in_between_neither_extend_nor_end_a_stay_until_it_fades() -> None:
    """Hysteresis: frames scoring between "another place" and "the place" (light changes, a
    slow creep) carry the stay to an older frame of the place; FADE of them in a row end it."""
    assert walk([ALIKE, BETWEEN, BETWEEN, ALIKE, BETWEEN, ELSEWHERE, ELSEWHERE]) == [
        1000,
        999,
        998,
        997,
    ]
    assert walk([ALIKE] + [BETWEEN] * (FADE - 1) + [ALIKE]) == list(
        range(1000, 1000 - FADE - 1, -1)
    )
    assert walk([ALIKE] + [BETWEEN] * FADE + [ALIKE]) == [1000]
    assert walk([float("nan"), float("nan"), ALIKE]) == []  # not held yet: another place


def test_a_long_stay_is_read_across_blocks() -> None:
    """A robot parked for 300 frames: read in blocks (32, 64, ...) until the robot was
    elsewhere."""
    scores = [ALIKE] * 300 + [ELSEWHERE, ELSEWHERE] + [ALIKE] * 10
    assert walk(scores) == list(range(1000, 1000 - 300, -1))


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


def test_a_sequence_never_aligns_with_the_stays_of_its_frames(calibrated: TestClient) -> None:
    """r1 stands at place 155 for 6 frames, then moves on to place 5: the newest frame has no
    stay, but its sequence's earlier frames do, and none of them aligns with r1's own frames
    of that stop (the same visit, not a loop)."""
    stop = {observe(calibrated, 155)["frame_id"] for _ in range(6)}
    moved = observe(calibrated, 5)
    assert moved["stay_frames"] == 0
    sequence = moved["sequence"]
    assert sequence is not None and sequence["length"] > 1
    assert not stop & {frame for frame in sequence["aligned"] if frame is not None}
    assert moved["status"] != "loop" or moved["loop_frame_id"] not in stop
