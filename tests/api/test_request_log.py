"""One log line per request: JSON by default, plain text on request; the id echoed back."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.fleet.keys import Role, create_key
from service.storage.db import transaction
from tests.conftest import make_settings, wait_ready


@pytest.fixture
def access_lines() -> Iterator[io.StringIO]:
    """What the ``loopnet.access`` logger writes during the test."""
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger = logging.getLogger("loopnet.access")
    logger.addHandler(handler)
    try:
        yield stream
    finally:
        logger.removeHandler(handler)


def lines(stream: io.StringIO) -> list[str]:
    return [line for line in stream.getvalue().splitlines() if line]


def test_json_line_per_request_with_request_id(
    tmp_path, pipeline, access_lines: io.StringIO
) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", auth="required")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
        with transaction(sessions) as session:
            admin = create_key(session, name="ops", role=Role.admin, atlases=[]).token
            token = create_key(session, name="husky-1", role=Role.robot, atlases=[]).token
        created = client.post(
            "/v1/atlases", json={"name": "campus"}, headers={"Authorization": f"Bearer {admin}"}
        )
        assert created.status_code == 201
        access_lines.seek(0)
        access_lines.truncate()
        response = client.get(
            "/v1/atlases/campus/frames",
            params={"limit": 5},
            headers={"Authorization": f"Bearer {token}", "X-Request-ID": "trace-42"},
        )
        assert response.status_code == 200
        assert response.headers["X-Request-ID"] == "trace-42"
        missing = client.get("/v1/atlases/nowhere", headers={"X-Request-ID": "bad id\x01"})
        assert missing.status_code == 401  # no key, no answer
        generated = missing.headers["X-Request-ID"]
        assert len(generated) == 32 and generated != "bad id\x01"  # unsafe ids are replaced
    first, second = (json.loads(line) for line in lines(access_lines)[:2])
    assert first["method"] == "GET" and first["route"] == "/v1/atlases/{atlas}/frames"
    assert first["path"] == "/v1/atlases/campus/frames" and first["status"] == 200
    assert first["atlas"] == "campus" and first["robot"] == "husky-1"
    assert first["request_id"] == "trace-42" and 0 < first["duration_ms"] < 10_000
    assert second["status"] == 401 and second["request_id"] == generated
    assert second["atlas"] == "nowhere" and second["robot"] is None


def test_plain_text_setting(tmp_path, pipeline, access_lines: io.StringIO) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", log_format="text")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        client.get("/v1/atlases/nowhere", headers={"X-Request-ID": "abc"})
    line = lines(access_lines)[-1]
    assert line.startswith("ts=") and "method=GET route=/v1/atlases/{atlas}" in line
    assert "status=404" in line and "atlas=nowhere" in line and "request_id=abc" in line
    with pytest.raises(ValueError):
        json.loads(line)


def test_text_lines_cannot_be_forged_through_the_path(
    tmp_path, pipeline, access_lines: io.StringIO
) -> None:  # type: ignore[no-untyped-def]
    """Issue 24: the text format wrote the decoded path raw, so ``%0A`` in a URL started a
    forged log line; values that are not plain tokens are now written as JSON strings."""
    settings = make_settings(tmp_path / "data", log_format="text")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        access_lines.seek(0)
        access_lines.truncate()
        forged = "/v1/atlases/x%0Ats=2020-01-01 method=GET status=200 robot=admin%22%20%3D%1b[31m"
        assert client.get(forged).status_code == 404
    (line,) = lines(access_lines)
    assert line.startswith("ts=") and "\n" not in line and "\x1b" not in line
    path, end = json.JSONDecoder().raw_decode(line.split(" path=", 1)[1])
    assert path == '/v1/atlases/x\nts=2020-01-01 method=GET status=200 robot=admin" =\x1b[31m'
    assert line.split(" path=", 1)[1][end:].startswith(" status=404 ")
