"""The ``loopnet`` command against a real server process over real HTTP."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.conftest import DATA_DIR, TEST_LONG_SIDE, TEST_MAX_KEYPOINTS

LOOPNET = [sys.executable, "-m", "service.cli"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    return {
        **os.environ,
        "LOOPNET_DATA_DIR": str(tmp_path / "data"),
        "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
        "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
        "LOOPNET_PORT": str(free_port()),
    }


def run(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*LOOPNET, *args], env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_serve_ingest_query_reindex(env: dict[str, str]) -> None:
    url = f"http://127.0.0.1:{env['LOOPNET_PORT']}"
    server = subprocess.Popen(
        [*LOOPNET, "serve"], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                if httpx.get(f"{url}/v1/ready").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert server.poll() is None, server.stdout.read()  # type: ignore[union-attr]
            assert time.monotonic() < deadline, "server not ready in 120 s"
            time.sleep(0.3)

        night = DATA_DIR / "gardenspoint_first10" / "ref"
        ingested = run(
            env,
            "ingest",
            str(night),
            "--atlas",
            "gp",
            "--submap",
            "night",
            "--create",
            "--url",
            url,
        )
        assert ingested.returncode == 0, ingested.stderr
        assert "ingested 10 frames into gp/night" in ingested.stdout
        assert "10/10" in ingested.stderr  # the progress bar
        assert "HTTP Request" not in ingested.stderr  # no per-request lines breaking it

        same = run(env, "query", str(night / "4.jpg"), "--atlas", "gp", "-k", "2", "--url", url)
        assert same.returncode == 0, same.stderr
        answer = json.loads(same.stdout)
        assert answer["match"]["similarity"] > 0.999 and answer["loop_closure"] is True

        missing = run(env, "query", str(night / "4.jpg"), "--atlas", "nowhere", "--url", url)
        assert missing.returncode == 1 and "atlas 'nowhere' does not exist" in missing.stderr

        # once a key exists, a keyless call is told which variable carries the key
        key = run(env, "keys", "create", "--role", "admin", "--name", "ops")
        assert key.returncode == 0, key.stderr
        deadline = time.monotonic() + 30
        while True:  # the service notices the first key within a few seconds
            refused = run(env, "query", str(night / "4.jpg"), "--atlas", "gp", "--url", url)
            if refused.returncode != 0 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert refused.returncode == 1 and "error 401" in refused.stderr
        assert "LOOPNET_API_KEY" in refused.stderr and "Traceback" not in refused.stderr
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=60)
    assert (Path(env["LOOPNET_DATA_DIR"]) / "indexes" / "atlas-1-v1.faiss").is_file()

    reindexed = run(env, "reindex")
    assert reindexed.returncode == 0, reindexed.stderr
    assert "gp: 10 frames indexed" in reindexed.stdout


def test_db_upgrade_creates_the_database(env: dict[str, str]) -> None:
    result = run(env, "db", "upgrade")
    assert result.returncode == 0, result.stderr
    assert (Path(env["LOOPNET_DATA_DIR"]) / "loopnet.sqlite3").is_file()


def test_ingest_refuses_a_missing_folder(env: dict[str, str], tmp_path: Path) -> None:
    result = run(env, "ingest", str(tmp_path / "nope"), "--atlas", "a", "--submap", "s")
    assert result.returncode == 2 and "is not a folder" in result.stderr


def test_an_unreachable_service_is_one_line(env: dict[str, str]) -> None:
    image = DATA_DIR / "gardenspoint_first10" / "ref" / "4.jpg"
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    result = run(env, "query", str(image), "--atlas", "gp", "--url", url)
    assert result.returncode == 1, result.stderr
    assert result.stderr.startswith("error: cannot reach the service at " + url)
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_a_missing_image_is_one_line(env: dict[str, str], tmp_path: Path) -> None:
    result = run(env, "query", str(tmp_path / "nope.jpg"), "--atlas", "gp")
    assert result.returncode == 1
    assert result.stderr.strip() == f"error: No such file or directory: {tmp_path / 'nope.jpg'}"
