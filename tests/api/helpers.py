"""Helpers for API tests: set-up calls and a snapshot of everything a write could touch."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service.storage.models import Frame, FrameFeatureRow, Submap


def create_atlas(
    client: TestClient, atlas: str = "campus", submaps: tuple[str, ...] = ("s0",)
) -> None:
    assert client.post("/v1/atlases", json={"name": atlas}).status_code == 201
    for name in submaps:
        response = client.post(f"/v1/atlases/{atlas}/submaps", json={"name": name})
        assert response.status_code == 201, response.text


def add_frame(
    client: TestClient,
    image: bytes,
    *,
    atlas: str = "campus",
    submap: str = "s0",
    robot: str = "r1",
    **fields: str,
) -> dict:
    response = client.post(
        f"/v1/atlases/{atlas}/frames",
        data={"submap": submap, "robot_id": robot, **fields},
        files={"image": ("frame.jpg", image, "image/jpeg")},
    )
    assert response.status_code == 201, response.text
    return response.json()


def stored_state(client: TestClient) -> dict[str, int]:
    """Row counts and index sizes: equal before and after a rejected request."""
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:
        state = {
            "frames": session.scalar(select(func.count(Frame.id))),
            "features": session.scalar(select(func.count(FrameFeatureRow.frame_id))),
            "submaps": session.scalar(select(func.count(Submap.id))),
        }
    state["indexed"] = sum(s.index.size for s in service._loaded.values())
    return state
