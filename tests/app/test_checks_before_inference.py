"""A request naming something that does not exist, or a value out of range, is refused before
any CNN runs: the extractor is never called and nothing is written."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from tests.api.helpers import add_frame, create_atlas, stored_state
from tests.conftest import gardens_point_day_night


@pytest.fixture
def counted(client: TestClient, pipeline, monkeypatch) -> Iterator[tuple[TestClient, list[int]]]:  # type: ignore[no-untyped-def]
    """The client, and a list that grows by one each time the CNNs run."""
    create_atlas(client, submaps=("s0",))
    add_frame(client, gardens_point_day_night(0, "ref"))
    calls: list[int] = []
    extract = pipeline.extract

    def counting(rgb):  # type: ignore[no-untyped-def]
        calls.append(1)
        return extract(rgb)

    monkeypatch.setattr(pipeline, "extract", counting)
    yield client, calls


def post(client: TestClient, route: str, **fields: str):  # type: ignore[no-untyped-def]
    return client.post(
        f"/v1/atlases/{route}",
        data=fields,
        files={"image": ("f.jpg", gardens_point_day_night(1, "query"), "image/jpeg")},
    )


@pytest.mark.parametrize(
    ("route", "fields", "status"),
    [
        ("campus/query", {"submap": "nowhere"}, 404),
        ("campus/observe", {"submap": "s0", "robot_id": "r1", "submap_filter": "nowhere"}, 404),
        ("campus/observe", {"submap": "nowhere", "robot_id": "r1"}, 404),
        ("elsewhere/query", {}, 404),
        ("campus/frames", {"submap": "nowhere", "robot_id": "r1"}, 404),
        ("campus/query", {"robot_id": "bad name!"}, 422),
        ("campus/query", {"robot_id": "r1", "exclude_recent_frames": str(2**63)}, 422),
        ("campus/query", {"robot_id": "r1", "exclude_recent_frames": str(2**70)}, 422),
        (
            "campus/observe",
            {"submap": "s0", "robot_id": "r1", "exclude_recent_frames": str(2**63)},
            422,
        ),
        ("campus/query", {"k": str(2**64)}, 422),
        ("campus/query", {"since": "5", "until": "1"}, 422),
        ("campus/query", {"robots": "own"}, 422),
    ],
)
def test_refused_before_the_cnns_run(
    counted: tuple[TestClient, list[int]], route: str, fields: dict[str, str], status: int
) -> None:
    client, calls = counted
    before = stored_state(client)
    response = post(client, route, **fields)
    assert response.status_code == status, response.text
    assert calls == []
    assert stored_state(client) == before


def test_a_good_query_runs_the_cnns_once(counted: tuple[TestClient, list[int]]) -> None:
    client, calls = counted
    response = post(client, "campus/query", robot_id="r2", submap="s0", exclude_recent_frames="3")
    assert response.status_code == 200, response.text
    assert len(calls) == 1
