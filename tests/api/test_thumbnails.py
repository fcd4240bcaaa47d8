"""Thumbnails: made at ingest from the decoded frame, served per frame, carried by snapshots."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy import delete, func, select

from service.fleet.snapshot_restore import restore_atlas
from service.fleet.snapshots import export_atlas
from service.ml.thumbnails import LONG_SIDE
from service.storage.models import FrameThumbnail
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night


def thumbnail(client: TestClient, atlas: str, frame_id: int) -> tuple[Image.Image, dict]:
    response = client.get(f"/v1/atlases/{atlas}/frames/{frame_id}/thumbnail")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/jpeg"
    return Image.open(io.BytesIO(response.content)), dict(response.headers)


def test_ingest_stores_a_small_jpeg_of_the_frame(client: TestClient) -> None:
    create_atlas(client)
    original = gardens_point_day_night(2, "ref")
    frame = add_frame(client, original)
    image, headers = thumbnail(client, "campus", frame["frame_id"])
    assert max(image.size) == LONG_SIDE
    width, height = Image.open(io.BytesIO(original)).size
    assert abs(image.size[0] / image.size[1] - width / height) < 0.02  # aspect ratio kept
    assert 1_000 < int(headers["content-length"]) < 20_000
    assert "x-thumbnail" not in headers
    # it shows the frame: its mean colour is the original's, within JPEG and resampling error
    small = Image.open(io.BytesIO(original)).convert("RGB").resize(image.size)
    assert abs(_mean(image) - _mean(small)) < 3.0


def _mean(image: Image.Image) -> float:
    return float(np.asarray(image.convert("L"), np.float64).mean())


def test_frame_without_thumbnail_gets_the_placeholder_and_unknown_frames_404(
    client: TestClient,
) -> None:
    create_atlas(client)
    frame = add_frame(client, gardens_point_day_night(1, "ref"))
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:  # as a frame stored before thumbnails existed
        session.execute(delete(FrameThumbnail))
        session.commit()
    image, headers = thumbnail(client, "campus", frame["frame_id"])
    assert headers["x-thumbnail"] == "placeholder" and max(image.size) == LONG_SIDE
    missing = client.get(f"/v1/atlases/campus/frames/{frame['frame_id'] + 1}/thumbnail")
    assert missing.status_code == 404
    assert client.get("/v1/atlases/nowhere/frames/1/thumbnail").status_code == 404


def test_queries_store_no_thumbnail_and_deleting_a_frame_deletes_its_thumbnail(
    client: TestClient,
) -> None:
    create_atlas(client)
    frame = add_frame(client, gardens_point_day_night(3, "ref"))
    files = {"image": ("q.jpg", gardens_point_day_night(3, "query"), "image/jpeg")}
    assert client.post("/v1/atlases/campus/query", files=files).status_code == 200
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:
        assert session.scalar(select(func.count()).select_from(FrameThumbnail)) == 1
    assert client.delete(f"/v1/atlases/campus/frames/{frame['frame_id']}").status_code == 204
    with service.sessions() as session:
        assert session.scalar(select(func.count()).select_from(FrameThumbnail)) == 0


def test_snapshots_carry_thumbnails(client: TestClient, tmp_path: Path) -> None:
    create_atlas(client)
    frames = [add_frame(client, gardens_point_day_night(i, "ref")) for i in (4, 5)]
    before = [
        client.get(f"/v1/atlases/campus/frames/{f['frame_id']}/thumbnail").content for f in frames
    ]
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    archive = tmp_path / "campus.tar"
    export_atlas(service.settings, service.sessions, "campus", archive)
    restore_atlas(service.settings, service.sessions, archive, name="copy")
    restored = client.get("/v1/atlases/copy/frames").json()
    assert len(restored) == 2
    after = [
        client.get(f"/v1/atlases/copy/frames/{f['frame_id']}/thumbnail").content for f in restored
    ]
    assert sorted(after) == sorted(before)
