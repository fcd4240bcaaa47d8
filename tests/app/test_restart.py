"""The index follows the database across restarts, crashes and rebuilds."""

from __future__ import annotations

import shutil
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import delete

from service.api.app import create_app
from service.storage.models import Frame
from tests.api.helpers import add_frame, create_atlas, stored_state
from tests.conftest import gardens_point_day_night, make_settings, wait_ready


def start(data_dir: Path, pipeline) -> TestClient:  # type: ignore[no-untyped-def]
    client = TestClient(create_app(make_settings(data_dir), pipeline=pipeline))
    client.__enter__()
    wait_ready(client)
    return client


def best(client: TestClient, image: bytes) -> int:
    response = client.post("/v1/atlases/campus/query", files={"image": ("q.jpg", image)})
    return response.json()["match"]["frame_id"]


def test_restart_serves_the_same_answers(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    client = start(tmp_path, pipeline)
    create_atlas(client)
    ids = [add_frame(client, gardens_point_day_night(i, "ref"))["frame_id"] for i in range(3)]
    before = [best(client, gardens_point_day_night(i, "ref")) for i in range(3)]
    client.__exit__(None, None, None)
    assert (tmp_path / "indexes" / "atlas-1-v1.faiss").is_file()

    client = start(tmp_path, pipeline)
    assert [best(client, gardens_point_day_night(i, "ref")) for i in range(3)] == before == ids
    assert stored_state(client)["indexed"] == 3
    client.__exit__(None, None, None)


def test_index_catches_up_after_a_crash(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    client = start(tmp_path, pipeline)
    create_atlas(client)
    add_frame(client, gardens_point_day_night(0, "ref"))
    client.__exit__(None, None, None)
    index_file = tmp_path / "indexes" / "atlas-1-v1.faiss"
    stale = tmp_path / "stale.faiss"
    shutil.copy(index_file, stale)

    client = start(tmp_path, pipeline)
    late = add_frame(client, gardens_point_day_night(1, "ref"))["frame_id"]
    client.__exit__(None, None, None)
    shutil.copy(stale, index_file)  # as if the process died before writing its index

    client = start(tmp_path, pipeline)
    assert stored_state(client)["indexed"] == 2
    assert best(client, gardens_point_day_night(1, "ref")) == late
    client.__exit__(None, None, None)


def test_index_drops_frames_the_database_no_longer_has(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    client = start(tmp_path, pipeline)
    create_atlas(client)
    first = add_frame(client, gardens_point_day_night(0, "ref"))["frame_id"]
    add_frame(client, gardens_point_day_night(1, "ref"))
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    client.__exit__(None, None, None)
    with service.sessions.begin() as session:
        session.execute(delete(Frame).where(Frame.id == first))

    client = start(tmp_path, pipeline)
    assert stored_state(client)["indexed"] == 1
    assert best(client, gardens_point_day_night(0, "ref")) != first
    client.__exit__(None, None, None)


def test_corrupt_index_file_is_rebuilt(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    client = start(tmp_path, pipeline)
    create_atlas(client)
    frame = add_frame(client, gardens_point_day_night(2, "ref"))["frame_id"]
    client.__exit__(None, None, None)
    (tmp_path / "indexes" / "atlas-1-v1.faiss").write_bytes(b"garbage")

    client = start(tmp_path, pipeline)
    assert best(client, gardens_point_day_night(2, "ref")) == frame
    client.__exit__(None, None, None)


def test_rebuild_from_stored_features_matches_live_index(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    client = start(tmp_path, pipeline)
    create_atlas(client)
    for i in range(4):
        add_frame(client, gardens_point_day_night(i, "ref"))
    query = gardens_point_day_night(1, "query")
    live = client.post(
        "/v1/atlases/campus/query", data={"k": "4"}, files={"image": ("q", query)}
    ).json()
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    assert service.rebuild_index("campus") == 4
    rebuilt = client.post(
        "/v1/atlases/campus/query", data={"k": "4"}, files={"image": ("q", query)}
    ).json()
    assert [c["frame_id"] for c in rebuilt["candidates"]] == [
        c["frame_id"] for c in live["candidates"]
    ]
    for a, b in zip(rebuilt["candidates"], live["candidates"], strict=True):
        assert abs(a["similarity"] - b["similarity"]) < 1e-5
    client.__exit__(None, None, None)
