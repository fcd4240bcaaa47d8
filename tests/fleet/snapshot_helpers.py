"""Shared by the snapshot tests: the CLI run in-process, deployments, and one exported
archive of a real atlas (two robots, a trained version, one inter-robot closure)."""

from __future__ import annotations

import io
import os
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

from fastapi.testclient import TestClient

from service.cli import main
from tests.conftest import TEST_LONG_SIDE, TEST_MAX_KEYPOINTS, gardens_point_day_night

QUERIES = (1, 4, 7)


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


def loopnet(env: dict[str, str], *args: str) -> Ran:
    """``loopnet ARGS`` in this process (the CLI's own code) with ``env`` set meanwhile."""
    saved = {name: os.environ.get(name) for name in env}
    os.environ.update(env)
    out, err = io.StringIO(), io.StringIO()
    try:
        with redirect_stdout(out), redirect_stderr(err):
            code = main(list(args))
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return Ran(code, out.getvalue(), err.getvalue())


def deployment_env(data_dir: Path, database_url: str | None = None) -> dict[str, str]:
    env = {
        "LOOPNET_DATA_DIR": str(data_dir),
        "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
        "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
    }
    if database_url:
        env["LOOPNET_DATABASE_URL"] = database_url
    return env


def answers(client: TestClient, atlas: str) -> list[dict]:
    """Query answers without what legitimately differs between deployments (ids, timings)."""
    out = []
    for i in QUERIES:
        body = client.post(
            f"/v1/atlases/{atlas}/query",
            data={"k": "4"},
            files={"image": ("q.jpg", gardens_point_day_night(i, "query"))},
        ).json()
        out.append(
            {
                "model_version": body["model_version"],
                "loop_closure": body["loop_closure"],
                "predicted": (
                    body["predicted_submap"]["submap"],
                    round(body["predicted_submap"]["probability"] or 0, 5),
                ),
                "candidates": [
                    (c["submap"], c["robot_id"], round(c["similarity"], 5))
                    for c in body["candidates"]
                ],
            }
        )
    return out
