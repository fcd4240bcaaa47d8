"""The decision as the API answers it: a look-alike of another place refused, a small atlas
answering with its reason, every candidate of a small atlas verified, a rival place verified
when the best candidates all show one place."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.app.decision import SMALL_ATLAS_FRAMES
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import DATA_DIR, gardens_point_day_night


def query(client: TestClient, image: bytes, **fields: str) -> dict:
    response = client.post(
        "/v1/atlases/campus/query",
        data=fields,
        files={"image": ("q.jpg", image, "image/jpeg")},
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
    assert same["status"] == "loop" and decision["passed"] is True and decision["closable"] is True
    assert "not calibrated yet" in decision["reason"]  # why the score part is missing
    assert set(decision["contributions"]) >= {"inliers", "inlier_ratio"}


def cohog_reference(index: int) -> bytes:
    return (DATA_DIR / "gardenspoint_cohog200" / "ref" / f"{index:04d}.png").read_bytes()


def test_a_rival_place_is_verified_when_the_best_candidates_all_show_one(
    client: TestClient,
) -> None:
    """Above a small atlas only the top 5 are verified. Here they are five robots' frames of
    one spot in one submap (one place: none is the others' rival), so without more the
    decision would have no rival to weigh; the most similar frame of another place is
    verified as well and its inliers enter the rival part."""
    create_atlas(client, "campus", ("spot", "route"))
    spot = cohog_reference(10)
    for robot in range(5):
        add_frame(client, spot, submap="spot", robot=f"r{robot}")
    for index in range(40, 40 + SMALL_ATLAS_FRAMES - 4):  # 33 frames: not a small atlas
        add_frame(client, cohog_reference(index), submap="route", robot="mapper")
    answer = query(client, spot, k="10")
    assert answer["verification"]["verified_candidates"] == 6
    assert answer["match"]["submap"] == "spot"
    verified_elsewhere = [
        c for c in answer["candidates"] if c["submap"] == "route" and c["inliers"] is not None
    ]
    assert len(verified_elsewhere) == 1
    decision = answer["decision"]
    assert "rival" in decision["parts"] and decision["contributions"]["rival"] > 0
    assert answer["status"] == "loop"
