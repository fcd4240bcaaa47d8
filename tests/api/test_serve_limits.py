"""``loopnet serve`` as a slow or lying client meets it (a real server over real sockets).

Issue 24: ``X-Forwarded-For`` was believed from loopback (a local client chose its own address,
past the failed-authentication limit), and a connection that sent its headers or body slowly
stayed open for good (50 of them for 60 s)."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.config import Settings
from tests.processes import create_token, service_env, serving

pytestmark = pytest.mark.slow  # starts a real server (CNNs included)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """A keyed service with a failure limit of 3 and one-second header and body time-outs;
    yields its URL and an admin key."""
    data = tmp_path_factory.mktemp("limits") / "data"
    admin = create_token(data, "root", "admin")
    env = service_env(
        data,
        LOOPNET_AUTH="required",
        LOOPNET_AUTH_FAILURE_LIMIT="3",
        LOOPNET_HEADER_TIMEOUT_SECONDS="1",
        LOOPNET_BODY_TIMEOUT_SECONDS="1",
    )
    with serving(env) as url:
        yield url, admin


def test_forwarded_for_is_not_believed_without_trusted_proxies(server: tuple[str, str]) -> None:
    url, _ = server
    statuses = [
        httpx.get(
            f"{url}/v1/atlases",
            headers={"X-Forwarded-For": f"203.0.113.{i}", "X-API-Key": "lnk_wrong"},
        ).status_code
        for i in range(6)
    ]
    assert statuses == [401, 401, 401, 429, 429, 429]  # all counted against 127.0.0.1


def test_forwarded_for_is_read_from_the_configured_proxies_only(tmp_path: Path) -> None:
    from service.api.serving import uvicorn_config

    plain = uvicorn_config(None, Settings(data_dir=tmp_path), "127.0.0.1", 8000)
    assert plain.proxy_headers is False
    proxied = Settings(data_dir=tmp_path, trusted_proxies="10.0.0.5, 172.18.0.0/16")
    config = uvicorn_config(None, proxied, "127.0.0.1", 8000)
    assert config.proxy_headers is True
    assert config.forwarded_allow_ips == ["10.0.0.5", "172.18.0.0/16"]


def connect(url: str) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=10)
    return sock


def closed_after(sock: socket.socket, trickle: bytes = b"") -> tuple[float, bytes]:
    """Seconds until the server closes ``sock`` (sending ``trickle`` a byte every 0.3 s
    meanwhile), and what it answered."""
    start = time.monotonic()
    answer = b""
    sock.settimeout(0.3)
    for byte in [trickle[i : i + 1] for i in range(len(trickle))] or [b""] * 40:
        try:
            if byte:
                sock.sendall(byte)
            chunk = sock.recv(4096)
            if not chunk:
                return time.monotonic() - start, answer
            answer += chunk
        except TimeoutError:
            continue
        except (ConnectionResetError, BrokenPipeError):
            return time.monotonic() - start, answer
    sock.settimeout(10)
    try:
        while chunk := sock.recv(4096):
            answer += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return time.monotonic() - start, answer


def test_slow_or_silent_headers_are_cut_off(server: tuple[str, str]) -> None:
    url, _ = server
    with connect(url) as silent:  # connects and sends nothing
        seconds, _ = closed_after(silent)
        assert seconds < 4
    with connect(url) as partial:  # never finishes its headers
        partial.sendall(b"GET /v1/health HTTP/1.1\r\nHost: localhost\r\n")
        seconds, _ = closed_after(partial)
        assert seconds < 4
    with connect(url) as trickling:  # a byte now and then does not keep the deadline away
        seconds, _ = closed_after(
            trickling, b"GET /v1/health HTTP/1.1\r\nHost: localhost\r\nX: " * 2
        )
        assert seconds < 4
    assert httpx.get(f"{url}/v1/health").status_code == 200  # the server is fine


def test_a_body_that_stops_arriving_is_408(server: tuple[str, str]) -> None:
    url, admin = server
    with connect(url) as sock:
        sock.sendall(
            b"POST /v1/atlases HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
            + f"X-API-Key: {admin}\r\n".encode()
            + b'Content-Length: 100\r\n\r\n{"name": '
        )
        seconds, answer = closed_after(sock)
    assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
    assert b"no part of the request body arrived" in answer
    assert seconds < 5
    listing = httpx.get(f"{url}/v1/atlases", headers={"X-API-Key": admin})
    assert listing.status_code == 200 and listing.json() == []
