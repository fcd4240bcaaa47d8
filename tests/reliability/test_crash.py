"""SIGKILL while robots ingest: no acknowledged frame is lost, no half-written frame is seen.

A real ``loopnet serve`` process is killed with SIGKILL at a random moment while three client
threads ingest real frames, then restarted; this repeats ``LOOPNET_CRASH_RESTARTS`` times
(default 3; the reported run used 20). After every kill, with the server down, the data
directory is checked: every frame acknowledged with 201 is in the frames table, every frame row
has its features row (and the other way round), and the index the service builds at start-up
(the stale file on disk, reconciled with the database) holds exactly the database's frames.
At the end the restarted server answers for every acknowledged frame, and after its graceful
stop the index file it wrote holds them all.
"""

from __future__ import annotations

import os
import random
import threading
import time
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from benchmarks.load import LiveServer
from service.app.catalog import AtlasService
from service.index import AtlasIndex
from service.index.pgvector_store import PgVectorStore
from service.storage import repository as repo
from service.storage.db import make_engine, make_session_factory
from service.storage.models import Frame, FrameFeatureRow
from tests.conftest import DATA_DIR, TEST_LONG_SIDE, TEST_MAX_KEYPOINTS, make_settings

RESTARTS = int(os.environ.get("LOOPNET_CRASH_RESTARTS", "3"))
CLIENTS = 3
ATLAS = "crash"


class Robots:
    """Client threads ingesting until told to stop; they keep every acknowledged frame id."""

    def __init__(self, url: str, images: list[bytes]) -> None:
        self.url = url
        self.images = images
        self.acked: set[int] = set()
        self.unexpected: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._run, args=(i,)) for i in range(CLIENTS)]

    def __enter__(self) -> Robots:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=120)

    def _run(self, index: int) -> None:
        rng = random.Random(index)
        with httpx.Client(base_url=self.url, timeout=60) as client:
            while not self._stop.is_set():
                try:
                    response = client.post(
                        f"/v1/atlases/{ATLAS}/frames",
                        data={"submap": "s0", "robot_id": f"r{index}"},
                        files={"image": ("f.png", rng.choice(self.images), "image/png")},
                    )
                except httpx.TransportError:
                    time.sleep(0.05)  # the server is down: no answer, nothing acknowledged
                    continue
                with self._lock:
                    if response.status_code == 201:
                        self.acked.add(response.json()["frame_id"])
                    elif response.status_code != 503:
                        self.unexpected.append(f"{response.status_code} {response.text[:200]}")

    def acknowledged(self) -> set[int]:
        with self._lock:
            return set(self.acked)


def check_data_dir(data_dir: Path, acked: set[int], pipeline, **db: str) -> set[int]:  # type: ignore[no-untyped-def]
    """With the server down: the database and the index built at start-up hold every
    acknowledged frame, and no frame lacks its features. Returns the database's frame ids.
    On pgvector (``db``: its settings) the vector table holds exactly the frames before any
    process reconciles it: each vector committed with its frame."""
    settings = make_settings(data_dir, **db)
    engine = make_engine(settings.resolved_database_url)
    sessions = make_session_factory(engine)
    try:
        with sessions() as session:
            in_db = set(session.scalars(select(Frame.id)))
            with_features = set(session.scalars(select(FrameFeatureRow.frame_id)))
            atlas_id = repo.get_atlas(session, name=ATLAS).id
            assert session.scalar(select(func.count(Frame.id))) == len(in_db)
        assert acked <= in_db, f"acknowledged frames lost: {sorted(acked - in_db)}"
        assert in_db == with_features, "a frame row without its features (or the reverse)"
        if db.get("vector_store") == "pgvector":
            table = PgVectorStore(sessions, atlas_id, 1, pipeline.heads_config().fused_dim)
            in_table = set(table.ids().tolist())
            assert in_table == in_db, (sorted(in_db - in_table), sorted(in_table - in_db))
        service = AtlasService(settings, sessions, pipeline)
        indexed = set(service.loaded(atlas_id).index.ids().tolist())
        assert indexed == in_db, (sorted(in_db - indexed), sorted(indexed - in_db))
        return in_db
    finally:
        engine.dispose()


@pytest.mark.slow
@pytest.mark.parametrize("store", ["faiss", "pgvector"])
def test_sigkill_during_ingest_loses_no_acknowledged_frame(
    tmp_path: Path, pipeline, store: str, request: pytest.FixtureRequest
) -> None:  # type: ignore[no-untyped-def]
    data_dir = tmp_path / "data"
    db = {}
    if store == "pgvector":  # the database outlives the server: its own process
        db = {"database_url": request.getfixturevalue("pgvector_url"), "vector_store": store}
    env = {
        "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
        "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
        **{f"LOOPNET_{name.upper()}": value for name, value in db.items()},
    }
    server = LiveServer(data_dir, env)
    images = [
        p.read_bytes() for p in sorted((DATA_DIR / "gardenspoint_cohog200" / "ref").iterdir())
    ]
    rng = random.Random(7)
    server.start()
    assert httpx.post(f"{server.url}/v1/atlases", json={"name": ATLAS}).status_code == 201
    assert httpx.post(f"{server.url}/v1/atlases/{ATLAS}/submaps", json={"name": "s0"}).is_success

    acked: set[int] = set()
    kills = 0
    for round_ in range(RESTARTS):
        if round_:
            server.start()
        with Robots(server.url, images) as robots:
            deadline = time.monotonic() + 120
            while len(robots.acknowledged()) < 1 + round_ % 3:  # some frames in every round
                assert time.monotonic() < deadline, f"no ingest acknowledged: {server.log()}"
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 1.5))  # then die at a random moment, mid-request
            server.kill()
            kills += 1
        assert robots.unexpected == []
        acked |= robots.acknowledged()
        in_db = check_data_dir(data_dir, acked, pipeline, **db)
        print(f"kill {kills}: {len(acked)} acknowledged, {len(in_db)} in the database")

    server.start()
    with httpx.Client(base_url=server.url, timeout=30) as client:
        for frame_id in sorted(acked):
            assert client.get(f"/v1/atlases/{ATLAS}/frames/{frame_id}").status_code == 200
    server.stop()  # graceful: the caught-up index is written
    if store == "pgvector":  # no file: the table is the index
        check_data_dir(data_dir, acked, pipeline, **db)
        assert kills == RESTARTS
        return
    index = AtlasIndex.load(
        data_dir / "indexes" / "atlas-1-v1.faiss", dim=pipeline.heads_config().fused_dim
    )
    assert acked <= set(index.ids().tolist()) == in_db
    assert kills == RESTARTS
