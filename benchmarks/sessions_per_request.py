"""Count the database sessions (transactions begun) one HTTP query, observation and ingest
open, on a real app over SQLite with the real CNNs.

    LOOPNET_TORCH_THREADS=1 python benchmarks/sessions_per_request.py

Counts come from a SQLAlchemy ``after_begin`` event on the service's session factory: every
session that touches the database begins exactly once. The inter-robot record (a write of its
own when the answer closes a loop onto another robot's frame) and the API-key check are
counted too; the background threads' sessions (change feed, loading) are not.
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import event

# Each request is sent this often (the first ingest also loads the atlas's state).
REPEATS = 3
DATA = Path(os.environ.get("LOOPNET_SHARED_DIR", "/work/shared")) / "data" / "gardenspoint_first10"


def request_thread() -> bool:
    """Sessions of the request itself, not of the service's background threads."""
    return not threading.current_thread().name.startswith("loopnet-")


def main() -> None:
    for poll in (3600.0, 0.0):
        print(f"model poll period {poll:g} s (0: every request checks the active version)")
        measure(poll)


def measure(poll: float) -> None:
    from service.api.app import create_app
    from service.config import Settings

    settings = Settings(
        data_dir=Path(tempfile.mkdtemp()),
        long_side=320,
        max_keypoints=256,
        model_poll_seconds=poll,
    )
    image = (DATA / "ref" / "0.jpg").read_bytes()
    query_image = (DATA / "query" / "0.jpg").read_bytes()
    with TestClient(create_app(settings)) as client:
        while client.get("/v1/ready").status_code != 200:
            time.sleep(0.1)
        client.post("/v1/atlases", json={"name": "campus"})
        client.post("/v1/atlases/campus/submaps", json={"name": "s0"})
        sessions = client.app.state.runtime.service.sessions  # type: ignore[attr-defined]
        begun: list[int] = []
        event.listen(
            sessions, "after_begin", lambda *_: begun.append(1) if request_thread() else None
        )

        def count(label: str, path: str, data: dict[str, str], img: bytes) -> None:
            counts = []
            for _ in range(REPEATS):
                begun.clear()
                response = client.post(
                    f"/v1/atlases/campus/{path}", data=data, files={"image": ("f.jpg", img)}
                )
                assert response.status_code in (200, 201), response.text
                counts.append(len(begun))
            print(f"{label:<34} sessions per request: {counts}")

        count("ingest (POST /frames)", "frames", {"submap": "s0", "robot_id": "r1"}, image)
        count("query (anonymous)", "query", {}, query_image)
        count(
            "query (robot r2, submap filter)",
            "query",
            {"robot_id": "r2", "submap": "s0"},
            query_image,
        )
        count("observe (robot r2)", "observe", {"submap": "s0", "robot_id": "r2"}, query_image)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
