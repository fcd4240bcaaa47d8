"""Snapshots: an atlas exported from one deployment answers the same queries after a restore
into another (SQLite -> PostgreSQL, SQLite -> SQLite); bad archives are refused."""

from __future__ import annotations

import io
import json
import os
import tarfile
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.atlas.loop_closures import record_if_inter_robot
from service.cli import main
from service.jobs.retraining import JobRunner
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import (
    TEST_LONG_SIDE,
    TEST_MAX_KEYPOINTS,
    gardens_point_day_night,
    make_settings,
    wait_ready,
)

QUERIES = (1, 4, 7)


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


def loopnet(env: dict[str, str], *args: str) -> Ran:
    """``loopnet ARGS`` in this process (the CLI's own code) with ``env`` set meanwhile."""
    saved = {name: os.environ.get(name) for name in env}
    os.environ.update(env)
    out, err = io.StringIO(), io.StringIO()
    try:
        with redirect_stdout(out), redirect_stderr(err):
            code = main(list(args))
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    return Ran(code, out.getvalue(), err.getvalue())


def deployment_env(data_dir: Path, database_url: str | None = None) -> dict[str, str]:
    env = {
        "LOOPNET_DATA_DIR": str(data_dir),
        "LOOPNET_LONG_SIDE": str(TEST_LONG_SIDE),
        "LOOPNET_MAX_KEYPOINTS": str(TEST_MAX_KEYPOINTS),
    }
    if database_url:
        env["LOOPNET_DATABASE_URL"] = database_url
    return env


def answers(client: TestClient, atlas: str) -> list[dict]:
    """Query answers without what legitimately differs between deployments (ids, timings)."""
    out = []
    for i in QUERIES:
        body = client.post(
            f"/v1/atlases/{atlas}/query",
            data={"k": "4"},
            files={"image": ("q.jpg", gardens_point_day_night(i, "query"))},
        ).json()
        out.append(
            {
                "model_version": body["model_version"],
                "loop_closure": body["loop_closure"],
                "predicted": (
                    body["predicted_submap"]["submap"],
                    round(body["predicted_submap"]["probability"] or 0, 5),
                ),
                "candidates": [
                    (c["submap"], c["robot_id"], round(c["similarity"], 5))
                    for c in body["candidates"]
                ],
            }
        )
    return out


@pytest.fixture(scope="module")
def exported(
    tmp_path_factory: pytest.TempPathFactory, pipeline
) -> tuple[Path, list[dict], list[dict]]:  # type: ignore[no-untyped-def]
    """A SQLite deployment's atlas (two robots, a trained version, one inter-robot closure),
    its answers, its loop closures, and its snapshot file."""
    tmp_path = tmp_path_factory.mktemp("snapshot-source")
    settings = make_settings(tmp_path / "source")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client, submaps=("s0", "s1"))
        for i in range(8):
            add_frame(
                client,
                gardens_point_day_night(i, "ref"),
                submap=f"s{i // 4}",
                robot="robot-a" if i % 2 else "robot-b",
            )
        service = client.app.state.runtime.service  # type: ignore[attr-defined]
        with transaction(service.sessions) as session:
            atlas_id = repo.get_atlas(session, name="campus").id
            job_id = jobs.create_job(
                session,
                atlas_id=atlas_id,
                kind="retrain",
                params={"shots": 2, "epochs": 20, "embed_dim": 32},
            ).id
        JobRunner(settings, service.sessions).run(job_id)
        result = service.query(
            atlas_name="campus", image_bytes=gardens_point_day_night(3, "ref"), k=1
        )
        assert result.loop_closure and result.match is not None
        assert result.match.robot_id == "robot-a"
        assert record_if_inter_robot(
            service.sessions, robot_id="robot-c", result=result, source="query"
        )
        assert (
            record_if_inter_robot(
                service.sessions, robot_id="robot-a", result=result, source="query"
            )
            is None
        )  # the robot's own frame: not an inter-robot closure
        before = answers(client, "campus")
        closures = client.get("/v1/atlases/campus/loop-closures").json()
        assert [(c["robot_id"], c["matched_robot_id"]) for c in closures] == [
            ("robot-c", "robot-a")
        ]
        assert client.get("/v1/atlases/campus/loop-closures?robot=robot-z").json() == []
    assert before[0]["model_version"] == 2
    archive = tmp_path / "campus.snapshot.tar"
    made = loopnet(
        deployment_env(tmp_path / "source"), "snapshot", "export", "campus", str(archive)
    )
    assert made.returncode == 0, made.stderr
    assert '"frames": 8' in made.stdout
    return archive, before, closures


@pytest.mark.slow
@pytest.mark.parametrize("target", ["sqlite", "postgres"])
def test_restored_snapshot_answers_the_same(
    target: str, exported, tmp_path: Path, pipeline, request: pytest.FixtureRequest
) -> None:  # type: ignore[no-untyped-def]
    archive, before, closures = exported
    url = request.getfixturevalue("postgres_url") if target == "postgres" else None
    env = deployment_env(tmp_path / "target", url)
    restored = loopnet(env, "snapshot", "restore", str(archive), "--as", "campus2")
    assert restored.returncode == 0, restored.stderr
    again = loopnet(env, "snapshot", "restore", str(archive), "--as", "campus2")
    assert again.returncode == 1 and "already exists" in again.stderr

    settings = make_settings(tmp_path / "target", database_url=url)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        assert answers(client, "campus2") == before
        restored_closures = client.get("/v1/atlases/campus2/loop-closures").json()
        keep = ("robot_id", "matched_robot_id", "submap", "similarity", "source")
        assert [{k: c[k] for k in keep} for c in restored_closures] == [
            {k: c[k] for k in keep} for c in closures
        ]
        versions = client.get("/v1/atlases/campus2/models").json()
        assert [(v["version"], v["is_active"], v["trained"]) for v in versions] == [
            (1, False, False),
            (2, True, True),
        ]


def rewrite_manifest(archive: Path, out: Path, **changes: object) -> Path:
    with tarfile.open(archive) as source, tarfile.open(out, "w") as target:
        for member in source.getmembers():
            data = source.extractfile(member).read()  # type: ignore[union-attr]
            if member.name == "manifest.json":
                data = json.dumps({**json.loads(data), **changes}).encode()
            member.size = len(data)
            target.addfile(member, io.BytesIO(data))
    return out


def test_restore_refuses_bad_archives(exported, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    archive = exported[0]
    env = deployment_env(tmp_path / "target")
    future = rewrite_manifest(archive, tmp_path / "future.tar", format_version=99)
    refused = loopnet(env, "snapshot", "restore", str(future))
    assert refused.returncode == 1 and "format version 99 is not supported" in refused.stderr

    other_features = loopnet(
        {**env, "LOOPNET_LONG_SIDE": "320"}, "snapshot", "restore", str(archive)
    )
    assert other_features.returncode == 1
    assert "restore it on a service running the snapshot's settings" in other_features.stderr

    corrupt = tmp_path / "corrupt.tar"
    with tarfile.open(archive) as source, tarfile.open(corrupt, "w") as target:
        for member in source.getmembers():
            data = source.extractfile(member).read()  # type: ignore[union-attr]
            if member.name == "frames.jsonl":
                data = data.replace(b"robot-a", b"robot-x")
            target.addfile(member, io.BytesIO(data))
    damaged = loopnet(env, "snapshot", "restore", str(corrupt))
    assert damaged.returncode == 1 and "frames.jsonl is corrupt" in damaged.stderr


def test_snapshot_over_http_round_trips(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data")
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client, submaps=("s0",))
        for i in range(3):
            add_frame(client, gardens_point_day_night(i, "ref"), robot=f"robot-{i}")
        download = client.get("/v1/atlases/campus/snapshot")
        assert download.status_code == 200
        assert download.headers["content-type"] == "application/x-tar"
        restored = client.post(
            "/v1/snapshots?name=copy", files={"archive": ("s.tar", download.content)}
        )
        assert restored.status_code == 201, restored.text
        assert restored.json()["frames"] == 3
        assert answers(client, "copy") == answers(client, "campus")
        again = client.post(
            "/v1/snapshots?name=copy", files={"archive": ("s.tar", download.content)}
        )
        assert again.status_code == 409
        junk = client.post("/v1/snapshots", files={"archive": ("s.tar", b"not a tar file")})
        assert (
            junk.status_code == 422 and "not a readable snapshot archive" in junk.json()["detail"]
        )


def test_a_calibrated_atlas_round_trips_with_its_calibration(tmp_path: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", verify_top=0)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        create_atlas(client, submaps=("s0",))
        for i in range(10):
            add_frame(client, gardens_point_day_night(i, "ref"), robot="robot-a")
        for i in (0, 9):
            add_frame(client, gardens_point_day_night(i, "query"), robot="robot-b")
        service = client.app.state.runtime.service  # type: ignore[attr-defined]
        with transaction(service.sessions) as session:
            atlas_id = repo.get_atlas(session, name="campus").id
            job_id = jobs.create_job(
                session, atlas_id=atlas_id, kind="calibrate", params={"words": 8}
            ).id
        JobRunner(settings, service.sessions).run(job_id)
        assert client.get("/v1/atlases/campus").json()["calibration"]["state"] == "calibrated"
        download = client.get("/v1/atlases/campus/snapshot")
        assert download.status_code == 200
        restored = client.post(
            "/v1/snapshots?name=copy", files={"archive": ("s.tar", download.content)}
        )
        assert restored.status_code == 201, restored.text
        summary = client.get("/v1/atlases/copy").json()
        assert summary["calibration"] == client.get("/v1/atlases/campus").json()["calibration"]
        assert answers(client, "copy") == answers(client, "campus")
        scores = [
            client.post(
                f"/v1/atlases/{atlas}/query",
                data={"k": "3"},
                files={"image": ("q.jpg", gardens_point_day_night(4, "query"))},
            ).json()["match"]["score"]
            for atlas in ("campus", "copy")
        ]
        assert scores[0] is not None and scores[0] == scores[1]
        # the copy's calibration is its own file, not the source atlas's
        paths = [
            client.get(f"/v1/atlases/{atlas}/models").json()[-1]["config"]["calibration"]["path"]
            for atlas in ("campus", "copy")
        ]
        assert paths[0] != paths[1]
        assert (settings.models_dir / paths[1]).read_bytes() == (
            settings.models_dir / paths[0]
        ).read_bytes()
