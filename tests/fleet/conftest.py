"""The fleet tests' shared fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.app.loop_closures import record_if_inter_robot
from service.jobs.retraining import JobRunner
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from tests.api.helpers import add_frame, create_atlas
from tests.conftest import gardens_point_day_night, make_settings, wait_ready
from tests.fleet.snapshot_helpers import answers, deployment_env, loopnet


@pytest.fixture(scope="package")
def exported(
    tmp_path_factory: pytest.TempPathFactory, pipeline
) -> tuple[Path, list[dict], list[dict]]:  # type: ignore[no-untyped-def]
    """A SQLite deployment's atlas (two robots, a trained version, one inter-robot closure),
    its answers, its loop closures, and its snapshot file."""
    tmp_path = tmp_path_factory.mktemp("snapshot-source")
    # the snapshot must carry a trained active version, whatever the not-worse gate says of
    # 20 epochs on 8 frames
    settings = make_settings(tmp_path / "source", retrain_activate_worse=True)
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
        service.catch_up()  # the new version arrives through the change feed, as in a replica
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
