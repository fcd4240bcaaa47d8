"""The request guard over a real HTTP server: 401 and 413 come before the body is read.

A raw socket announces a large body and sends only its first bytes; the answer must arrive
while the rest is still unsent (a server that waited for the whole body would never answer).
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import uvicorn
from fastapi import FastAPI

from service.api.app import create_app
from service.fleet.keys import Role, create_key
from service.storage.db import transaction
from tests.conftest import make_settings

SNAPSHOT_LIMIT = 256 * 1024
ANSWER_WAIT_S = 20.0


@contextmanager
def live_server(app: FastAPI) -> Iterator[int]:
    """``app`` served by uvicorn in a thread; yields its port."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.05)
    try:
        yield sock.getsockname()[1]
    finally:
        server.should_exit = True
        thread.join(30)
        sock.close()


@pytest.fixture
def served(tmp_path: Path, pipeline) -> Iterator[tuple[int, str]]:  # type: ignore[no-untyped-def]
    """A server with keys required and a small snapshot limit; yields (port, admin token)."""
    settings = make_settings(tmp_path / "data", auth="required", max_snapshot_bytes=SNAPSHOT_LIMIT)
    app = create_app(settings, pipeline=pipeline)
    with live_server(app) as port:
        with transaction(app.state.runtime.sessions) as session:
            token = create_key(session, name="root", role=Role.admin, atlases=[]).token
        yield port, token


def status_of_answer(sock: socket.socket) -> int:
    """The status code of the answer on ``sock`` (waits at most ANSWER_WAIT_S)."""
    sock.settimeout(ANSWER_WAIT_S)
    data = b""
    while b"\r\n" not in data:
        chunk = sock.recv(4096)
        assert chunk, "the server closed the connection without answering"
        data += chunk
    return int(data.split(b" ", 2)[1])


def send_quietly(sock: socket.socket, data: bytes) -> None:
    """Send what the server still takes; a server that has answered may stop reading."""
    try:
        sock.settimeout(5)
        sock.sendall(data)
    except OSError:
        pass


def request_head(path: str, headers: dict[str, str]) -> bytes:
    lines = [f"POST {path} HTTP/1.1", "Host: 127.0.0.1", *(f"{k}: {v}" for k, v in headers.items())]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


@pytest.mark.parametrize(
    ("path", "content_type"),
    [
        ("/v1/snapshots", "multipart/form-data; boundary=b"),
        ("/v1/atlases/campus/frames", "multipart/form-data; boundary=b"),
        ("/v1/keys", "application/json"),
    ],
)
def test_a_large_body_without_a_key_is_refused_before_it_is_read(
    served: tuple[int, str], path: str, content_type: str
) -> None:
    port, _ = served
    with socket.create_connection(("127.0.0.1", port)) as sock:
        head = {"Content-Type": content_type, "Content-Length": str(300 * 1024 * 1024)}
        sock.sendall(request_head(path, head))
        send_quietly(sock, b"x" * 65536)  # 64 KiB of the announced 300 MB
        assert status_of_answer(sock) == 401


def test_a_declared_length_over_the_snapshot_limit_is_refused_at_once(
    served: tuple[int, str],
) -> None:
    port, token = served
    with socket.create_connection(("127.0.0.1", port)) as sock:
        head = {
            "Authorization": f"Bearer {token}",
            "Content-Type": "multipart/form-data; boundary=b",
            "Content-Length": str(SNAPSHOT_LIMIT + 1),
        }
        sock.sendall(request_head("/v1/snapshots", head))  # not a byte of the body
        assert status_of_answer(sock) == 413


def test_a_chunked_upload_is_refused_once_it_passes_the_limit(served: tuple[int, str]) -> None:
    port, token = served
    with socket.create_connection(("127.0.0.1", port)) as sock:
        head = {
            "Authorization": f"Bearer {token}",
            "Content-Type": "multipart/form-data; boundary=b",
            "Transfer-Encoding": "chunked",  # no length declared: counted as it arrives
        }
        sock.sendall(request_head("/v1/snapshots", head))
        part = (
            b'--b\r\nContent-Disposition: form-data; name="archive"; filename="a.tar"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n"
        )
        chunks = [part] + [b"x" * 65536] * (2 * SNAPSHOT_LIMIT // 65536)  # twice the limit
        for chunk in chunks:  # and never the end
            send_quietly(sock, f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
        assert status_of_answer(sock) == 413
