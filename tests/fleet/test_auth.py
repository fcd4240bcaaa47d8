"""API keys: 401 without a valid key, 403 outside the role or the key's atlases; the CLI."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.fleet.keys import Role, create_key, hash_token
from service.storage.db import transaction
from service.storage.models import ApiKey
from tests.api.helpers import stored_state
from tests.conftest import gardens_point_day_night, make_settings, wait_ready


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def new_key(client: TestClient, role: Role, *atlases: str) -> str:
    sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
    with transaction(sessions) as session:
        return create_key(session, name=f"{role.name}-key", role=role, atlases=list(atlases)).token


@pytest.fixture
def open_client(tmp_path: Path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    with TestClient(create_app(make_settings(tmp_path / "data"), pipeline=pipeline)) as client:
        wait_ready(client)
        yield client


def test_the_open_default_says_so(
    tmp_path: Path, pipeline, caplog: pytest.LogCaptureFixture
) -> None:  # type: ignore[no-untyped-def]
    with (
        caplog.at_level("WARNING"),
        TestClient(create_app(make_settings(tmp_path / "data"), pipeline=pipeline)),
    ):
        pass
    assert "no API keys exist, so the API is open" in caplog.text


def test_keys_turn_on_once_one_exists_and_roles_nest(open_client: TestClient) -> None:
    client = open_client
    # embedded default: no keys, open access
    assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
    assert client.post("/v1/atlases", json={"name": "other"}).status_code == 201
    admin = new_key(client, Role.admin)
    client.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
    robot = new_key(client, Role.robot, "campus")
    operator = new_key(client, Role.operator, "campus")

    assert client.get("/v1/health").status_code == 200  # probes stay open
    missing = client.get("/v1/atlases")
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    assert client.get("/v1/atlases", headers=bearer("lnk_wrong")).status_code == 401
    assert client.get("/v1/atlases", headers={"X-API-Key": robot}).status_code == 200

    # robot: its atlas only, no jobs, no deletions, no atlas creation
    listed = client.get("/v1/atlases", headers=bearer(robot)).json()
    assert [a["name"] for a in listed] == ["campus"]
    assert client.get("/v1/atlases/other", headers=bearer(robot)).status_code == 403
    submap = client.post("/v1/atlases/campus/submaps", json={"name": "s0"}, headers=bearer(robot))
    assert submap.status_code == 201
    frame = client.post(
        "/v1/atlases/campus/frames",
        data={"submap": "s0", "robot_id": "robot-key"},  # a robot key is its robot
        files={"image": ("f.jpg", gardens_point_day_night(0, "ref"))},
        headers=bearer(robot),
    )
    assert frame.status_code == 201, frame.text
    forbidden = client.get("/v1/atlases/campus/jobs", headers=bearer(robot))
    assert forbidden.status_code == 403 and "operator role" in forbidden.json()["detail"]
    frame_url = f"/v1/atlases/campus/frames/{frame.json()['frame_id']}"
    assert client.delete(frame_url, headers=bearer(robot)).status_code == 403
    assert client.post("/v1/atlases", json={"name": "x"}, headers=bearer(robot)).status_code == 403

    # operator: jobs, models, deletions on its atlas; not keys, not atlases
    assert client.get("/v1/atlases/campus/models", headers=bearer(operator)).status_code == 200
    assert client.delete(frame_url, headers=bearer(operator)).status_code == 204
    assert client.get("/v1/keys", headers=bearer(operator)).status_code == 403
    assert client.delete("/v1/atlases/campus", headers=bearer(operator)).status_code == 403

    # admin: keys over the API; a revoked key is refused at once
    created = client.post(
        "/v1/keys",
        json={"name": "r2", "role": "robot", "atlases": ["other"]},
        headers=bearer(admin),
    )
    assert created.status_code == 201
    token = created.json()["token"]
    assert token.startswith(created.json()["prefix"])
    assert client.get("/v1/atlases/other", headers=bearer(token)).status_code == 200
    keys = client.get("/v1/keys", headers=bearer(admin)).json()
    assert all("token" not in k for k in keys) and len(keys) == 4
    revoked = client.delete(f"/v1/keys/{created.json()['id']}", headers=bearer(admin))
    assert revoked.status_code == 200 and revoked.json()["revoked_at"] is not None
    assert client.get("/v1/atlases/other", headers=bearer(token)).status_code == 401
    bad_role = client.post("/v1/keys", json={"name": "x", "role": "god"}, headers=bearer(admin))
    assert bad_role.status_code == 422


def test_a_robot_key_acts_as_its_robot_and_its_closures_are_recorded(
    open_client: TestClient,
) -> None:
    client = open_client
    assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
    assert client.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
    sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
    with transaction(sessions) as session:
        husky = create_key(session, name="husky-1", role=Role.robot, atlases=["campus"]).token
        ops = create_key(session, name="ops", role=Role.operator, atlases=["campus"]).token
    client.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
    image = {"image": ("f.jpg", gardens_point_day_night(2, "ref"))}

    def post_frame(robot_id: str, token: str) -> int:
        data = {"submap": "s0", "robot_id": robot_id}
        return client.post(
            "/v1/atlases/campus/frames", data=data, files=image, headers=bearer(token)
        ).status_code

    before = stored_state(client)
    assert post_frame("husky-2", husky) == 403  # posing as another robot: refused, nothing written
    assert stored_state(client) == before
    assert (
        client.post(
            "/v1/atlases/campus/query",
            data={"robot_id": "husky-2"},
            files=image,
            headers=bearer(husky),
        ).status_code
        == 403
    )
    assert post_frame("husky-1", husky) == 201
    assert post_frame("husky-9", ops) == 201  # operators may file frames for any robot

    # no robot_id: the key's robot asks, so its own recent frame is excluded and the closure
    # onto husky-9's frame of the same place is recorded as an inter-robot one
    answer = client.post("/v1/atlases/campus/query", files=image, headers=bearer(husky)).json()
    assert answer["match"]["robot_id"] == "husky-9" and answer["loop_closure"] is True
    closures = client.get("/v1/atlases/campus/loop-closures", headers=bearer(husky)).json()
    assert [(c["robot_id"], c["matched_robot_id"]) for c in closures] == [("husky-1", "husky-9")]


def test_required_mode_refuses_without_any_key(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", auth="required")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        assert client.get("/v1/atlases").status_code == 401
        assert client.get("/v1/ready").status_code == 200


def test_cli_creates_lists_and_revokes_keys(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli import main

    monkeypatch.setenv("LOOPNET_DATA_DIR", str(tmp_path / "data"))

    def loopnet(*args: str) -> tuple[int, str, str]:
        code = main(list(args))
        out, err = capsys.readouterr()
        return code, out, err

    code, out, err = loopnet(
        "keys", "create", "--role", "robot", "--atlas", "a", "--atlas", "b", "--name", "husky"
    )
    assert code == 0, err
    key = json.loads(out)
    assert key["role"] == "robot" and key["atlases"] == ["a", "b"]
    assert "not shown again" in err
    code, listed, _ = loopnet("keys", "list")
    assert key["token"] not in listed and f'"prefix": "{key["prefix"]}"' in listed
    assert loopnet("keys", "revoke", str(key["id"]))[0] == 0
    code, _, err = loopnet("keys", "revoke", "999")
    assert code == 1 and "API key 999 does not exist" in err
    code, _, err = loopnet(
        "keys", "create", "--role", "robot", "--atlas", "bad name", "--name", "x"
    )
    assert code == 1 and "atlas name 'bad name' is invalid" in err

    from service.storage.db import make_engine, make_session_factory

    engine = make_engine(f"sqlite:///{tmp_path / 'data' / 'loopnet.sqlite3'}")
    with make_session_factory(engine)() as session:
        row = session.get(ApiKey, key["id"])
        assert row is not None and row.revoked_at is not None
        assert row.key_hash == hash_token(key["token"]) != key["token"]
    engine.dispose()
