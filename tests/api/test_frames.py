"""Adding frames, and every rejected upload leaving nothing written."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.api.helpers import add_frame, create_atlas, stored_state
from tests.conftest import encode


def test_add_and_get_frame_with_metadata(client: TestClient, day_image: bytes) -> None:
    create_atlas(client)
    pose = {"rotation": [0.0, 1.0, 0.0, 0.0], "translation": [1.5, -2.0, 0.25]}
    intrinsics = {"fx": 700.0, "fy": 705.0, "cx": 480.0, "cy": 270.0}
    frame = add_frame(
        client,
        day_image,
        robot="husky-2",
        timestamp="1700000000.25",
        pose=json.dumps(pose),
        intrinsics=json.dumps(intrinsics),
    )
    assert frame["width"] == 960 and frame["height"] == 540 and frame["keypoints"] > 0
    fetched = client.get(f"/v1/atlases/campus/frames/{frame['frame_id']}").json()
    assert fetched["robot_id"] == "husky-2" and fetched["timestamp"] == 1700000000.25
    assert fetched["pose"] == pose and fetched["intrinsics"] == intrinsics
    assert fetched["submap"] == "s0" and fetched["created_at"].endswith("Z")
    assert stored_state(client) == {"frames": 1, "features": 1, "submaps": 1, "indexed": 1}


def test_unknown_frame_and_frame_of_another_atlas(client: TestClient, day_image: bytes) -> None:
    create_atlas(client, "a")
    create_atlas(client, "b")
    frame = add_frame(client, day_image, atlas="a")
    assert client.get("/v1/atlases/a/frames/999").status_code == 404
    assert client.get(f"/v1/atlases/b/frames/{frame['frame_id']}").status_code == 404


BAD_UPLOADS = {
    "empty file": (b"", {}, 422, "empty"),
    "not an image": (b"GIF89a-but-not-really", {}, 422, "not a JPEG, PNG or WebP"),
    "truncated": (None, {}, 422, "truncated"),
    "unknown submap": (None, {"submap": "nope"}, 404, "submap 'nope' does not exist"),
    "bad robot id": (None, {"robot_id": "a robot with spaces"}, 422, "robot name"),
    "pose not json": (None, {"pose": "{rotation"}, 422, "not valid JSON"),
    "pose wrong shape": (
        None,
        {"pose": '{"rotation": [1, 0], "translation": [0, 0, 0]}'},
        422,
        "quaternion",
    ),
    "pose not unit": (
        None,
        {"pose": '{"rotation": [2, 0, 0, 0], "translation": [0, 0, 0]}'},
        422,
        "unit quaternion",
    ),
    "intrinsics missing fy": (None, {"intrinsics": '{"fx": 1, "cx": 0, "cy": 0}'}, 422, "fy"),
    "negative focal": (
        None,
        {"intrinsics": '{"fx": -1, "fy": 1, "cx": 0, "cy": 0}'},
        422,
        "positive",
    ),
    "timestamp not a number": (None, {"timestamp": "yesterday"}, 422, "timestamp"),
}


@pytest.mark.parametrize("case", sorted(BAD_UPLOADS))
def test_rejected_upload_writes_nothing(client: TestClient, day_image: bytes, case: str) -> None:
    create_atlas(client)
    add_frame(client, day_image)
    before = stored_state(client)
    image, fields, status, message = BAD_UPLOADS[case]
    if image is None:
        image = day_image[: len(day_image) // 3] if case == "truncated" else day_image
    data = {"submap": "s0", "robot_id": "r1", **fields}
    response = client.post(
        "/v1/atlases/campus/frames", data=data, files={"image": ("f.jpg", image)}
    )
    assert response.status_code == status, response.text
    assert message in json.dumps(response.json())
    assert stored_state(client) == before


def test_missing_fields_are_422(client: TestClient, day_image: bytes) -> None:
    create_atlas(client)
    no_image = client.post("/v1/atlases/campus/frames", data={"submap": "s0", "robot_id": "r"})
    assert no_image.status_code == 422 and "image" in no_image.text
    no_submap = client.post(
        "/v1/atlases/campus/frames", data={"robot_id": "r"}, files={"image": ("f.jpg", day_image)}
    )
    assert no_submap.status_code == 422 and "submap" in no_submap.text
    assert stored_state(client)["frames"] == 0


def test_upload_limits_give_413(tmp_path, pipeline) -> None:  # type: ignore[no-untyped-def]
    from service.api.app import create_app
    from tests.conftest import make_settings, wait_ready

    settings = make_settings(tmp_path, max_upload_bytes=50_000, max_image_pixels=100_000)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client)
        noise = np.random.default_rng(0).integers(0, 255, (200, 200, 3), dtype=np.uint8)
        too_many_bytes = encode(noise, "PNG")
        assert len(too_many_bytes) > 50_000
        too_many_pixels = encode(np.zeros((400, 400, 3), np.uint8), "PNG")
        for image, message in ((too_many_bytes, "50000 bytes"), (too_many_pixels, "pixels")):
            response = client.post(
                "/v1/atlases/campus/frames",
                data={"submap": "s0", "robot_id": "r1"},
                files={"image": ("f.png", image)},
            )
            assert response.status_code == 413 and message in response.json()["detail"]
        assert stored_state(client)["frames"] == 0
