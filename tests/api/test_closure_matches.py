"""A loop closure's verified matches, redrawn from the stored keypoints of both frames: only for
closures an observation recorded (a query stores no frame), and carried by snapshots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from service.fleet.snapshot_restore import restore_atlas
from service.fleet.snapshots import export_atlas
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night

INTRINSICS = json.dumps({"fx": 700.0, "fy": 700.0, "cx": 480.0, "cy": 270.0})


def observe(client: TestClient, image: bytes, robot: str, **fields: str) -> dict:
    response = client.post(
        "/v1/atlases/campus/observe",
        data={"submap": "s0", "robot_id": robot, **fields},
        files={"image": ("f.jpg", image)},
    )
    assert response.status_code == 201, response.text
    return response.json()


def closures(client: TestClient, atlas: str = "campus") -> list[dict]:
    response = client.get(f"/v1/atlases/{atlas}/loop-closures")
    assert response.status_code == 200, response.text
    return response.json()


def test_an_observed_closure_returns_its_inlier_point_pairs(client: TestClient) -> None:
    create_atlas(client)
    # robot r1 drives frames 0-2 of the day traverse, robot r2 comes by at frame 3, a few
    # metres on: an inter-robot closure onto r1's frame 2
    mapped = [
        add_frame(client, gardens_point_day_night(i, "query"), intrinsics=INTRINSICS)
        for i in range(3)
    ]
    seen = observe(client, gardens_point_day_night(3, "query"), "r2", intrinsics=INTRINSICS)
    assert seen["loop_closure"] is True and seen["match"]["frame_id"] == mapped[2]["frame_id"]
    (closure,) = closures(client)
    detail = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}").json()
    assert detail["query_frame_id"] == seen["frame_id"]

    response = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}/matches")
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["query_frame"]["frame_id"] == seen["frame_id"]
    assert body["frame"]["frame_id"] == mapped[2]["frame_id"]
    assert body["inliers"] >= seen["verification"]["min_inliers"]
    assert body["inliers"] <= body["matches"] and body["model"] == "essential"
    # recomputed from stored (half-precision) descriptors: close to what the observation found
    assert abs(body["inliers"] - seen["match"]["inliers"]) <= 0.1 * seen["match"]["inliers"]
    recorded = np.asarray(seen["match"]["relative_pose"]["rotation"])
    assert abs(float(np.dot(recorded, body["relative_pose"]["rotation"]))) > 0.999
    pairs = np.asarray(body["pairs"])
    assert pairs.shape == (body["inliers"], 4)
    for frame, columns in ((body["query_frame"], [0, 1]), (body["frame"], [2, 3])):
        assert (pairs[:, columns] >= 0).all()
        assert (pairs[:, columns[0]] < frame["width"]).all()
        assert (pairs[:, columns[1]] < frame["height"]).all()
    # each pair obeys the epipolar geometry of the pose, which only holds when the pairs index
    # the right keypoint in each frame
    assert np.median(_epipolar_px(pairs, body["relative_pose"])) < 3.0
    shuffled = np.c_[pairs[:, :2], np.roll(pairs[:, 2:], len(pairs) // 2, axis=0)]
    assert np.median(_epipolar_px(shuffled, body["relative_pose"])) > 10

    limited = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}/matches?limit=5")
    assert len(limited.json()["pairs"]) == 5 and limited.json()["inliers"] == body["inliers"]


def _epipolar_px(pairs: np.ndarray, pose: dict) -> np.ndarray:
    """Distance in pixels of each matched point to its epipolar line in the matched frame,
    under ``X_frame = R X_query + t``."""
    w, x, y, z = pose["rotation"]
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    tx, ty, tz = pose["translation"]
    essential = np.array([[0, -tz, ty], [tz, 0, -tx], [-ty, tx, 0]]) @ rotation
    k = np.array([[700.0, 0, 480.0], [0, 700.0, 270.0], [0, 0, 1]])
    fundamental = np.linalg.inv(k).T @ essential @ np.linalg.inv(k)
    a = np.c_[pairs[:, :2], np.ones(len(pairs))]
    b = np.c_[pairs[:, 2:], np.ones(len(pairs))]
    lines = a @ fundamental.T
    return np.abs(np.sum(b * lines, axis=1)) / np.linalg.norm(lines[:, :2], axis=1)


def test_a_query_closure_keeps_no_frame_so_its_matches_are_404(client: TestClient) -> None:
    create_atlas(client)
    add_frame(client, gardens_point_day_night(1, "ref"))
    response = client.post(
        "/v1/atlases/campus/query",
        data={"robot_id": "r2"},
        files={"image": ("q.jpg", gardens_point_day_night(1, "ref"))},
    )
    assert response.json()["loop_closure"] is True
    (closure,) = closures(client)
    assert closure["source"] == "query"
    detail = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}").json()
    assert detail["query_frame_id"] is None
    # a query makes its thumbnail only when a loop closes, and this one is kept
    assert detail["query_thumbnail"] is True
    thumbnail = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}/query-thumbnail")
    assert thumbnail.status_code == 200 and thumbnail.content[:2] == b"\xff\xd8"
    missing = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}/matches")
    assert missing.status_code == 404
    assert "only kept for observed frames" in missing.json()["detail"]
    unknown = client.get(f"/v1/atlases/campus/loop-closures/{closure['id'] + 1}/matches")
    assert unknown.status_code == 404 and "does not exist" in unknown.json()["detail"]


def test_deleting_the_observed_frame_keeps_the_closure_without_matches(
    client: TestClient,
) -> None:
    create_atlas(client)
    add_frame(client, gardens_point_day_night(3, "ref"))
    seen = observe(client, gardens_point_day_night(3, "ref"), "r2")
    (closure,) = closures(client)
    deleted = client.delete(f"/v1/atlases/campus/frames/{seen['frame_id']}")
    assert deleted.status_code == 204
    detail = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}").json()
    assert detail["query_frame_id"] is None
    gone = client.get(f"/v1/atlases/campus/loop-closures/{closure['id']}/matches")
    assert gone.status_code == 404 and "no longer stored" in gone.json()["detail"]


def test_snapshots_carry_the_observed_frame_of_a_closure(
    client: TestClient, tmp_path: Path
) -> None:
    create_atlas(client)
    add_frame(client, gardens_point_day_night(5, "ref"))
    observe(client, gardens_point_day_night(5, "ref"), "r2")
    before = client.get(f"/v1/atlases/campus/loop-closures/{closures(client)[0]['id']}/matches")
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    archive = tmp_path / "campus.tar"
    export_atlas(service.settings, service.sessions, "campus", archive)
    restore_atlas(service.settings, service.sessions, archive, name="copy")
    (copied,) = closures(client, "copy")
    after = client.get(f"/v1/atlases/copy/loop-closures/{copied['id']}/matches")
    assert after.status_code == 200, after.text
    robots = {f["frame_id"]: f["robot_id"] for f in client.get("/v1/atlases/copy/frames").json()}
    assert robots[after.json()["query_frame"]["frame_id"]] == "r2"
    assert after.json()["pairs"] == before.json()["pairs"]
