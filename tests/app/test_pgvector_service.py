"""The service on pgvector: vectors in the frame's transaction, the feed without frames, lost
rows re-embedded at start, a rebuild from stored features, filters in SQL."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import func, select, text

from service.api.app import create_app
from service.app import model_versions as models_store
from service.index.pgvector_store import PgVectorStore
from service.index.store import fill_version_table
from service.ml.active_model import ActiveModel
from service.storage.models import AtlasChange, ModelVersion
from tests.api.helpers import add_frame, create_atlas
from tests.app.test_change_feed import add_untrained_version, within
from tests.conftest import gardens_point_day_night, make_settings, wait_ready


def start(data_dir: Path, url: str, pipeline) -> TestClient:  # type: ignore[no-untyped-def]
    settings = make_settings(data_dir, database_url=url, vector_store="pgvector")
    client = TestClient(create_app(settings, pipeline=pipeline))
    client.__enter__()
    wait_ready(client)
    return client


def best(client: TestClient, image: bytes, **form: str) -> list[int]:
    response = client.post(
        "/v1/atlases/campus/query", data={"k": "3", **form}, files={"image": ("q.jpg", image)}
    )
    assert response.status_code == 200, response.text
    return [c["frame_id"] for c in response.json()["candidates"]]


def test_pgvector_service_end_to_end(tmp_path: Path, pgvector_url: str, pipeline) -> None:  # type: ignore[no-untyped-def]
    client = start(tmp_path, pgvector_url, pipeline)
    create_atlas(client)
    ids = [
        add_frame(client, gardens_point_day_night(i, "ref"), robot=f"robot-{i % 2}")["frame_id"]
        for i in range(4)
    ]
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    state = service.loaded(1)
    assert isinstance(state.index, PgVectorStore) and sorted(state.index.ids().tolist()) == ids
    with service.sessions() as session:  # the feed orders commits but carries no frames
        assert session.scalar(select(func.count()).select_from(AtlasChange)) == 0
    before = best(client, gardens_point_day_night(1, "ref"))
    assert before[0] == ids[1]
    own = best(client, gardens_point_day_night(1, "ref"), robot_id="robot-1", robots="others")
    assert own and set(own) <= {ids[0], ids[2]}
    client.__exit__(None, None, None)

    # vectors lost (a table truncated): the start-up re-embeds them from stored features
    with service.sessions.begin() as session:
        session.execute(text(f"DELETE FROM {state.index.table} WHERE frame_id = {ids[1]}"))
    client = start(tmp_path, pgvector_url, pipeline)
    assert best(client, gardens_point_day_night(1, "ref")) == before
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    assert service.rebuild_index("campus") == 4  # the table dropped, re-embedded
    assert best(client, gardens_point_day_night(1, "ref")) == before

    # a new version's vectors are written beside the active ones, then switched to at once
    version = add_untrained_version(client)
    model = ActiveModel(models_store.load_heads(version_row(service, version), tmp_path), None)
    assert fill_version_table("pgvector", service.sessions, 1, version, model) == 4
    assert client.post(f"/v1/atlases/campus/models/{version}/activate").status_code == 200
    within(10, lambda: service.states.current(1).model_version == version)
    swapped = service.states.current(1)
    assert swapped.index.table.endswith(f"_v{version}") and swapped.index.size == 4
    assert best(client, gardens_point_day_night(1, "ref"))[0] == ids[1]
    client.__exit__(None, None, None)


def version_row(service, version: int):  # type: ignore[no-untyped-def]
    with service.sessions() as session:
        row = session.scalar(select(ModelVersion).where(ModelVersion.version == version))
        session.expunge(row)
        return row
