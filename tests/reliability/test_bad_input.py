"""Bad input through the HTTP API: the 500s fuzzing found, now clear 4xx that write nothing,
and a property test of ingest over every kind of upload."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings

from tests.api.helpers import create_atlas, stored_state
from tests.conftest import make_settings, wait_ready
from tests.reliability.uploads import encode_image, image_uploads, pixel_bomb

HUGE = 2**70


@pytest.fixture(scope="module")
def small_limits_client(tmp_path_factory, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """One app for the module (hypothesis runs many examples against it), small limits."""
    from service.api.app import create_app

    settings_ = make_settings(
        tmp_path_factory.mktemp("bad"), max_upload_bytes=200_000, max_image_pixels=1_000_000
    )
    with TestClient(create_app(settings_, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client)
        yield client


def post_frame(client: TestClient, image: bytes, content_type: str = "image/png"):  # type: ignore[no-untyped-def]
    return client.post(
        "/v1/atlases/campus/frames",
        data={"submap": "s0", "robot_id": "r1"},
        files={"image": ("f", image, content_type)},
    )


@pytest.mark.parametrize(
    "path",
    [
        f"/v1/atlases/campus/frames/{HUGE}",
        f"/v1/atlases/campus/jobs/{HUGE}",
        "/v1/atlases/campus/frames/0",
        "/v1/atlases/campus/frames/-3",
    ],
)
def test_ids_beyond_bigint_or_below_one_are_422_not_500(
    small_limits_client: TestClient, path: str
) -> None:
    response = small_limits_client.get(path)
    assert response.status_code == 422, response.text
    assert "frame_id" in response.text or "job_id" in response.text


@pytest.mark.parametrize("method_path", ["POST /models/{id}/activate", "POST /jobs/{id}/cancel"])
def test_huge_ids_in_writes_are_422_and_write_nothing(
    small_limits_client: TestClient, method_path: str
) -> None:
    before = stored_state(small_limits_client)
    method, path = method_path.split()
    url = "/v1/atlases/campus" + path.format(id=HUGE)
    assert small_limits_client.request(method, url).status_code == 422
    assert stored_state(small_limits_client) == before


@pytest.mark.parametrize(
    ("fmt", "cut"),
    [("PNG", 16), ("JPEG", 6), ("WEBP", 16)],  # the header itself is cut short
)
def test_image_with_a_truncated_header_is_422(
    small_limits_client: TestClient, fmt: str, cut: int
) -> None:
    before = stored_state(small_limits_client)
    response = post_frame(small_limits_client, encode_image(8, 8, "RGB", fmt, 0)[:cut])
    assert response.status_code == 422, response.text
    assert response.json()["error"] == "InvalidImage"
    assert stored_state(small_limits_client) == before


def test_pixel_bomb_is_413_before_decoding(small_limits_client: TestClient) -> None:
    bomb = pixel_bomb(4000, 4000)  # 16 Mpx, a few kB
    before = stored_state(small_limits_client)
    response = post_frame(small_limits_client, bomb)
    assert response.status_code == 413 and "pixels" in response.json()["detail"]
    assert stored_state(small_limits_client) == before


def test_wrong_content_type_and_json_body_are_4xx(small_limits_client: TestClient) -> None:
    before = stored_state(small_limits_client)
    as_json = small_limits_client.post(
        "/v1/atlases/campus/frames", json={"submap": "s0", "robot_id": "r1", "image": "abc"}
    )
    assert as_json.status_code == 422
    raw = small_limits_client.post(
        "/v1/atlases/campus/query", content=b"\x89PNG", headers={"content-type": "image/png"}
    )
    assert raw.status_code == 422
    text_file = post_frame(small_limits_client, b"hello, robot", "text/plain")
    assert text_file.status_code == 422 and text_file.json()["error"] == "InvalidImage"
    assert stored_state(small_limits_client) == before


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(image_uploads())
def test_ingest_of_any_upload_is_201_or_a_4xx_that_writes_nothing(
    small_limits_client: TestClient, image: bytes
) -> None:
    before = stored_state(small_limits_client)
    response = post_frame(small_limits_client, image)
    if response.status_code == 201:
        after = stored_state(small_limits_client)
        assert after["frames"] == before["frames"] + 1
        assert after["features"] == before["features"] + 1
        assert after["indexed"] == before["indexed"] + 1
    else:
        assert response.status_code in (413, 422), response.text
        assert response.json()["detail"]
        assert stored_state(small_limits_client) == before
