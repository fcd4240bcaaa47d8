"""The fleet topology without Docker: two real ``loopnet serve`` processes and a real
``loopnet worker`` on one PostgreSQL database, a Redis queue and one shared data directory.

Robot A ingests through process 1 and robot B finds it through process 2; a retraining job
submitted through process 2 makes process 1 serve the new version; a deletion through one
process reaches the other; wrong keys get 401 and 403.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.conftest import DATA_DIR, TEST_LONG_SIDE, TEST_MAX_KEYPOINTS
from tests.processes import free_port

LOOPNET = [sys.executable, "-m", "service.cli"]
SYNC_SECONDS = 0.25
QUICK_JOB = {"kind": "retrain", "params": {"shots": 2, "epochs": 30, "embed_dim": 32}}


def cohog(place: int, side: str = "ref") -> tuple[str, bytes]:
    root = DATA_DIR / "gardenspoint_cohog200"
    rows = list(csv.DictReader((root / "gt.csv").open()))
    path = root / rows[place][side]
    return path.name, path.read_bytes()


def eventually(seconds: float, check: Callable[[], Any]) -> tuple[Any, float]:
    """Call ``check`` until it returns something truthy; its value and the seconds it took."""
    start = time.monotonic()
    while True:
        value = check()
        if value:
            return value, time.monotonic() - start
        assert time.monotonic() - start < seconds, f"not within {seconds} s"
        time.sleep(0.05)


class Fleet:
    def __init__(self, env: dict[str, str]) -> None:
        self.env = env
        self.processes: list[subprocess.Popen[str]] = []
        self.urls: list[str] = []

    def start(self, *args: str) -> subprocess.Popen[str]:
        process = subprocess.Popen(
            [*LOOPNET, *args],
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.processes.append(process)
        return process

    def serve(self) -> httpx.Client:
        port = free_port()
        self.start("serve", "--port", str(port))
        url = f"http://127.0.0.1:{port}"
        self.urls.append(url)
        return httpx.Client(base_url=url + "/v1", timeout=120)

    def wait_ready(self, timeout: float = 240) -> None:
        deadline = time.monotonic() + timeout
        for url in self.urls:
            while True:
                try:
                    if httpx.get(f"{url}/v1/ready").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                for process in self.processes:
                    assert process.poll() is None, self.stop()
                assert time.monotonic() < deadline, self.stop()
                time.sleep(0.3)

    def stop(self) -> str:
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        logs = []
        for process in self.processes:
            try:
                output, _ = process.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                output, _ = process.communicate()
            logs.append(output[-3000:])
        return "\n-----\n".join(logs)


@pytest.fixture
def fleet_env(tmp_path: Path, postgres_url: str, redis_queue: dict[str, str]) -> dict[str, str]:
    return {
        **os.environ,
        **redis_queue,
        "LOOPNET_DATABASE_URL": postgres_url,
        "LOOPNET_DATA_DIR": str(tmp_path / "shared-data"),
        "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
        "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
        "LOOPNET_SYNC_SECONDS": str(SYNC_SECONDS),
        "LOOPNET_MODEL_POLL_SECONDS": str(SYNC_SECONDS),
        "LOOPNET_AUTH": "required",
        "LOOPNET_TORCH_THREADS": "1",
    }


@pytest.fixture
def fleet(fleet_env: dict[str, str]) -> Iterator[Fleet]:
    running = Fleet(fleet_env)
    try:
        yield running
    finally:
        running.stop()


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.mark.slow
def test_two_api_processes_and_a_worker_on_postgres_and_redis(
    fleet: Fleet, fleet_env: dict[str, str]
) -> None:
    # the operator's first key comes from the CLI, before anything runs
    made = subprocess.run(
        [*LOOPNET, "keys", "create", "--role", "admin", "--name", "ops-lead"],
        env=fleet_env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert made.returncode == 0, made.stderr
    admin = auth(json.loads(made.stdout)["token"])

    one, two = fleet.serve(), fleet.serve()
    worker = fleet.start("worker")
    fleet.wait_ready()
    assert one.get("/atlases").status_code == 401
    for name in ("campus", "elsewhere"):
        assert one.post("/atlases", json={"name": name}, headers=admin).status_code == 201

    def key(role: str, name: str, *atlases: str) -> dict[str, str]:
        body = {"name": name, "role": role, "atlases": list(atlases)}
        response = two.post("/keys", json=body, headers=admin)
        assert response.status_code == 201, response.text
        return auth(response.json()["token"])

    robot_a, robot_b = key("robot", "robot-a", "campus"), key("robot", "robot-b", "campus")
    outsider = key("robot", "robot-c", "elsewhere")
    operator = key("operator", "ops", "campus")

    # robot A maps two submaps through process 1
    frames: dict[int, int] = {}
    for submap, places in (("s0", (0, 1, 2)), ("s1", (10, 11, 12))):
        assert one.post(
            "/atlases/campus/submaps", json={"name": submap}, headers=robot_a
        ).is_success
        for place in places:
            name, data = cohog(place)
            response = one.post(
                "/atlases/campus/frames",
                data={"submap": submap, "robot_id": "robot-a"},
                files={"image": (name, data)},
                headers=robot_a,
            )
            assert response.status_code == 201, response.text
            frames[place] = response.json()["frame_id"]
    ingested_at = time.monotonic()

    # robot B localises in robot A's submap through process 2
    def query(client: httpx.Client, place: int, headers: dict[str, str]) -> dict:
        name, data = cohog(place)
        response = client.post(
            "/atlases/campus/query", data={"k": "3"}, files={"image": (name, data)}, headers=headers
        )
        assert response.status_code == 200, response.text
        return response.json()

    def found_by_two() -> dict | None:
        answer = query(two, 11, robot_b)
        match = answer["match"]
        return answer if match and match["frame_id"] == frames[11] else None

    answer, _ = eventually(10, found_by_two)
    print(f"robot A's frame found through process 2 {time.monotonic() - ingested_at:.2f} s after")
    assert answer["match"]["robot_id"] == "robot-a" and answer["match"]["submap"] == "s1"
    assert answer["match"]["similarity"] > 0.999 and answer["loop_closure"] is True

    # wrong keys
    assert two.get("/atlases/campus").status_code == 401
    assert two.get("/atlases/campus", headers=auth("lnk_not-a-key")).status_code == 401
    assert two.get("/atlases/campus", headers=outsider).status_code == 403
    assert two.post("/atlases/campus/jobs", json=QUICK_JOB, headers=robot_b).status_code == 403
    outsider_id = [k for k in two.get("/keys", headers=admin).json() if k["name"] == "robot-c"]
    assert two.delete(f"/keys/{outsider_id[0]['id']}", headers=admin).status_code == 200
    assert one.get("/atlases/elsewhere", headers=outsider).status_code == 401

    # robot B's closure onto robot A's frame was recorded, and any process lists it
    closures = one.get("/atlases/campus/loop-closures", headers=robot_b).json()
    assert ("robot-b", "robot-a") in [(c["robot_id"], c["matched_robot_id"]) for c in closures]

    # a retraining job submitted through process 2 makes process 1 serve the new version (robot
    # B asks: a robot key is its robot, and robot A's own recent frames never match robot A)
    before = query(one, 11, robot_b)
    assert before["model_version"] == 1
    job = two.post("/atlases/campus/jobs", json=QUICK_JOB, headers=operator)
    assert job.status_code == 202, job.text

    def job_done() -> dict | None:
        assert worker.poll() is None, fleet.stop()
        body = two.get(f"/atlases/campus/jobs/{job.json()['id']}", headers=operator).json()
        return body if body["status"] in ("succeeded", "failed", "cancelled") else None

    finished, _ = eventually(240, job_done)
    assert finished["status"] == "succeeded", finished
    after, delay = eventually(
        10, lambda: (a := query(one, 11, robot_b))["model_version"] == 2 and a
    )
    print(f"process 1 served model version 2 within {delay:.2f} s of the job's end")
    assert after["predicted_submap"]["available"] is True
    assert after["match"]["frame_id"] == frames[11]

    # a deletion through process 2 reaches process 1's index
    deleted = two.delete(f"/atlases/campus/frames/{frames[11]}", headers=operator)
    assert deleted.status_code == 204
    eventually(10, lambda: query(one, 11, robot_b)["match"]["frame_id"] != frames[11])
