from __future__ import annotations

from fastapi.testclient import TestClient

from tests.api.helpers import add_frame, create_atlas


def test_health_ready_and_openapi(client: TestClient) -> None:
    assert client.get("/v1/health").json() == {"status": "ok"}
    ready = client.get("/v1/ready").json()
    assert (
        ready["ready"] and ready["backbone"] == "mobilenetv2" and ready["local_extractor"] == "disk"
    )
    spec = client.get("/openapi.json").json()
    assert "/v1/atlases/{atlas}/query" in spec["paths"]
    assert client.get("/docs").status_code == 200


def test_create_list_get_delete_atlas(client: TestClient) -> None:
    created = client.post("/v1/atlases", json={"name": "campus", "description": "QUT"})
    assert created.status_code == 201
    body = created.json()
    assert body["frames"] == 0 and body["active_model_version"] == 1
    assert body["classifier_trained"] is False
    assert body["feature_signature"]["local"]["name"] == "disk"
    assert [a["name"] for a in client.get("/v1/atlases").json()] == ["campus"]
    assert client.get("/v1/atlases/campus").json()["description"] == "QUT"
    assert client.delete("/v1/atlases/campus").status_code == 204
    assert client.get("/v1/atlases/campus").status_code == 404
    assert client.get("/v1/atlases").json() == []


def test_duplicate_atlas_is_a_conflict(client: TestClient) -> None:
    create_atlas(client)
    response = client.post("/v1/atlases", json={"name": "campus"})
    assert response.status_code == 409 and "already exists" in response.json()["detail"]


def test_bad_atlas_name(client: TestClient) -> None:
    response = client.post("/v1/atlases", json={"name": "../etc"})
    assert response.status_code == 422


def test_unknown_atlas_is_404_with_its_name(client: TestClient) -> None:
    for response in (
        client.get("/v1/atlases/nowhere"),
        client.delete("/v1/atlases/nowhere"),
        client.get("/v1/atlases/nowhere/submaps"),
        client.post("/v1/atlases/nowhere/submaps", json={"name": "s"}),
    ):
        assert response.status_code == 404
        assert response.json() == {"detail": "atlas 'nowhere' does not exist", "error": "NotFound"}


def test_submaps_with_frame_counts(client: TestClient, day_image: bytes) -> None:
    create_atlas(client, submaps=("a", "b"))
    add_frame(client, day_image, submap="b")
    listed = client.get("/v1/atlases/campus/submaps").json()
    assert [(s["name"], s["frames"]) for s in listed] == [("a", 0), ("b", 1)]
    duplicate = client.post("/v1/atlases/campus/submaps", json={"name": "a"})
    assert duplicate.status_code == 409


def test_model_versions_list_the_untrained_initial_version(client: TestClient) -> None:
    create_atlas(client)
    versions = client.get("/v1/atlases/campus/models").json()
    assert len(versions) == 1
    assert versions[0]["version"] == 1 and versions[0]["is_active"] and not versions[0]["trained"]
    assert versions[0]["config"]["heads"]["alpha"] == 0.7


def test_deleting_an_atlas_removes_its_frames_and_index(
    client: TestClient, day_image: bytes
) -> None:
    create_atlas(client)
    add_frame(client, day_image)
    client.post("/v1/atlases/campus/query", files={"image": ("q.jpg", day_image)})
    assert client.delete("/v1/atlases/campus").status_code == 204
    create_atlas(client)  # same name again: a fresh, empty atlas
    assert client.get("/v1/atlases/campus").json()["frames"] == 0
    answer = client.post("/v1/atlases/campus/query", files={"image": ("q.jpg", day_image)})
    assert answer.json()["candidates"] == []
