"""Queries: honest cosine similarity, top-k, filters, the loop-closure decision, timings."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.ml.images import decode_image
from service.ml.pipeline import embed_vectors
from tests.api.helpers import add_frame, create_atlas, stored_state
from tests.conftest import gardens_point_day_night, make_settings, wait_ready


def query(client: TestClient, image: bytes, atlas: str = "campus", **fields: str):  # type: ignore[no-untyped-def]
    return client.post(f"/v1/atlases/{atlas}/query", data=fields, files={"image": ("q.jpg", image)})


@pytest.fixture
def atlas_of_five(client: TestClient) -> list[dict]:
    """Night frames 0-4 of Gardens Point in two submaps, by two robots."""
    create_atlas(client, submaps=("start", "end"))
    return [
        add_frame(
            client,
            gardens_point_day_night(i, "ref"),
            submap="start" if i < 3 else "end",
            robot="r1" if i % 2 == 0 else "r2",
        )
        for i in range(5)
    ]


def test_query_answer_shape_and_timings(client: TestClient, atlas_of_five: list[dict]) -> None:
    response = query(client, gardens_point_day_night(3, "ref"), k="3")
    assert response.status_code == 200, response.text
    body = response.json()
    assert len(body["candidates"]) == 3
    sims = [c["similarity"] for c in body["candidates"]]
    assert sims == sorted(sims, reverse=True)
    assert body["match"] == body["candidates"][0]
    assert body["model_version"] == 1 and body["threshold"] == 0.9
    assert set(body["timings_ms"]) == {
        "decode",
        "local_features",
        "global_features",
        "heads",
        "search",
        "verification",
        "total",
    }
    assert body["verification"]["enabled"] is True
    assert body["verification"]["verified_candidates"] == 5  # top 5 verified, k=3 returned
    assert body["predicted_submap"]["available"] is False
    assert "no trained classification head" in body["predicted_submap"]["reason"]


def test_same_image_matches_itself_with_similarity_one(
    client: TestClient, atlas_of_five: list[dict]
) -> None:
    body = query(client, gardens_point_day_night(3, "ref")).json()
    assert body["match"]["frame_id"] == atlas_of_five[3]["frame_id"]
    assert body["match"]["submap"] == "end"
    assert body["match"]["similarity"] == pytest.approx(1.0, abs=1e-4)
    assert body["loop_closure"] is True


def test_similarity_is_the_cosine_of_the_embeddings(
    client: TestClient, atlas_of_five: list[dict], pipeline
) -> None:  # type: ignore[no-untyped-def]
    image = gardens_point_day_night(2, "query")
    body = query(client, image, k="5").json()
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    heads = service.loaded(1).heads

    def embedding(data: bytes) -> np.ndarray:
        features = pipeline.extract(decode_image(data))
        return embed_vectors(heads, features.local_vector[None], features.global_vector[None])[0]

    q = embedding(image)
    for candidate in body["candidates"]:
        index = [f["frame_id"] for f in atlas_of_five].index(candidate["frame_id"])
        expected = float(q @ embedding(gardens_point_day_night(index, "ref")))
        assert candidate["similarity"] == pytest.approx(expected, abs=1e-4)


def test_robot_filter(client: TestClient, atlas_of_five: list[dict]) -> None:
    no_exclusion = {"exclude_recent_frames": "0", "exclude_recent_seconds": "0"}
    image = gardens_point_day_night(0, "ref")
    own = query(client, image, k="5", robot_id="r2", robots="own", **no_exclusion).json()
    assert {c["robot_id"] for c in own["candidates"]} == {"r2"}
    assert len(own["candidates"]) == 2
    others = query(client, image, k="5", robot_id="r2", robots="others", **no_exclusion).json()
    assert {c["robot_id"] for c in others["candidates"]} == {"r1"}
    assert len(others["candidates"]) == 3
    nobody = query(client, image, robot_id="nobody", robots="own").json()
    assert nobody["match"] is None and nobody["loop_closure"] is False


def test_empty_atlas_answers_no_match(client: TestClient, day_image: bytes) -> None:
    create_atlas(client)
    body = query(client, day_image).json()
    assert body["match"] is None and body["candidates"] == [] and body["loop_closure"] is False


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"k": "0"}, "greater than or equal to 1"),
        ({"k": "101"}, "k must be between 1 and 100"),
        ({"k": "many"}, "valid integer"),
    ],
)
def test_bad_k(client: TestClient, day_image: bytes, fields: dict, message: str) -> None:
    create_atlas(client)
    response = query(client, day_image, **fields)
    assert response.status_code == 422 and message in response.text


def test_query_errors_write_nothing(client: TestClient, atlas_of_five: list[dict]) -> None:
    before = stored_state(client)
    assert query(client, b"").status_code == 422
    assert query(client, b"not an image").status_code == 422
    assert query(client, gardens_point_day_night(0, "ref"), atlas="nowhere").status_code == 404
    query(client, gardens_point_day_night(0, "ref"))
    assert stored_state(client) == before


def test_threshold_decides_loop_closure(tmp_path, pipeline) -> None:  # type: ignore[no-untyped-def]
    from service.api.app import create_app

    settings = make_settings(tmp_path, loop_closure_threshold=0.9999)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client)
        add_frame(client, gardens_point_day_night(0, "ref"))
        other = query(client, gardens_point_day_night(0, "query")).json()
        assert other["match"]["similarity"] < 0.9999 and other["loop_closure"] is False
        same = query(client, gardens_point_day_night(0, "ref")).json()
        assert same["loop_closure"] is True


def test_atlas_built_with_other_features_is_refused(tmp_path, pipeline) -> None:  # type: ignore[no-untyped-def]
    from service.api.app import create_app
    from service.storage import repository as repo
    from service.storage.db import transaction

    settings = make_settings(tmp_path)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client)
        service = client.app.state.runtime.service  # type: ignore[attr-defined]
        with transaction(service.sessions) as session:
            atlas = repo.get_atlas(session, name="campus")
            atlas.feature_signature = {
                **atlas.feature_signature,
                "local": {"name": "disk", "long_side": 1024},
            }
        response = query(client, gardens_point_day_night(0, "ref"))
        assert (
            response.status_code == 409
            and "run the service with the atlas's preset" in response.text
        )
