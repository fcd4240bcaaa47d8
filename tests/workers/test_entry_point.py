"""The worker process's entry point: ``python -m workers`` is ``loopnet worker``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import workers.__main__ as entry
from service.runtime.worker import run_worker

ROOT = Path(__file__).resolve().parents[2]


def test_the_entry_point_runs_the_service_worker() -> None:
    assert entry.run_worker is run_worker


def test_python_m_workers_answers_help() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, "-m", "workers", "--help"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert "--threads" in done.stdout
