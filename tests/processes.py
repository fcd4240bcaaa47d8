"""Real LoopNet processes for tests that need them: ``loopnet serve`` on a free port, keys
written straight into its database (as ``loopnet keys create`` does)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

from tests.conftest import TEST_LONG_SIDE, TEST_MAX_KEYPOINTS

LOOPNET = [sys.executable, "-m", "service.cli"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def service_env(data_dir: Path, **extra: str) -> dict[str, str]:
    return {
        **os.environ,
        "LOOPNET_DATA_DIR": str(data_dir),
        "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
        "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
        "LOOPNET_PORT": str(free_port()),
        **extra,
    }


@contextmanager
def serving(env: dict[str, str], *, wait: bool = True, timeout: float = 120) -> Iterator[str]:
    """Run ``loopnet serve``; yields its URL (once ready, unless ``wait`` is false)."""
    with served_process(env, wait=wait, timeout=timeout) as (url, _):
        yield url


def peak_rss_bytes(pid: int) -> int:
    """The process's peak resident memory since it started or :func:`reset_peak_rss`."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc: not Linux?")


def reset_peak_rss(pid: int) -> None:
    """Start the process's peak resident memory again from now (Linux >= 4.0)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


@contextmanager
def served_process(
    env: dict[str, str], *, wait: bool = True, timeout: float = 120
) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """:func:`serving`, yielding the server process too."""
    url = f"http://127.0.0.1:{env['LOOPNET_PORT']}"
    # a file, not a pipe: nobody reads the log while the server runs, and a full pipe (a few
    # hundred requests' log lines) blocks the server
    with tempfile.TemporaryFile("w+") as log:
        server = subprocess.Popen(
            [*LOOPNET, "serve"], env=env, stdout=log, stderr=subprocess.STDOUT
        )
        try:
            deadline = time.monotonic() + timeout
            while wait:
                try:
                    if httpx.get(f"{url}/v1/ready").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if server.poll() is not None:
                    log.seek(0)
                    raise AssertionError(f"the server exited: {log.read()[-4000:]}")
                assert time.monotonic() < deadline, f"server not ready in {timeout} s"
                time.sleep(0.3)
            yield url, server
        finally:
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(timeout=60)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()


def create_token(data_dir: Path, name: str, role: str, atlases: tuple[str, ...] = ()) -> str:
    """A new API key in the service's database (migrated first); returns its token."""
    from service.config import Settings
    from service.fleet.keys import Role, create_key
    from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database

    url = Settings(data_dir=data_dir).resolved_database_url
    data_dir.mkdir(parents=True, exist_ok=True)
    upgrade_database(url)
    engine = make_engine(url)
    try:
        with transaction(make_session_factory(engine)) as session:
            return create_key(session, name=name, role=Role[role], atlases=list(atlases)).token
    finally:
        engine.dispose()
