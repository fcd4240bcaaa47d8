"""Small uploads that decode huge, sent to a real ``loopnet serve``: its peak memory stays
bounded (read from /proc, reset before the bombs).

Issue 24: a 128 KB PNG of 6300 x 6300 (under the 40 MP limit) cost about 1.4 GB per request;
4 at once peaked at 3.6 GB. Decodes are now shrunk to what the networks use and held within
one budget (``benchmarks/bomb_memory.py`` measures the same with the fast preset and more
kinds)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from tests.processes import peak_rss_bytes, reset_peak_rss, served_process, service_env
from tests.reliability.uploads import solid_image

pytestmark = pytest.mark.slow  # a real server with its CNNs

MB = 1024 * 1024


def test_concurrent_pixel_bombs_keep_the_server_within_bounds(tmp_path: Path) -> None:
    bomb = solid_image(6300, 6300, "RGB", "PNG")
    assert len(bomb) < 256 * 1024
    env = service_env(tmp_path / "data", LOOPNET_INFERENCE_WORKERS="2")
    with served_process(env) as (url, server), httpx.Client(base_url=url, timeout=120) as http:
        assert http.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert http.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201

        def post() -> httpx.Response:
            return http.post(
                "/v1/atlases/campus/frames",
                data={"submap": "s0", "robot_id": "r1"},
                files={"image": ("bomb.png", bomb, "image/png")},
            )

        assert post().status_code == 201  # warm: the CNNs' first-call buffers are in place
        reset_peak_rss(server.pid)
        before = peak_rss_bytes(server.pid)
        with ThreadPoolExecutor(4) as pool:
            answers = list(pool.map(lambda _: post(), range(4)))
        rise = peak_rss_bytes(server.pid) - before
    assert [a.status_code for a in answers] == [201] * 4, answers[0].text
    assert {(a.json()["width"], a.json()["height"]) for a in answers} == {(6300, 6300)}
    assert rise < 700 * MB, f"4 bombs raised the server by {rise / MB:.0f} MB"
