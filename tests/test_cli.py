"""The ``loopnet`` command against a real server process over real HTTP."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest

from tests.conftest import DATA_DIR
from tests.processes import LOOPNET, free_port, service_env, serving


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    return service_env(tmp_path / "data")


def run(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*LOOPNET, *args], env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_serve_ingest_query_reindex(env: dict[str, str]) -> None:
    with serving(env) as url:
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
