"""Snapshots: an atlas exported from one deployment answers the same queries after a restore
into another (SQLite -> PostgreSQL, SQLite -> SQLite); bad archives are refused."""

from __future__ import annotations

import io
import json
import tarfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.jobs.retraining import JobRunner
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night, make_settings, wait_ready
from tests.fleet.snapshot_helpers import answers, deployment_env, loopnet
from tests.fleet.test_snapshot_restore_safety import jsonl_edit, members_of, write_archive


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
        _refuses_bad_calibration_members(client, tmp_path, download.content)


def _refuses_bad_calibration_members(client: TestClient, tmp_path: Path, archive: bytes) -> None:
    """A restore validates the calibration member like every other: no pickle, the member its
    row names and no other, loadable into the version's heads; a refused one writes nothing."""
    source = tmp_path / "calibrated.tar"
    source.write_bytes(archive)
    members = members_of(source)
    (member,) = [n for n in members if n.endswith("-calibration.npz")]
    pickled = io.BytesIO()
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with_pickle = io.BytesIO()
    with zipfile.ZipFile(with_pickle, "w") as zipped:
        zipped.writestr("meta.npy", pickled.getvalue())
    truncated = io.BytesIO()
    with np.load(io.BytesIO(members[member])) as npz:
        np.savez(truncated, meta=npz["meta"])  # no aggregator or whitening arrays

    def without_row_file(rows: list[dict]) -> None:
        for row in rows:
            row.pop("calibration_file", None)

    mutations: dict[str, Callable[[dict[str, bytes]], None]] = {
        "pickled": lambda m: m.update({member: with_pickle.getvalue()}),
        "truncated": lambda m: m.update({member: truncated.getvalue()}),
        "missing": lambda m: m.pop(member),
        "unnamed": jsonl_edit("model_versions.jsonl", without_row_file),
        "extra": lambda m: m.update({"models/v77-calibration.npz": m[member]}),
    }
    for label, mutate in mutations.items():
        bad = dict(members)
        mutate(bad)
        path = write_archive(bad, tmp_path / f"{label}.tar")
        answer = client.post(
            f"/v1/snapshots?name=bad-{label}", files={"archive": ("s.tar", path.read_bytes())}
        )
        assert answer.status_code == 422, (label, answer.text)
        assert "calibration" in answer.json()["detail"], (label, answer.text)
        assert client.get(f"/v1/atlases/bad-{label}").status_code == 404
