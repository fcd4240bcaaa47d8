"""GET /metrics after real traffic: every series an operator's dashboard reads, with sane values."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from service.api.app import create_app
from service.fleet.keys import KeyAdmin, Role
from service.storage import jobs
from service.storage.db import transaction
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night, make_settings, wait_ready

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def scrape(client: TestClient) -> Samples:
    response = client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(response.text)
        for s in family.samples
    }


def value(samples: Samples, name: str, **labels: str) -> float:
    return samples[(name, frozenset(labels.items()))]


@pytest.fixture
def gated_client(tmp_path, pipeline) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """One inference slot and no queue, so a held slot makes the next inference a 503."""
    settings = make_settings(
        tmp_path / "data", inference_workers=1, inference_queue=0, sync_seconds=0.1
    )
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        yield client


def test_metrics_after_traffic(gated_client: TestClient) -> None:
    client = gated_client
    before = scrape(client)
    create_atlas(client, submaps=("s0", "s1"))
    for i in range(3):
        add_frame(client, gardens_point_day_night(i, "ref"), submap=f"s{i % 2}")
    image = {"image": ("q.jpg", gardens_point_day_night(1, "query"), "image/jpeg")}
    assert client.post("/v1/atlases/campus/query", files=image).status_code == 200
    assert client.get("/v1/atlases/nowhere").status_code == 404
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.inference.slot():  # every slot busy, no queue: the gate refuses
        assert client.post("/v1/atlases/campus/query", files=image).status_code == 503
    with transaction(service.sessions) as session:  # a job as a worker leaves it
        job = jobs.create_job(session, atlas_id=1, kind="retrain", params={})
        job_id = job.id
    with transaction(service.sessions) as session:
        jobs.start_job(session, job_id=job_id)
    time.sleep(0.05)
    with transaction(service.sessions) as session:
        job = jobs.get_job(session, job_id=job_id)
        jobs.finish_job(session, job=job, status="succeeded", message="done")
    time.sleep(0.3)  # the change feed follower runs every 0.1 s
    after = scrape(client)

    def grew(name: str, by: float = 1, **labels: str) -> None:
        old = before.get((name, frozenset(labels.items())), 0.0)
        assert value(after, name, **labels) - old >= by, (name, labels)

    # request latency by route template and status
    query = {"method": "POST", "route": "/v1/atlases/{atlas}/query"}
    grew("loopnet_http_request_duration_seconds_count", 1, **query, status="200")
    grew("loopnet_http_request_duration_seconds_count", 1, **query, status="503")
    grew(
        "loopnet_http_request_duration_seconds_count",
        3,
        method="POST",
        route="/v1/atlases/{atlas}/frames",
        status="201",
    )
    grew(
        "loopnet_http_request_duration_seconds_count",
        1,
        method="GET",
        route="/v1/atlases/{atlas}",
        status="404",
    )
    slow = value(after, "loopnet_http_request_duration_seconds_sum", **query, status="200")
    assert 0.01 < slow < 60  # a real CNN pass: tens of ms at least
    assert not any("nowhere" in str(labels) for _, labels in after)  # templates, never paths
    # inference stages
    for stage in ("decode", "local_features", "global_features", "heads", "search"):
        grew("loopnet_inference_stage_seconds_count", 1, stage=stage)
    assert value(after, "loopnet_inference_stage_seconds_sum", stage="local_features") > 0.005
    # admission gate: depth, wait and the refusal
    assert value(after, "loopnet_admission_queue_depth") == 0
    assert value(after, "loopnet_admission_slots") == 1
    assert value(after, "loopnet_admission_refused_total") == 1
    grew("loopnet_admission_wait_seconds_count", 5)
    # index size per atlas, change feed
    assert value(after, "loopnet_index_frames", atlas="campus") == 3
    assert value(after, "loopnet_change_feed_revisions_behind", atlas="campus") == 0
    assert 0 <= value(after, "loopnet_change_feed_sync_age_seconds") < 5
    # jobs by state and duration
    assert value(after, "loopnet_jobs", kind="retrain", state="succeeded") == 1
    assert (
        value(after, "loopnet_job_duration_seconds_count", kind="retrain", state="succeeded") == 1
    )
    assert (
        0 < value(after, "loopnet_job_duration_seconds_sum", kind="retrain", state="succeeded") < 5
    )
    assert value(after, "loopnet_ready") == 1


def test_metrics_can_require_an_operator_key(tmp_path, pipeline) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", metrics_public=False, auth="required")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        assert client.get("/metrics").status_code == 401
        sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
        robot = KeyAdmin(sessions).issue(name="r", role=Role.robot, atlases=[]).token
        operator = KeyAdmin(sessions).issue(name="o", role=Role.operator, atlases=[]).token
        assert client.get("/metrics", headers={"X-API-Key": robot}).status_code == 403
        answer = client.get("/metrics", headers={"X-API-Key": operator})
        assert answer.status_code == 200
        assert "loopnet_ready" in answer.text


def series(client: TestClient, **headers: str) -> set[tuple[str, frozenset[tuple[str, str]]]]:
    response = client.get("/metrics", headers=headers)
    assert response.status_code == 200
    return {
        (s.name, frozenset(s.labels.items()))
        for family in text_string_to_metric_families(response.text)
        for s in family.samples
    }


def test_series_stay_bounded_whatever_clients_send(client: TestClient) -> None:
    """Issue 24: a method label took any token a client sent, so 300 keyless requests with
    2,000-character methods grew /metrics to 11.5 MB. Random methods, paths, robot ids and atlas
    names now only ever land on the closed sets of labels."""
    import random
    import string

    from service.metrics import HTTP_METHODS, OTHER_METHOD

    # the registry is the process's: earlier tests' series are in it too, so what this test's
    # traffic adds is measured (alone, 450 requests add about 45 kB; issue 24 added 11.5 MB)
    at_start = len(client.get("/metrics").content)
    create_atlas(client)
    rng = random.Random(24)

    def token(length: int) -> str:
        return "".join(rng.choices(string.ascii_letters + string.digits + "-_", k=length))

    def hostile_requests(count: int) -> None:
        for _ in range(count):
            method = rng.choice(["GET", "POST", "DELETE", token(rng.randint(1, 2000)).upper()])
            path = rng.choice(
                [
                    f"/v1/atlases/{token(rng.randint(1, 60))}",
                    f"/v1/atlases/campus/frames?robot_id={token(40)}",
                    f"/v1/atlases/{token(12)}/query?robot={token(30)}",
                    f"/{token(rng.randint(1, 300))}/{token(8)}",
                    f"/console/{token(20)}.js",
                    f"/v1/atlases/{token(10)}/",
                ]
            )
            client.request(method, path)

    hostile_requests(150)
    first = series(client)
    hostile_requests(300)
    second = series(client)
    templates = set(client.app.openapi()["paths"]) | {"unmatched", "/console", "/metrics"}
    http = [labels for name, labels in second if name.startswith("loopnet_http_request")]
    for labels in map(dict, http):
        assert labels["method"] in HTTP_METHODS | {OTHER_METHOD}, labels["method"][:40]
        assert labels["route"] in templates or labels["route"].startswith("/"), labels
        assert len(labels["route"]) < 100
    # the second, larger batch met only series the first had made (or a handful more)
    assert len(second - first) <= 30, sorted(second - first)[:5]
    assert len(client.get("/metrics").content) - at_start < 100_000


def test_public_metrics_name_no_atlas_without_a_key(tmp_path, pipeline) -> None:  # type: ignore[no-untyped-def]
    """Issue 24: public /metrics listed every atlas name to anyone; without a key it now gives
    the index figures as totals, per atlas only to a caller showing a valid key."""
    settings = make_settings(tmp_path / "data", auth="required")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
        admin = KeyAdmin(sessions).issue(name="a", role=Role.admin, atlases=[]).token
        key = {"X-API-Key": admin}
        for name in ("secret-site", "other-site"):
            assert client.post("/v1/atlases", json={"name": name}, headers=key).status_code == 201
        client.app.state.runtime.service.load_all()  # type: ignore[attr-defined]
        anonymous = client.get("/metrics")
        assert anonymous.status_code == 200
        assert "secret-site" not in anonymous.text and "other-site" not in anonymous.text
        samples = {(n, labels) for n, labels in series(client)}
        assert ("loopnet_index_frames", frozenset()) in samples
        assert ("loopnet_atlases_served", frozenset()) in samples
        wrong = client.get("/metrics", headers={"X-API-Key": "lnk_wrong"})
        assert "secret-site" not in wrong.text
        named = series(client, **key)
        assert ("loopnet_index_frames", frozenset({("atlas", "secret-site")})) in named
        robot = KeyAdmin(sessions).issue(name="r", role=Role.robot, atlases=["other-site"]).token
        scoped = client.get("/metrics", headers={"X-API-Key": robot}).text
        assert 'atlas="other-site"' in scoped and "secret-site" not in scoped
