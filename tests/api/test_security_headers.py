"""Issue 24: no Content-Security-Policy, X-Frame-Options / frame-ancestors,
X-Content-Type-Options or Referrer-Policy on the console and the API. Every answer has them
now; the console runs only its own files, the docs pages exactly their own start-up script
(tests/console checks both still work in a real browser)."""

from __future__ import annotations

import base64
import hashlib
import re

from fastapi.testclient import TestClient

from tests.api.helpers import create_atlas


def directives(answer) -> dict[str, str]:  # type: ignore[no-untyped-def]
    policy = answer.headers["content-security-policy"]
    return {part.split()[0]: part for part in (p.strip() for p in policy.split(";")) if part}


def assert_hardened(answer) -> dict[str, str]:  # type: ignore[no-untyped-def]
    assert answer.headers["x-content-type-options"] == "nosniff"
    assert answer.headers["x-frame-options"] == "DENY"
    assert answer.headers["referrer-policy"] == "no-referrer"
    found = directives(answer)
    assert found["frame-ancestors"] == "frame-ancestors 'none'"
    assert found["base-uri"] == "base-uri 'none'"
    return found


def test_every_answer_carries_the_security_headers(client: TestClient) -> None:
    create_atlas(client)
    for answer in (
        client.get("/v1/health"),
        client.get("/v1/atlases"),
        client.get("/v1/atlases/nowhere"),  # an error
        client.post("/v1/atlases", json={"name": "../x"}),  # a validation error
        client.get("/metrics"),
        client.get("/openapi.json"),
        client.get("/v1/atlases/", follow_redirects=False),  # the slash redirect
    ):
        policy = assert_hardened(answer)
        assert policy["default-src"] == "default-src 'none'", answer.request.url


def test_the_console_runs_only_its_own_files(client: TestClient) -> None:
    page = client.get("/")
    policy = assert_hardened(page)
    assert policy["script-src"] == "script-src 'self'"  # no inline script, no eval
    assert policy["style-src"] == "style-src 'self'"
    assert policy["img-src"] == "img-src 'self' blob: data:"  # thumbnails are blob: URLs
    assert policy["connect-src"] == "connect-src 'self'"
    assert "<script>" not in page.text and " style=" not in page.text
    assert assert_hardened(client.get("/console/app.js"))["script-src"] == "script-src 'self'"


def test_the_docs_pages_allow_exactly_their_start_up_script(client: TestClient) -> None:
    for path in ("/docs", "/redoc"):
        page = client.get(path)
        policy = assert_hardened(page)
        inline = re.findall(r"<script>(.*?)</script>", page.text, re.DOTALL)
        allowed = {
            "'sha256-" + base64.b64encode(hashlib.sha256(s.encode()).digest()).decode() + "'"
            for s in inline
        }
        assert set(policy["script-src"].split()[1:]) == {"'self'", *allowed}, path
        assert "'unsafe-eval'" not in page.headers["content-security-policy"]
    assert len(allowed) == 0  # ReDoc's page has no inline script; Swagger UI's one was checked
