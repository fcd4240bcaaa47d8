"""Bad field values through the HTTP API on SQLite and PostgreSQL: deep JSON, NUL characters,
retraining parameters the worker could never use, and a robot key's frames without robot_id."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.fleet.keys import Role, create_key
from service.ml.presets import PRESETS
from service.storage.db import transaction
from tests.api.helpers import create_atlas, stored_state
from tests.conftest import gardens_point_day_night, make_settings, wait_ready

FUSED_INPUT = sum(PRESETS["default"].signature.dims)  # an uncalibrated atlas's D + R

DEEP = "[" * 100_000 + "]" * 100_000


@pytest.fixture(params=["sqlite", "postgresql"])
def client(request: pytest.FixtureRequest, tmp_path: Path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """The real app with an atlas ``campus`` and a submap ``s0``, on each database."""
    from service.api.app import create_app

    database = {}
    if request.param == "postgresql":
        database["database_url"] = request.getfixturevalue("postgres_url")
    settings = make_settings(tmp_path / "data", **database)
    with TestClient(create_app(settings, pipeline=pipeline)) as test_client:
        wait_ready(test_client)
        create_atlas(test_client)
        yield test_client


def frame_image() -> dict[str, tuple[str, bytes]]:
    return {"image": ("f.jpg", gardens_point_day_night(2, "ref"))}


@pytest.mark.parametrize("field", ["pose", "intrinsics"])
def test_deeply_nested_json_fields_are_422(client: TestClient, field: str) -> None:
    before = stored_state(client)
    response = client.post(
        "/v1/atlases/campus/frames",
        data={"submap": "s0", "robot_id": "r1", field: DEEP},
        files=frame_image(),
    )
    assert response.status_code == 422, response.text
    assert "nested too deeply" in response.json()["detail"]
    assert stored_state(client) == before


@pytest.mark.parametrize(
    ("route", "field"),
    [
        ("frames", "pose"),
        ("frames", "intrinsics"),
        ("query", "intrinsics"),
        ("observe", "pose"),
        ("observe", "intrinsics"),
        ("frames:features", "pose"),  # the form is read before the payload there
    ],
)
def test_numbers_past_the_integer_conversion_limit_are_422(
    client: TestClient, route: str, field: str
) -> None:
    """Issue 24: a number of more than 4,300 digits in a JSON form field made ``json.loads``
    raise a bare ValueError inside the form parser: a 500."""
    from tests.reliability.hostile import long_number_fields

    upload = "features" if route.endswith(":features") else "image"
    files = {upload: ("f.bin", gardens_point_day_night(2, "ref"))}
    fields = {"submap": "s0", "robot_id": "r1"} if route != "query" else {}
    for value in long_number_fields():
        before = stored_state(client)
        response = client.post(
            f"/v1/atlases/campus/{route}", data={**fields, field: value}, files=files
        )
        assert response.status_code == 422, response.text
        assert "digits" in response.json()["detail"]
        assert stored_state(client) == before


@pytest.mark.parametrize(
    ("method", "path", "payload"),
    [
        ("POST", "/v1/atlases", {"name": "a", "description": "before\x00after"}),
        ("POST", "/v1/atlases/campus/submaps", {"name": "s\x00"}),
        ("POST", "/v1/keys", {"name": "ops\x00", "role": "operator"}),
        ("GET", "/v1/atlases/cam%00pus", None),
    ],
)
def test_nul_characters_in_text_are_422_on_every_database(
    client: TestClient, method: str, path: str, payload: dict | None
) -> None:
    headers = {}
    if path == "/v1/keys":  # keys are created over HTTP only with an admin key (issue 24)
        sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
        with transaction(sessions) as session:
            admin = create_key(session, name="root", role=Role.admin, atlases=[]).token
        client.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
        headers = {"X-API-Key": admin}
    before = stored_state(client)
    atlases = client.get("/v1/atlases", headers=headers).json()
    response = client.request(method, path, json=payload, headers=headers)
    assert response.status_code == 422, response.text
    assert {"detail", "error"} <= set(response.json())
    assert stored_state(client) == before
    assert client.get("/v1/atlases", headers=headers).json() == atlases


@pytest.mark.parametrize(
    "path",
    [
        "/v1/atlases/campus/frames/2147483648",  # 2**31: one past PostgreSQL's INTEGER ids
        "/v1/atlases/campus/frames/6469693229/thumbnail",
        "/v1/atlases/campus/jobs/2147483648",
    ],
)
def test_ids_past_the_databases_range_are_422_on_every_database(
    client: TestClient, path: str
) -> None:
    response = client.get(path)
    assert response.status_code == 422, response.text
    assert "2147483647" in response.text
    assert client.get("/v1/atlases/campus/frames/2147483647").status_code == 404


def test_nul_characters_in_form_fields_are_422(client: TestClient) -> None:
    before = stored_state(client)
    for data in ({"submap": "s0\x00", "robot_id": "r1"}, {"submap": "s0", "robot_id": "r\x001"}):
        response = client.post("/v1/atlases/campus/frames", data=data, files=frame_image())
        assert response.status_code == 422, response.text
    assert stored_state(client) == before


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"embed_dim": FUSED_INPUT + 1}, f"fused input size {FUSED_INPUT}"),
        ({"embed_dim": 4096}, f"fused input size {FUSED_INPUT}"),
        ({"seed": 2**64}, "seed must be in"),
        ({"seed": 10**30}, "seed must be in"),
        ({"classification_weight": 0, "contrastive_weight": 0}, "loss weight must be positive"),
        ({"shots": 101}, "less than or equal to 100"),
        ({"train": ["backbone"]}, "'fusion', 'similarity' or 'classifier'"),
    ],
)
def test_retraining_parameters_the_worker_cannot_use_are_422_at_submit(
    client: TestClient, params: dict, message: str
) -> None:
    response = client.post("/v1/atlases/campus/jobs", json={"kind": "retrain", "params": params})
    assert response.status_code == 422, response.text
    assert message in response.json()["detail"]
    assert client.get("/v1/atlases/campus/jobs").json() == []


def test_a_robot_keys_frames_need_no_robot_id(client: TestClient) -> None:
    sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
    with transaction(sessions) as session:
        husky = create_key(session, name="husky-1", role=Role.robot, atlases=["campus"]).token
        admin = create_key(session, name="root", role=Role.admin, atlases=[]).token
    client.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
    as_husky = {"Authorization": f"Bearer {husky}"}
    frame = client.post(
        "/v1/atlases/campus/frames", data={"submap": "s0"}, files=frame_image(), headers=as_husky
    )
    assert frame.status_code == 201, frame.text
    assert frame.json()["robot_id"] == "husky-1"
    observed = client.post(
        "/v1/atlases/campus/observe", data={"submap": "s0"}, files=frame_image(), headers=as_husky
    )
    assert observed.status_code == 201, observed.text
    # any other caller still names the robot
    before = stored_state(client)
    nameless = client.post(
        "/v1/atlases/campus/frames",
        data={"submap": "s0"},
        files=frame_image(),
        headers={"Authorization": f"Bearer {admin}"},
    )
    assert nameless.status_code == 422 and "robot_id is required" in nameless.json()["detail"]
    assert stored_state(client) == before
