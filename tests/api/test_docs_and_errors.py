"""The documentation pages work offline, and every error answer has the documented shape."""

from __future__ import annotations

import gc
import re
import weakref
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text

from service.storage.db import transaction
from tests.api.helpers import create_atlas
from tests.conftest import make_settings, wait_ready


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_reference_only_same_origin_assets_that_are_served(
    client: TestClient, page: str
) -> None:
    html = client.get(page)
    assert html.status_code == 200
    assets = re.findall(r'(?:src|href)="([^"]+)"', html.text)
    assert assets, html.text
    for asset in assets:
        assert asset.startswith("/") and not asset.startswith("//"), asset
        served = client.get(asset)
        assert served.status_code == 200 and len(served.content) > 1000, asset
    assert not re.search(r"https?://", html.text)
    spec_url = re.search(r"(?:url: '|spec-url=\")([^'\"]+)", html.text)
    assert spec_url and client.get(spec_url.group(1)).status_code == 200


def test_a_stopped_app_is_freed(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    """Nothing process-wide keeps an app (and its models, indexes, engine) once it has stopped:
    the /docs endpoints once closed over theirs, FastAPI cached them, and a test run grew to
    17 GB."""
    from service.api.app import create_app

    with TestClient(create_app(make_settings(tmp_path / "data"), pipeline=pipeline)) as client:
        wait_ready(client)
        assert client.get("/docs").status_code == 200
        runtime = weakref.ref(client.app.state.runtime)  # type: ignore[attr-defined]
    del client
    gc.collect()
    assert runtime() is None


def assert_error_shape(response, status: int) -> dict:  # type: ignore[no-untyped-def]
    assert response.status_code == status, response.text
    body = response.json()
    assert isinstance(body["detail"], str) and body["detail"], body
    assert isinstance(body["error"], str) and body["error"], body
    return body


def test_validation_errors_keep_the_shape_and_list_the_problems(client: TestClient) -> None:
    create_atlas(client)
    body = assert_error_shape(client.post("/v1/atlases", json={"name": "../etc"}), 422)
    assert body["error"] == "InvalidInput" and "body.name" in body["detail"]
    assert body["errors"][0]["loc"] == ["body", "name"]
    missing = assert_error_shape(client.post("/v1/atlases/campus/frames", data={}), 422)
    assert "image" in missing["detail"]


def test_unknown_routes_wrong_methods_and_broken_multipart_keep_the_shape(
    client: TestClient,
) -> None:
    assert assert_error_shape(client.get("/v1/no-such-thing"), 404)["error"] == "NotFound"
    wrong = assert_error_shape(client.put("/v1/atlases"), 405)
    assert wrong["error"] == "MethodNotAllowed"
    create_atlas(client)
    broken = client.post(
        "/v1/atlases/campus/frames",
        content=b'--x\r\nContent-Disposition: form-data; name="submap"\r\n\r\ns0',
        headers={"content-type": "multipart/form-data; boundary=x"},
    )
    assert broken.status_code in (400, 422)
    assert_error_shape(broken, broken.status_code)


def test_a_server_error_keeps_the_shape_and_hides_the_cause(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    from service.api.app import create_app

    app = create_app(make_settings(tmp_path / "data"), pipeline=pipeline)
    with TestClient(app, raise_server_exceptions=False) as client:
        wait_ready(client)
        create_atlas(client)
        with transaction(app.state.runtime.sessions) as session:  # a database gone wrong
            session.execute(text("DROP TABLE loop_closures"))
        body = assert_error_shape(client.get("/v1/atlases/campus/loop-closures"), 500)
        assert body["error"] == "Internal" and "loop_closures" not in body["detail"]


def test_the_trailing_slash_redirect_is_relative(client: TestClient) -> None:
    """Issue 24: the 307 to the path without its trailing slash echoed the Host header."""
    answer = client.get(
        "/v1/atlases/?limit=3", headers={"Host": "localhost:8000"}, follow_redirects=False
    )
    assert answer.status_code == 307
    assert answer.headers["location"] == "/v1/atlases?limit=3"
    followed = client.get("/v1/atlases/")
    assert followed.status_code == 200 and followed.url.path == "/v1/atlases"
    assert client.get("/docs/", follow_redirects=False).headers["location"] == "/docs"
