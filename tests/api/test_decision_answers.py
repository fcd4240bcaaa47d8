"""The decision as the API answers it: a look-alike of another place refused, a small atlas
answering with its reason, every candidate of a small atlas verified."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night


def query(client: TestClient, image: bytes) -> dict:
    response = client.post(
        "/v1/atlases/campus/query", files={"image": ("q.jpg", image, "image/jpeg")}
    )
    assert response.status_code == 200, response.text
    return response.json()


def test_a_look_alike_of_another_place_is_refused(client: TestClient) -> None:
    """Gardens Point 0-4 mapped by day; night frame 9 (another place, ~50 m further on the
    route) looks alike to the embeddings (cosine high, as every frame of this campus is)
    but not to the geometry: no loop, and the answer says the inliers failed."""
    create_atlas(client, "campus", ("day",))
    for i in range(5):
        add_frame(client, gardens_point_day_night(i, "query"), submap="day")
    answer = query(client, gardens_point_day_night(9, "ref"))
    assert answer["match"]["similarity"] > 0.8  # a high cosine
    assert answer["loop_closure"] is False and answer["status"] != "loop"
    decision = answer["decision"]
    assert decision["passed"] is False and decision["failed"] is not None
    assert decision["loop_probability"] < decision["threshold"]
    assert "below" in decision["reason"]


def test_a_small_atlas_answers_with_its_reason(client: TestClient) -> None:
    create_atlas(client, "campus", ("day",))
    for i in (2, 3, 4):
        add_frame(client, gardens_point_day_night(i, "query"), submap="day")
    same = query(client, gardens_point_day_night(3, "query"))
    decision = same["decision"]
    assert same["verification"]["verified_candidates"] == 3  # all of a small atlas
    assert decision["loop_probability"] is not None and decision["loop_probability"] > 0.98
    assert same["status"] == "loop" and decision["passed"] is True
    assert "not calibrated yet" in decision["reason"]  # why the score part is missing
    assert set(decision["contributions"]) >= {"inliers", "inlier_ratio"}
