"""Snapshots: an atlas exported from one deployment answers the same queries after a restore
into another (SQLite -> PostgreSQL, SQLite -> SQLite); bad archives are refused."""

from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night, make_settings, wait_ready
from tests.fleet.snapshot_helpers import answers, deployment_env, loopnet


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
