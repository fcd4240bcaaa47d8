"""Several API processes on one PostgreSQL atlas: each index follows the others' writes.

Two apps (each with its own in-memory indexes, as two processes would have) share one
PostgreSQL database and data directory; what one ingests or deletes, and a model version one activates, the
other serves within LOOPNET_SYNC_SECONDS.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.app.change_feed import ADD, changes_between, prune, record, revisions
from service.app.model_versions import initial_version_config
from service.config import Settings
from service.fleet.atlas_repair import activate_version
from service.storage import repository as repo
from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database
from service.storage.models import Atlas
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night, make_settings, wait_ready

SYNC_SECONDS = 0.2


def atlas_id_of(client: TestClient, atlas: str = "campus") -> int:
    with client.app.state.runtime.sessions() as session:  # type: ignore[attr-defined]
        return int(repo.get_atlas(session, name=atlas).id)


def indexed(client: TestClient, atlas: str = "campus") -> set[int]:
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    return set(service.loaded(atlas_id_of(client, atlas)).index.ids().tolist())


def within(seconds: float, condition: Callable[[], bool]) -> float:
    """Seconds until ``condition`` holds; fails after ``seconds``."""
    start = time.monotonic()
    while not condition():
        assert time.monotonic() - start < seconds, f"not within {seconds} s"
        time.sleep(0.01)
    return time.monotonic() - start


def _two_apps(settings: Settings, pipeline) -> Iterator[tuple[TestClient, TestClient]]:  # type: ignore[no-untyped-def]
    """Two API processes' apps on the same settings (one database), both ready."""
    with (
        TestClient(create_app(settings, pipeline=pipeline)) as one,
        TestClient(create_app(settings, pipeline=pipeline)) as two,
    ):
        wait_ready(one)
        wait_ready(two)
        yield one, two


@pytest.fixture
def two_apps(
    tmp_path: Path, postgres_url: str, pipeline
) -> Iterator[tuple[TestClient, TestClient]]:  # type: ignore[no-untyped-def]
    settings = make_settings(
        tmp_path / "data", database_url=postgres_url, sync_seconds=SYNC_SECONDS
    )
    yield from _two_apps(settings, pipeline)


@pytest.fixture(params=["faiss", "pgvector"])
def two_apps_each_store(
    request: pytest.FixtureRequest, tmp_path: Path, pipeline
) -> Iterator[tuple[TestClient, TestClient]]:  # type: ignore[no-untyped-def]
    """Two apps on one PostgreSQL database, with each vector store: FAISS (the machine's
    PostgreSQL) and pgvector (the embedded one, see tests/services.py)."""
    store = request.param
    url = request.getfixturevalue("postgres_url" if store == "faiss" else "pgvector_url")
    settings = make_settings(
        tmp_path / "data", database_url=url, sync_seconds=SYNC_SECONDS, vector_store=store
    )
    yield from _two_apps(settings, pipeline)


def test_frames_and_deletions_reach_the_other_process(
    two_apps_each_store: tuple[TestClient, TestClient],
) -> None:
    one, two = two_apps_each_store
    create_atlas(one, submaps=("s0", "s1"))
    assert indexed(two) == set()
    frames = [
        add_frame(one, gardens_point_day_night(i, "ref"), submap=f"s{i % 2}", robot="robot-a")
        for i in range(4)
    ]
    ids = {f["frame_id"] for f in frames}
    delay = within(5 * SYNC_SECONDS + 2, lambda: indexed(two) == ids)
    print(f"frames visible in the other process after {delay:.3f} s")
    answer = two.post(
        "/v1/atlases/campus/query",
        data={"k": "1"},
        files={"image": ("q.jpg", gardens_point_day_night(2, "ref"))},
    ).json()
    assert answer["match"]["frame_id"] == frames[2]["frame_id"]
    assert answer["match"]["robot_id"] == "robot-a" and answer["match"]["similarity"] > 0.999

    assert two.delete(f"/v1/atlases/campus/frames/{frames[0]['frame_id']}").status_code == 204
    within(5 * SYNC_SECONDS + 2, lambda: frames[0]["frame_id"] not in indexed(one))
    assert one.delete("/v1/atlases/campus/submaps/s1").status_code == 204
    within(5 * SYNC_SECONDS + 2, lambda: indexed(two) == {frames[2]["frame_id"]})
    assert indexed(one) == {frames[2]["frame_id"]}
    assert [s["name"] for s in two.get("/v1/atlases/campus/submaps").json()] == ["s0"]

    service_two = two.app.state.runtime.service  # type: ignore[attr-defined]
    assert service_two._loaded
    assert one.delete("/v1/atlases/campus").status_code == 204
    within(5 * SYNC_SECONDS + 2, lambda: not service_two._loaded)
    assert two.get("/v1/atlases/campus").status_code == 404


def test_revisions_follow_commit_order_not_id_order(postgres_url: str) -> None:
    """A transaction that logs a change holds the atlas row until it commits, so a later one
    cannot publish revision r + 1 while revision r is still invisible."""
    upgrade_database(postgres_url)
    engine = make_engine(postgres_url)
    sessions = make_session_factory(engine)
    with sessions.begin() as session:
        atlas = Atlas(name="a", description="", feature_signature={})
        session.add(atlas)
        session.flush()
        atlas_id = atlas.id

    first = sessions()
    first.begin()
    first_revision = record(first, atlas_id=atlas_id, op=ADD, frame_ids=[1])
    second_revision: list[int] = []

    def second_transaction() -> None:
        with sessions.begin() as session:
            second_revision.append(record(session, atlas_id=atlas_id, op=ADD, frame_ids=[2]))

    thread = threading.Thread(target=second_transaction)
    thread.start()
    thread.join(timeout=1.0)
    assert thread.is_alive() and not second_revision  # waits for the first to commit
    with sessions() as reader:
        assert changes_between(reader, atlas_id=atlas_id, after=0, upto=1).complete is False
    first.commit()
    first.close()
    thread.join(timeout=10)
    assert (first_revision, second_revision) == (1, [2])
    with sessions() as reader:
        changes = changes_between(reader, atlas_id=atlas_id, after=0, upto=2)
    assert changes.complete and changes.added == [1, 2]
    engine.dispose()


def test_a_process_behind_the_pruned_log_reconciles_everything(
    two_apps: tuple[TestClient, TestClient],
) -> None:
    one, two = two_apps
    create_atlas(one)
    first = add_frame(one, gardens_point_day_night(0, "ref"))["frame_id"]
    within(5 * SYNC_SECONDS + 2, lambda: indexed(two) == {first})
    runtime_two = two.app.state.runtime  # type: ignore[attr-defined]
    runtime_two._follower.stop()  # process two falls behind ...
    later = [add_frame(one, gardens_point_day_night(i, "ref"))["frame_id"] for i in (1, 2)]
    assert one.delete(f"/v1/atlases/campus/frames/{first}").status_code == 204
    with transaction(runtime_two.sessions) as session:  # ... past what the log still holds
        assert prune(session, older_than_seconds=-60) >= 3
    assert indexed(two) == {first}
    with runtime_two.sessions() as session:
        runtime_two.service.follow(revisions(session))
    assert indexed(two) == set(later)


def add_untrained_version(client: TestClient, atlas: str = "campus") -> int:
    """A second model version (untrained heads rebuilt from its config, no weights file)."""
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with transaction(service.sessions) as session:
        atlas_id = repo.get_atlas(session, name=atlas).id
        return repo.create_model_version(
            session,
            atlas_id=atlas_id,
            config=initial_version_config(service.pipeline.heads_config()),
            metrics={},
            weights_path=None,
            activate=False,
        ).version


def count_loads(client: TestClient) -> list[str]:
    """The names of the threads that load an atlas's state from now on."""
    states = client.app.state.runtime.service.states  # type: ignore[attr-defined]
    threads: list[str] = []
    load = states._load

    def counted(atlas_id: int):  # type: ignore[no-untyped-def]
        threads.append(threading.current_thread().name)
        return load(atlas_id)

    states._load = counted
    return threads


def serving(client: TestClient, atlas_id: int) -> int | None:
    """The model version a process holds in memory for an atlas (asks no request)."""
    state = client.app.state.runtime.service.states.current(atlas_id)  # type: ignore[attr-defined]
    return None if state is None else state.model_version


def test_an_activation_reaches_every_process_through_its_follower(
    two_apps_each_store: tuple[TestClient, TestClient],
) -> None:
    """Activating a version (API, then the offline CLI path for the rollback) is swapped in by
    each process's follower thread: an idle atlas too, and no request ever loads a model."""
    one, two = two_apps_each_store
    create_atlas(one)
    create_atlas(one, "idle")
    frame = add_frame(one, gardens_point_day_night(0, "ref"))["frame_id"]
    ids = {}
    for name in ("campus", "idle"):
        ids[name] = atlas_id_of(two, name)
        for client in (one, two):  # both processes hold both atlases in memory
            indexed(client, name)
        assert add_untrained_version(one, name) == 2
    loads = {"one": count_loads(one), "two": count_loads(two)}

    activated = one.post("/v1/atlases/campus/models/2/activate")
    assert activated.status_code == 200 and activated.json()["is_active"]
    assert one.post("/v1/atlases/idle/models/2/activate").status_code == 200
    for client in (one, two):
        delay = within(10 * SYNC_SECONDS + 5, lambda c=client: serving(c, ids["idle"]) == 2)
        within(10 * SYNC_SECONDS + 5, lambda c=client: serving(c, ids["campus"]) == 2)
        print(f"version 2 served after {delay:.3f} s")
    answer = two.post(
        "/v1/atlases/campus/query",
        data={"k": "1"},
        files={"image": ("q.jpg", gardens_point_day_night(0, "ref"))},
    ).json()
    assert answer["model_version"] == 2 and answer["match"]["frame_id"] == frame

    settings = one.app.state.runtime.settings  # type: ignore[attr-defined]
    activate_version(settings, one.app.state.runtime.sessions, "idle", 1)  # type: ignore[attr-defined]
    for client in (one, two):
        within(10 * SYNC_SECONDS + 5, lambda c=client: serving(c, ids["idle"]) == 1)
    assert serving(two, ids["campus"]) == 2
    assert indexed(two, "campus") == {frame}
    assert loads == {"one": ["loopnet-sync"] * 3, "two": ["loopnet-sync"] * 3}
