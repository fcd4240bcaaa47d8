"""The inference gate: bounded slots and queue, 503 + Retry-After beyond them, a free event loop."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient

from service.concurrency import InferenceGate
from service.errors import Overloaded
from tests.api.helpers import create_atlas, stored_state
from tests.conftest import gardens_point_day_night, make_settings, wait_ready


def wait_until(condition, timeout: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.01)


# ----- the gate on its own ----------------------------------------------------------------


def test_gate_admits_workers_queues_fifo_and_refuses_the_rest() -> None:
    gate = InferenceGate(workers=2, queue=2, wait_timeout_s=10)
    release = threading.Event()
    order: list[int] = []

    def hold(i: int) -> None:
        with gate.slot():
            order.append(i)
            release.wait()

    with ThreadPoolExecutor(4) as pool:
        running = [pool.submit(hold, i) for i in (0, 1)]
        wait_until(lambda: gate.stats().running == 2)
        queued = []
        for i in (2, 3):
            queued.append(pool.submit(hold, i))
            wait_until(lambda n=i - 1: gate.stats().waiting == n)
        with pytest.raises(Overloaded) as refused, gate.slot():
            pass
        assert "2 running and 2 waiting" in str(refused.value)
        assert refused.value.retry_after_s >= 1
        release.set()
        for future in running + queued:
            future.result(timeout=10)
    assert order[2:] == [2, 3]  # the queue is served first come, first served
    stats = gate.stats()
    assert (stats.running, stats.waiting, stats.admitted, stats.refused) == (0, 0, 4, 1)
    assert stats.mean_inference_ms is not None and stats.mean_inference_ms > 0


def test_gate_refuses_a_waiter_after_its_timeout() -> None:
    gate = InferenceGate(workers=1, queue=1, wait_timeout_s=0.2)
    with gate.slot():
        start = time.monotonic()
        with pytest.raises(Overloaded, match="within 0.2 s"), gate.slot():
            pass
        assert time.monotonic() - start >= 0.2
    with gate.slot():  # a refused waiter leaves no trace in the queue
        assert gate.stats().waiting == 0


def test_gate_retry_after_grows_with_the_work_ahead() -> None:
    gate = InferenceGate(workers=1, queue=0, wait_timeout_s=1)
    for _ in range(3):
        with gate.slot():
            time.sleep(0.01)
    with gate.slot(), pytest.raises(Overloaded) as refused, gate.slot():
        pass
    assert refused.value.retry_after_s == 1  # ~10 ms of work ahead rounds up to one second
    slow = InferenceGate(workers=1, queue=0, wait_timeout_s=1)
    slow._mean_s = 2.5  # as after inferences of 2.5 s each
    with slow.slot(), pytest.raises(Overloaded) as refused, slow.slot():
        pass
    assert refused.value.retry_after_s == 3


def test_gate_rejects_nonsense_limits() -> None:
    with pytest.raises(ValueError, match="workers >= 1"):
        InferenceGate(workers=0, queue=1, wait_timeout_s=1)


# ----- through the API --------------------------------------------------------------------


@pytest.fixture
def tight_client(tmp_path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """An app with one inference slot and one waiting place."""
    from service.api.app import create_app

    settings = make_settings(tmp_path, inference_workers=1, inference_queue=1)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client)
        yield client


def post_frame(client: TestClient, image: bytes):  # type: ignore[no-untyped-def]
    return client.post(
        "/v1/atlases/campus/frames",
        data={"submap": "s0", "robot_id": "r1"},
        files={"image": ("f.jpg", image, "image/jpeg")},
    )


def test_saturated_inference_answers_503_with_retry_after_and_writes_nothing(
    tight_client: TestClient,
) -> None:
    gate = tight_client.app.state.runtime.service.inference  # type: ignore[attr-defined]
    image = gardens_point_day_night(0, "ref")
    before = stored_state(tight_client)
    with ThreadPoolExecutor(1) as pool:
        with gate.slot():  # the one slot is busy
            waiting = pool.submit(post_frame, tight_client, image)
            wait_until(lambda: gate.stats().waiting == 1)  # the one queue place is taken
            refused = post_frame(tight_client, image)
            query = tight_client.post(
                "/v1/atlases/campus/query", files={"image": ("q.jpg", image, "image/jpeg")}
            )
            assert stored_state(tight_client) == before
        assert waiting.result(timeout=60).status_code == 201
    for response in (refused, query):
        assert response.status_code == 503
        assert int(response.headers["Retry-After"]) >= 1
        body = response.json()
        assert body["error"] == "Overloaded" and "saturated" in body["detail"]
    assert stored_state(tight_client)["frames"] == before["frames"] + 1


def test_health_answers_fast_while_inference_is_saturated(tight_client: TestClient) -> None:
    gate = tight_client.app.state.runtime.service.inference  # type: ignore[attr-defined]
    image = gardens_point_day_night(0, "ref")
    with ThreadPoolExecutor(1) as pool, gate.slot():
        waiting = pool.submit(post_frame, tight_client, image)
        wait_until(lambda: gate.stats().waiting == 1)
        start = time.perf_counter()
        health = tight_client.get("/v1/health")
        elapsed = time.perf_counter() - start
        # the slot stays held by this test: a health check that waited for inference would
        # never come back; the bound only keeps a slow machine from hiding a stall
        assert health.status_code == 200 and elapsed < 5.0
        atlases = tight_client.get("/v1/atlases")  # a database read is not held up either
        assert atlases.status_code == 200
    assert waiting.result(timeout=60).status_code == 201
