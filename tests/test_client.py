"""``LoopNetClient`` against a real ``loopnet serve`` process over real HTTP."""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path

import httpx
import pytest
from PIL import Image

from service.client import LoopNetClient, LoopNetError, retry_after
from tests.conftest import DATA_DIR
from tests.processes import create_token, service_env, serving

COHOG = DATA_DIR / "gardenspoint_cohog200"
PLACES = (0, 50, 100, 150)  # far apart along the route: no two look alike


def cohog(place: int, side: str) -> Path:
    rows = list(csv.DictReader((COHOG / "gt.csv").open()))
    return COHOG / rows[place][side]


@pytest.mark.slow
def test_client_drives_a_real_server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = tmp_path / "data"
    admin = create_token(data, "ops", "admin")
    env = service_env(data, LOOPNET_AUTH="required")
    with serving(env, wait=False) as url:
        # the service answers 503 + Retry-After while it loads: the client waits and retries
        monkeypatch.setenv("LOOPNET_API_KEY", admin)  # the key from the environment
        with LoopNetClient(url, retries=120) as loopnet:
            started = time.monotonic()
            assert _until_listening(url) and loopnet.ready().ready
            assert loopnet.whoami().role == "admin"
            assert time.monotonic() - started < 120

            loopnet.create_atlas("campus", "client test")
            for submap in ("s0", "s1"):
                loopnet.create_submap("campus", submap)
            frames = [
                loopnet.add_frame(
                    "campus",
                    cohog(place, "ref"),
                    submap=f"s{i % 2}",
                    robot_id="husky-1",
                    timestamp=float(i),
                    pose={"rotation": [1, 0, 0, 0], "translation": [i, 0, 0]},
                    intrinsics={"fx": 100.0, "fy": 100.0, "cx": 50.0, "cy": 28.0},
                )
                for i, place in enumerate(PLACES)
            ]
            assert [f.frame_id for f in loopnet.list_frames("campus", robot="husky-1")] == [
                f.frame_id for f in frames
            ]
            assert frames[2].pose is not None and frames[2].pose.translation == [2, 0, 0]
            assert loopnet.get_atlas("campus").frames == 4
            assert [s.frames for s in loopnet.list_submaps("campus")] == [2, 2]
            assert loopnet.list_robots("campus")[0].frames == 4
            thumb = Image.open(io.BytesIO(loopnet.thumbnail("campus", frames[0].frame_id)))
            assert thumb.format == "JPEG" and max(thumb.size) <= 192  # never enlarged

            answer = loopnet.query("campus", cohog(PLACES[2], "query"), k=2)
            assert answer.match is not None and answer.match.frame_id == frames[2].frame_id
            observed = loopnet.observe(
                "campus", cohog(PLACES[3], "query"), submap="s1", robot_id="husky-2", timestamp=10.0
            )
            assert observed.match is not None and observed.match.frame_id == frames[3].frame_id
            closures = loopnet.loop_closures("campus")
            if observed.loop_closure:  # inter-robot: husky-2 recognised husky-1's place
                detail = loopnet.loop_closure("campus", closures[0].id)
                assert detail.frame.frame_id == frames[3].frame_id and detail.query_thumbnail

            assert [v.version for v in loopnet.list_models("campus")] == [1]
            assert loopnet.activate_model("campus", 1).is_active
            job = loopnet.submit_job("campus", shots=1, epochs=5, embed_dim=16)
            assert loopnet.get_job("campus", job.id).status == "queued"
            assert loopnet.cancel_job("campus", job.id).status == "cancelled"  # no worker here
            assert [j.id for j in loopnet.list_jobs("campus")] == [job.id]

            robot = loopnet.create_key("husky-1", "robot", ["campus"])
            assert robot.token.startswith("lnk_")
            assert robot.id in {k.id for k in loopnet.list_keys()}
            with LoopNetClient(url, api_key=robot.token) as as_robot:
                assert as_robot.whoami().role == "robot"
                with pytest.raises(LoopNetError) as denied:
                    as_robot.list_keys()
                assert denied.value.status == 403
            assert loopnet.revoke_key(robot.id).revoked_at is not None
            with (
                LoopNetClient(url, api_key=robot.token) as revoked,
                pytest.raises(LoopNetError) as e,
            ):
                revoked.list_atlases()
            assert e.value.status == 401

            with pytest.raises(LoopNetError) as missing:
                loopnet.get_atlas("nowhere")
            assert missing.value.status == 404 and "does not exist" in missing.value.detail
            loopnet.delete_atlas("campus")
            assert loopnet.list_atlases() == []


def _until_listening(url: str, timeout: float = 60) -> bool:
    """The client retries HTTP answers; before the port opens there is no answer to retry."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            httpx.get(f"{url}/v1/health")
            return True
        except httpx.TransportError:
            time.sleep(0.2)
    return False


def test_retry_after_is_honoured_and_capped() -> None:
    def answer(headers: dict[str, str]) -> httpx.Response:
        return httpx.Response(503, headers=headers)

    assert retry_after(answer({"Retry-After": "3"}), attempt=0) == 3.0
    assert retry_after(answer({"Retry-After": "7200"}), attempt=0) == 60.0
    assert retry_after(answer({}), attempt=0) == 0.5  # no header: exponential back-off
    assert retry_after(answer({}), attempt=3) == 4.0
