"""Online SLAM use: observe (query then insert), the robot's own recent frames excluded, query
filters by robot, submap and time, the margin, verification fields and bad filter values."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.api.helpers import add_frame, create_atlas, stored_state
from tests.conftest import gardens_point_day_night

NO_EXCLUSION = {"exclude_recent_frames": "0", "exclude_recent_seconds": "0"}


def observe(client: TestClient, image: bytes, atlas: str = "campus", **fields: str):  # type: ignore[no-untyped-def]
    data = {"submap": "s0", "robot_id": "r1", **fields}
    return client.post(f"/v1/atlases/{atlas}/observe", data=data, files={"image": ("f.jpg", image)})


def query(client: TestClient, image: bytes, **fields: str):  # type: ignore[no-untyped-def]
    return client.post("/v1/atlases/campus/query", data=fields, files={"image": ("q.jpg", image)})


def test_observe_queries_then_inserts_and_never_matches_itself(client: TestClient) -> None:
    create_atlas(client)
    image = gardens_point_day_night(4, "ref")
    first = observe(client, image, timestamp="10")
    assert first.status_code == 201, first.text
    body = first.json()
    assert body["match"] is None and body["loop_closure"] is False  # empty before the insert
    frame = client.get(f"/v1/atlases/campus/frames/{body['frame_id']}").json()
    assert frame["robot_id"] == "r1" and frame["timestamp"] == 10

    # the same view again, by the same robot: its own recent frame is excluded by default
    again = observe(client, image, timestamp="11").json()
    assert again["match"] is None and again["loop_closure"] is False
    assert again["frame_id"] != body["frame_id"]

    # ... but a revisit once exclusion is off, verified by many inliers
    revisit = observe(client, image, timestamp="12", **NO_EXCLUSION).json()
    assert revisit["match"]["frame_id"] in {body["frame_id"], again["frame_id"]}
    assert revisit["match"]["verified"] is True
    assert revisit["match"]["inliers"] >= revisit["verification"]["min_inliers"]
    assert revisit["loop_closure"] is True
    assert revisit["frame_id"] not in {c["frame_id"] for c in revisit["candidates"]}


def test_another_robots_frames_are_not_excluded(client: TestClient) -> None:
    create_atlas(client)
    image = gardens_point_day_night(4, "ref")
    mine = observe(client, image).json()
    other = observe(client, image, robot_id="r2").json()
    assert other["match"]["frame_id"] == mine["frame_id"]
    assert other["match"]["robot_id"] == "r1" and other["loop_closure"] is True


def test_recent_frames_by_count_and_by_seconds(client: TestClient) -> None:
    create_atlas(client)
    ids = [
        add_frame(client, gardens_point_day_night(i, "ref"), timestamp=str(t))["frame_id"]
        for i, t in [(0, 0.0), (1, 100.0), (2, 110.0)]
    ]
    image = gardens_point_day_night(1, "ref")

    def seen(**fields: str) -> set[int]:
        body = query(client, image, k="5", robot_id="r1", **fields).json()
        return {c["frame_id"] for c in body["candidates"]}

    assert seen(**NO_EXCLUSION) == set(ids)
    assert seen(exclude_recent_frames="1", exclude_recent_seconds="0") == set(ids[:2])
    # T seconds before the robot's latest frame (110): 100 and 110 go, 0 stays
    assert seen(exclude_recent_frames="0", exclude_recent_seconds="30") == {ids[0]}
    # or before the query's own timestamp
    assert seen(exclude_recent_frames="0", exclude_recent_seconds="5", timestamp="104") == {ids[0]}
    # an anonymous query excludes nothing
    anonymous = query(client, image, k="5").json()
    assert {c["frame_id"] for c in anonymous["candidates"]} == set(ids)


def test_submap_and_time_filters(client: TestClient) -> None:
    create_atlas(client, submaps=("a", "b"))
    frames = [
        add_frame(
            client,
            gardens_point_day_night(i, "ref"),
            submap="a" if i < 2 else "b",
            timestamp=str(i),
        )
        for i in range(4)
    ]
    untimed = add_frame(client, gardens_point_day_night(4, "ref"), submap="b")
    image = gardens_point_day_night(0, "ref")
    in_b = query(client, image, k="10", submap="b").json()["candidates"]
    assert {c["frame_id"] for c in in_b} == {
        frames[2]["frame_id"],
        frames[3]["frame_id"],
        untimed["frame_id"],
    }
    window = query(client, image, k="10", since="1", until="2").json()["candidates"]
    assert {c["frame_id"] for c in window} == {frames[1]["frame_id"], frames[2]["frame_id"]}
    both = query(client, image, k="10", submap="b", since="3").json()["candidates"]
    assert [c["frame_id"] for c in both] == [frames[3]["frame_id"]]


def test_margin_between_best_place_and_the_next(client: TestClient) -> None:
    create_atlas(client, submaps=("a", "b"))
    add_frame(client, gardens_point_day_night(0, "ref"), submap="a")
    add_frame(client, gardens_point_day_night(1, "ref"), submap="a")
    body = query(client, gardens_point_day_night(1, "ref")).json()
    assert body["margin"] is None  # one place only
    add_frame(client, gardens_point_day_night(8, "ref"), submap="b")
    body = query(client, gardens_point_day_night(1, "ref"), k="1").json()
    other = query(client, gardens_point_day_night(1, "ref"), k="5", submap="b").json()
    expected = body["match"]["similarity"] - other["match"]["similarity"]
    assert body["match"]["submap"] == "a"
    assert body["margin"] == pytest.approx(expected, abs=1e-5) and body["margin"] > 0


def test_candidates_carry_verification_and_pose_with_intrinsics(client: TestClient) -> None:
    create_atlas(client)
    intrinsics = json.dumps({"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 180.0})
    add_frame(client, gardens_point_day_night(5, "ref"), intrinsics=intrinsics)
    add_frame(client, gardens_point_day_night(9, "ref"))
    image = gardens_point_day_night(5, "ref")
    body = query(client, image, intrinsics=intrinsics).json()
    best = body["match"]
    assert best["verified"] and 0 < best["inlier_ratio"] <= 1
    pose = best["relative_pose"]
    assert pose is not None
    assert np.linalg.norm(pose["rotation"]) == pytest.approx(1.0, abs=1e-6)
    assert np.linalg.norm(pose["translation"]) == pytest.approx(1.0, abs=1e-6)
    without = [c for c in body["candidates"] if c["frame_id"] != best["frame_id"]]
    assert all(c["relative_pose"] is None for c in without)  # that frame has no intrinsics
    plain = query(client, image).json()  # no query intrinsics: fundamental matrix, no pose
    assert plain["match"]["verified"] and plain["match"]["relative_pose"] is None
    assert "verification" in body["timings_ms"]


@pytest.mark.parametrize(
    ("fields", "status", "message"),
    [
        ({"robots": "own"}, 422, "needs robot_id"),
        ({"robots": "others"}, 422, "needs robot_id"),
        ({"robots": "mine", "robot_id": "r1"}, 422, "robots must be one of"),
        ({"since": "5", "until": "1"}, 422, "is after until"),
        ({"since": "nan"}, 422, "finite"),
        ({"exclude_recent_frames": "-1", "robot_id": "r1"}, 422, "0 or more"),
        ({"exclude_recent_seconds": "-2"}, 422, "0 or more"),
        ({"robot_id": "bad robot"}, 422, "robot name"),
        ({"submap": "nowhere"}, 404, "submap 'nowhere' does not exist"),
    ],
)
def test_bad_filters(client: TestClient, fields: dict, status: int, message: str) -> None:
    create_atlas(client)
    add_frame(client, gardens_point_day_night(0, "ref"))
    response = query(client, gardens_point_day_night(0, "ref"), **fields)
    assert response.status_code == status and message in response.text, response.text


def test_failed_observation_writes_nothing(client: TestClient) -> None:
    create_atlas(client)
    add_frame(client, gardens_point_day_night(0, "ref"))
    before = stored_state(client)
    image = gardens_point_day_night(0, "ref")
    assert observe(client, image, submap="nowhere").status_code == 404
    assert observe(client, image, robot_id="bad robot").status_code == 422
    assert observe(client, image, robots="sideways").status_code == 422
    assert (
        observe(
            client, image, pose='{"rotation": [2, 0, 0, 0], "translation": [0, 0, 0]}'
        ).status_code
        == 422
    )
    assert observe(client, b"not an image").status_code == 422
    assert stored_state(client) == before
