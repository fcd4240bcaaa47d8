"""API keys: 401 without a valid key, 403 outside the role or the key's atlases; the CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.fleet.keys import Role, create_key, hash_token
from service.storage.db import transaction
from service.storage.models import ApiKey
from tests.api.helpers import stored_state
from tests.conftest import ROOT, gardens_point_day_night, make_settings, wait_ready


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def new_key(client: TestClient, role: Role, *atlases: str) -> str:
    sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
    with transaction(sessions) as session:
        token = create_key(session, name=f"{role.name}-key", role=role, atlases=list(atlases)).token
    client.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
    return token


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
    assert "so the API is open" in caplog.text


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


def test_revoking_every_key_never_reopens_the_api(
    tmp_path: Path, pipeline, caplog: pytest.LogCaptureFixture
) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data")  # LOOPNET_AUTH=auto, the default
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        assert client.get("/v1/atlases").status_code == 200  # no key yet: open
        admin = new_key(client, Role.admin)
        authenticator = client.app.state.authenticator  # type: ignore[attr-defined]
        authenticator._keys_exist = None  # as if the 2 s cache had expired
        with caplog.at_level("WARNING"):
            assert client.get("/v1/atlases").status_code == 401
        assert "API keys are now required" in caplog.text
        keys = client.get("/v1/keys", headers=bearer(admin)).json()
        for key in keys:  # the admin revokes every key, its own last
            assert client.delete(f"/v1/keys/{key['id']}", headers=bearer(admin)).status_code == 200
        authenticator._keys_exist = None
        assert client.get("/v1/atlases").status_code == 401
        attacker = client.post("/v1/keys", json={"name": "attacker", "role": "admin"})
        assert attacker.status_code == 401
    # a restarted process on the same database stays closed too
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        assert client.get("/v1/atlases").status_code == 401


def test_a_scoped_admin_stays_within_its_atlases(open_client: TestClient) -> None:
    client = open_client
    for name in ("campus", "lab", "other"):
        assert client.post("/v1/atlases", json={"name": name}).status_code == 201
    root = new_key(client, Role.admin)
    scoped = new_key(client, Role.admin, "campus", "lab")
    outsider = new_key(client, Role.robot, "other")

    def create(token: str, **body: object) -> int:
        body = {"name": "k", "role": "robot", **body}
        return client.post("/v1/keys", json=body, headers=bearer(token)).status_code

    # keys only within its atlases (a subset is fine), at most admin
    assert create(scoped, atlases=["campus"]) == 201
    assert create(scoped, role="admin", atlases=["campus", "lab"]) == 201
    assert create(scoped) == 403  # unscoped
    assert create(scoped, atlases=["campus", "other"]) == 403
    assert create(scoped, role="operator", atlases=["other"]) == 403
    assert create(root, atlases=["nowhere"]) == 404  # an atlas that does not exist
    assert create(root, name="not a robot id") == 422  # a robot key's name is its robot id
    operator = new_key(client, Role.operator, "campus")
    assert create(operator, atlases=["campus"]) == 403  # operators manage no keys

    # it sees and revokes only keys within its atlases
    visible = client.get("/v1/keys", headers=bearer(scoped)).json()
    assert {tuple(k["atlases"]) for k in visible} <= {("campus",), ("campus", "lab")}
    assert len(visible) == 4  # itself, the two it made, the operator, not root nor outsider
    all_keys = client.get("/v1/keys", headers=bearer(root)).json()
    assert len(all_keys) == 6
    ids = {k["name"]: k["id"] for k in all_keys}
    root_id = next(k["id"] for k in all_keys if k["role"] == "admin" and not k["atlases"])
    assert client.delete(f"/v1/keys/{root_id}", headers=bearer(scoped)).status_code == 404
    assert client.delete(f"/v1/keys/{ids['robot-key']}", headers=bearer(scoped)).status_code == 404
    assert client.get("/v1/atlases", headers=bearer(outsider)).status_code == 200

    # atlases and restores are for unscoped admins
    assert client.post("/v1/atlases", json={"name": "x"}, headers=bearer(scoped)).status_code == 403
    restore = client.post(
        "/v1/snapshots", files={"archive": ("a.tar", b"x")}, headers=bearer(scoped)
    )
    assert restore.status_code == 403
    assert client.post("/v1/atlases", json={"name": "x"}, headers=bearer(root)).status_code == 201
    # within its atlases it is a full admin
    assert client.get("/v1/atlases/campus/snapshot", headers=bearer(scoped)).status_code == 200
    assert client.delete("/v1/atlases/lab", headers=bearer(scoped)).status_code == 204


def test_failed_authentications_are_logged_and_limited_per_address(
    tmp_path: Path, pipeline, caplog: pytest.LogCaptureFixture
) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(
        tmp_path / "data", auth="required", auth_failure_limit=3, auth_failure_window_seconds=60
    )
    secret = "lnk_guessed-token-never-logged"
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        valid = new_key(client, Role.admin)
        with caplog.at_level("WARNING"):
            codes = [
                client.get("/v1/atlases", headers=bearer(secret)).status_code for _ in range(3)
            ]
            assert codes == [401, 401, 401]
            refused = client.get("/v1/atlases", headers=bearer(secret))
            assert refused.status_code == 429 and int(refused.headers["retry-after"]) >= 1
            assert refused.json()["error"] == "TooManyFailures"
            assert client.get("/v1/atlases").status_code == 429  # no key is a failure too
            # a valid key still passes: robots behind one address are not locked out by one
            assert client.get("/v1/atlases", headers=bearer(valid)).status_code == 200
        assert client.get("/v1/health").status_code == 200
        assert "authentication failed from testclient: unknown key" in caplog.text
        assert secret not in caplog.text and secret[4:12] not in caplog.text
    with TestClient(
        create_app(settings, pipeline=pipeline), client=("10.0.0.9", 5000)
    ) as other:  # another address is not affected
        wait_ready(other)
        assert other.get("/v1/atlases", headers=bearer(valid)).status_code == 200


def test_ready_hides_start_up_errors_without_a_key(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", auth="required")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        admin = new_key(client, Role.admin)
        runtime = client.app.state.runtime  # type: ignore[attr-defined]
        runtime._service = None  # as after a failed start-up
        runtime.error = f"OSError: cannot read {tmp_path}/data/models/secret.pt"
        anonymous = client.get("/v1/ready")
        assert anonymous.status_code == 503 and "OSError" not in anonymous.text
        assert str(tmp_path) not in anonymous.text
        wrong = client.get("/v1/ready", headers=bearer("lnk_wrong"))
        assert "OSError" not in wrong.text
        shown = client.get("/v1/ready", headers=bearer(admin))
        assert shown.json()["detail"] == "start-up failed: OSError: cannot read secret.pt"


def test_error_messages_show_no_server_paths(open_client: TestClient) -> None:
    client = open_client
    answer = client.post("/v1/snapshots", files={"archive": ("a.tar", b"not an archive")})
    assert answer.status_code == 422
    assert "/tmp" not in answer.text and "loopnet-restore" not in answer.text, answer.text


def test_cli_creates_lists_and_revokes_keys(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    pipeline,  # type: ignore[no-untyped-def]
) -> None:
    from service.cli import main

    monkeypatch.setenv("LOOPNET_DATA_DIR", str(tmp_path / "data"))
    with TestClient(create_app(make_settings(tmp_path / "data"), pipeline=pipeline)) as client:
        wait_ready(client)
        for name in ("a", "b"):
            assert client.post("/v1/atlases", json={"name": name}).status_code == 201
        api_keys = client.get("/v1/keys")

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
    code, out, err = loopnet("keys", "create", "--role", "admin", "--name", "root")
    assert code == 0, err
    code, listed, _ = loopnet("keys", "list")
    assert key["token"] not in listed and f'"prefix": "{key["prefix"]}"' in listed
    rows = [json.loads(line) for line in listed.splitlines()]
    assert [row["atlases"] for row in rows] == [["a", "b"], []]  # as the API shows them
    assert api_keys.status_code == 200
    assert loopnet("keys", "revoke", str(key["id"]))[0] == 0
    code, _, err = loopnet("keys", "revoke", "999")
    assert code == 1 and "API key 999 does not exist" in err
    code, _, err = loopnet(
        "keys", "create", "--role", "robot", "--atlas", "bad name", "--name", "x"
    )
    assert code == 1 and "atlas name 'bad name' is invalid" in err
    code, _, err = loopnet("keys", "create", "--role", "robot", "--atlas", "c", "--name", "x")
    assert code == 1 and "['c'] do not exist" in err
    code, _, err = loopnet("keys", "create", "--role", "robot", "--name", "husky 1")
    assert code == 1 and "robot name 'husky 1' is invalid" in err

    from service.storage.db import make_engine, make_session_factory

    engine = make_engine(f"sqlite:///{tmp_path / 'data' / 'loopnet.sqlite3'}")
    with make_session_factory(engine)() as session:
        row = session.get(ApiKey, key["id"])
        assert row is not None and row.revoked_at is not None
        assert row.key_hash == hash_token(key["token"]) != key["token"]
    engine.dispose()


def test_the_keys_command_loads_no_model_libraries(tmp_path: Path) -> None:
    """``loopnet keys`` starts fast: neither torch nor faiss is imported on its path."""
    script = (
        "import sys\n"
        "from service.cli import main\n"
        "assert main(['keys', 'list']) == 0\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'faiss', 'kornia'}))\n"
    )
    env = {**os.environ, "LOOPNET_DATA_DIR": str(tmp_path / "data"), "PYTHONPATH": str(ROOT)}
    run = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().splitlines()[-1] == "[]"
