"""Issue 24: the open service trusted any origin and any host. A DNS-rebinding page (whose
requests name its own host) or a cross-site form (a "simple" request) could create frames,
restore snapshots and make itself the first admin. Now: a Host outside the allowed names is
400, a keyless state change from another origin is 403, and the first key comes from the CLI."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service.api.app import create_app
from service.fleet.keys import KeyAdmin, Role
from service.storage.models import ApiKey
from tests.api.helpers import create_atlas, stored_state
from tests.conftest import gardens_point_day_night, make_settings, wait_ready

PUBLIC = "loopnet.example.org"


@pytest.fixture
def open_service(tmp_path: Path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """The open embedded service (no key yet), answering to loopback and its public name."""
    settings = make_settings(tmp_path / "data", allowed_hosts=f"{PUBLIC},*.fleet.example.org")
    app = create_app(settings, pipeline=pipeline)
    with TestClient(app, base_url="http://localhost:8000") as client:
        wait_ready(client)
        yield client


def keys_in(client: TestClient) -> int:
    sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
    with sessions() as session:
        return int(session.scalar(select(func.count(ApiKey.id))) or 0)


@pytest.mark.parametrize(
    "host",
    ["localhost:8000", "127.0.0.1", "[::1]:8000", "LoopNet.Example.org:443", "a.fleet.example.org"],
)
def test_the_service_answers_to_its_own_names(open_service: TestClient, host: str) -> None:
    assert open_service.get("/v1/atlases", headers={"Host": host}).status_code == 200


@pytest.mark.parametrize(
    "host", ["evil.example", "loopnet.example.org.evil.example", "fleet.example.org", ""]
)
def test_a_foreign_host_is_refused(open_service: TestClient, host: str) -> None:
    """What a DNS-rebinding page sends: its own name, resolved to the service's address."""
    create_atlas(open_service)
    before = stored_state(open_service)
    for method, path in (("GET", "/v1/atlases"), ("POST", "/v1/atlases"), ("GET", "/")):
        answer = open_service.request(
            method, path, headers={"Host": host}, json={"name": "rebound"}
        )
        assert answer.status_code == 400, (method, path, answer.text)
        assert answer.json()["error"] == "UnknownHost"
        assert "LOOPNET_ALLOWED_HOSTS" in answer.json()["detail"]
    frame = open_service.post(
        "/v1/atlases/campus/frames",
        data={"submap": "s0", "robot_id": "r1"},
        files={"image": ("f.jpg", gardens_point_day_night(0, "ref"))},
        headers={"Host": host},
    )
    assert frame.status_code == 400
    assert stored_state(open_service) == before
    # probes and metrics answer by address (orchestrators, Prometheus), and name nothing
    for path in ("/v1/health", "/v1/ready", "/metrics"):
        assert open_service.get(path, headers={"Host": "10.0.3.7:8000"}).status_code == 200


def test_a_cross_site_state_change_without_a_key_is_refused(open_service: TestClient) -> None:
    create_atlas(open_service)
    before = stored_state(open_service)
    foreign = (
        {"Origin": "https://evil.example"},
        {"Origin": "null"},  # a sandboxed frame or a file: page
        {"Origin": "http://localhost:3000"},  # another port is another origin
        {"Sec-Fetch-Site": "cross-site"},
        {"Sec-Fetch-Site": "same-site", "Origin": "http://localhost:8000"},
    )
    for headers in foreign:
        frame = open_service.post(
            "/v1/atlases/campus/frames",
            data={"submap": "s0", "robot_id": "r1"},
            files={"image": ("f.jpg", gardens_point_day_night(0, "ref"))},
            headers=headers,
        )
        assert frame.status_code == 403, (headers, frame.text)
        assert "another web origin" in frame.json()["detail"]
        restore = open_service.post(
            "/v1/snapshots", files={"archive": ("s.tar", b"x" * 1000)}, headers=headers
        )
        assert restore.status_code == 403
        assert open_service.delete("/v1/atlases/campus", headers=headers).status_code == 403
    assert stored_state(open_service) == before
    # reading stays possible cross-origin (the browser keeps the answer from the page)
    assert open_service.get("/v1/atlases", headers=foreign[0]).status_code == 200
    # the console's own page (same origin) and clients that are not browsers pass
    same = {"Origin": "http://localhost:8000", "Sec-Fetch-Site": "same-origin"}
    assert open_service.post("/v1/atlases", json={"name": "a"}, headers=same).status_code == 201
    assert open_service.post("/v1/atlases", json={"name": "b"}).status_code == 201
    # a request showing a key is no form post: the key decides (any key while the API is open)
    keyed = {"Origin": "https://tool.example", "X-API-Key": "lnk_anything"}
    assert open_service.post("/v1/atlases", json={"name": "c"}, headers=keyed).status_code == 201


def test_the_first_admin_key_comes_only_from_the_cli(open_service: TestClient) -> None:
    answer = open_service.post("/v1/keys", json={"name": "me", "role": "admin"})
    assert answer.status_code == 403, answer.text
    assert "loopnet keys create" in answer.json()["detail"]
    assert keys_in(open_service) == 0
    assert open_service.get("/v1/atlases").status_code == 200  # still open: nothing changed
    sessions = open_service.app.state.runtime.sessions  # type: ignore[attr-defined]
    root = (
        KeyAdmin(sessions).issue(name="root", role=Role.admin, atlases=[]).token
    )  # what the CLI does
    open_service.app.state.authenticator._keys_exist = None  # type: ignore[attr-defined]
    created = open_service.post(
        "/v1/keys", json={"name": "ops", "role": "operator"}, headers={"X-API-Key": root}
    )
    assert created.status_code == 201, created.text
    assert keys_in(open_service) == 2
