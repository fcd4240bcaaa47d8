"""Fixtures the job tests share."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from tests.conftest import make_settings, wait_ready


@pytest.fixture
def app_client(tmp_path: Path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """The API on a fresh data folder. No automatic calibration: an atlas stays at its initial
    version until a job changes it (milestone calibration has its own tests in
    test_calibration_jobs.py)."""
    settings = make_settings(tmp_path / "data", sync_seconds=0.2, calibration_milestones="")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        yield client
