"""Shared fixtures: a TORCH_HOME seeded with the real weights, real data, real apps.

The weights and datasets come from ``shared/`` beside the repository (override with
``LOOPNET_SHARED_DIR``). Nothing is mocked: the CNNs are the pretrained ones, databases are
SQLite files in temporary directories, and the API is the real app.
"""

from __future__ import annotations

import io
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("LOOPNET_SHARED_DIR", ROOT.parent / "shared"))
WEIGHTS_DIR = SHARED / "weights"
DATA_DIR = SHARED / "data"
TEST_LONG_SIDE = 256  # DISK at 256 px keeps the suite fast; the presets use 512 and 1024
TEST_MAX_KEYPOINTS = 512

pytest_plugins = ["tests.services"]  # postgres_url, redis_queue


def _seed_torch_home() -> Path:
    from service.ml.weights import seed_cache, set_offline

    set_offline(True)  # never reach for the network in tests (LOOPNET_OFFLINE: in subprocesses)
    if not WEIGHTS_DIR.is_dir():
        raise RuntimeError(
            f"the tests need the pretrained weights in {WEIGHTS_DIR} (set LOOPNET_SHARED_DIR)"
        )
    torch_home = Path(os.environ.get("TORCH_HOME", ROOT / ".pytest-torch-home"))
    seed_cache(WEIGHTS_DIR, torch_home / "hub" / "checkpoints")
    return torch_home


os.environ["TORCH_HOME"] = str(_seed_torch_home())
os.environ["LOOPNET_OFFLINE"] = "1"  # never reach for the network in tests
# Starlette's TestClient sends "Host: testserver"; the service answers only to the hosts it is
# told (tests/api/test_host_and_origin.py sets its own list)
os.environ.setdefault("LOOPNET_ALLOWED_HOSTS", "testserver")


@pytest.fixture(scope="session")
def pipeline():  # type: ignore[no-untyped-def]
    """The real CNNs (DISK + MobileNetV2), loaded once for the whole session."""
    from service.ml.pipeline import FeaturePipeline
    from service.ml.presets import resolve_preset

    return FeaturePipeline(
        resolve_preset("default", long_side=TEST_LONG_SIDE, max_keypoints=TEST_MAX_KEYPOINTS)
    )


def make_settings(data_dir: Path, **overrides: object):  # type: ignore[no-untyped-def]
    from service.config import Settings

    values: dict[str, object] = {
        "data_dir": data_dir,
        "long_side": TEST_LONG_SIDE,
        "max_keypoints": TEST_MAX_KEYPOINTS,
    }
    values.update(overrides)
    return Settings(**values)  # type: ignore[arg-type]


@pytest.fixture
def settings(tmp_path: Path):  # type: ignore[no-untyped-def]
    return make_settings(tmp_path / "data")


def wait_ready(client: TestClient, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if client.get("/v1/ready").status_code == 200:
            return
        time.sleep(0.05)
    raise TimeoutError(client.get("/v1/ready").json())


@pytest.fixture
def client(settings, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """The real app on a fresh SQLite database, sharing the session's loaded CNNs."""
    from service.api.app import create_app

    with TestClient(create_app(settings, pipeline=pipeline)) as test_client:
        wait_ready(test_client)
        yield test_client


# ----- real images ------------------------------------------------------------------------


def gardens_point_day_night(index: int, side: str) -> bytes:
    """Full-size Gardens Point frame ``index`` (0-9): side 'query' (day) or 'ref' (night)."""
    return (DATA_DIR / "gardenspoint_first10" / side / f"{index}.jpg").read_bytes()


def encode(array: np.ndarray, fmt: str = "PNG", **params: object) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format=fmt, **params)
    return buffer.getvalue()


@pytest.fixture
def day_image() -> bytes:
    return gardens_point_day_night(3, "query")
