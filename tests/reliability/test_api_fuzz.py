"""Schema-driven fuzzing of the whole HTTP API (schemathesis, in-process over ASGI).

Every operation of the OpenAPI spec gets generated requests, both fitting the schema and
violating it. Half the time the generator is steered onto names that exist (the atlas, its
submap, frames, model version, job) and the image onto an upload strategy (tiny valid images in
every mode, broken ones, bombs), so requests get past the 404s into the service; fields are also
swapped for the hostile values schema fuzzing does not make on its own (``hostile.py``: deeply
nested JSON, integers beyond 64 bits, NUL characters, feature arrays of the wrong shape).
Asserted for every request: no 5xx, an error answer has the ``{"detail", "error"}`` shape, and
a rejected request (4xx) leaves every table, job and index as it was. It runs on SQLite and on
PostgreSQL (where the server is reachable; ``LOOPNET_REQUIRE_SERVICES=1`` makes it required).

``LOOPNET_FUZZ_EXAMPLES`` sets the examples per operation (default 15 on SQLite, a third of that
on PostgreSQL: a few hundred requests in CI); ``LOOPNET_FUZZ_REPORT`` names a JSON file that
receives the status counts (``benchmarks/fuzz_api.py`` runs this module with both and prints
the counts).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.python.asgi import shutdown_lifespans
from sqlalchemy import func, select

from service.app.ingest import FrameFields
from service.features_payload import encode_features
from service.ml.images import decode_image
from service.storage.models import Atlas, Frame, FrameFeatureRow, Job, ModelVersion, Submap
from tests.conftest import DATA_DIR, make_settings
from tests.reliability.hostile import (
    feature_payloads,
    hostile_integers,
    hostile_json_field,
    hostile_text,
)
from tests.reliability.uploads import image_uploads
from tests.services import new_postgres_database

EXAMPLES = int(os.environ.get("LOOPNET_FUZZ_EXAMPLES", "15"))
REPORT = os.environ.get("LOOPNET_FUZZ_REPORT")
DATABASES = ("sqlite", "postgresql")
ATLAS, SUBMAP, ROBOT = "campus", "s0", "r1"
JSON_FIELDS = ("pose", "intrinsics")
STATUSES: dict[str, Counter[int]] = {database: Counter() for database in DATABASES}
OPERATIONS: Counter[str] = Counter()


def seed_image() -> bytes:
    return (DATA_DIR / "gardenspoint_cohog200" / "ref").glob("*.png").__next__().read_bytes()


@pytest.fixture(scope="module", params=DATABASES)
def fuzzed_app(  # type: ignore[no-untyped-def]
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, pipeline
) -> Iterator[Any]:
    """The real app with small upload limits, an atlas, a submap and two frames."""
    from service.api.app import create_app

    with contextlib.ExitStack() as stack:
        database = {}
        if request.param == "postgresql":
            database["database_url"] = stack.enter_context(new_postgres_database())
        settings_ = make_settings(
            tmp_path_factory.mktemp("fuzz"),
            max_upload_bytes=200_000,
            max_image_pixels=1_000_000,
            **database,
        )
        app = create_app(settings_, pipeline=pipeline, background_load=False)
        app.state.fuzz_database = request.param
        app.state.fuzz_features = encode_features(
            pipeline.extract(decode_image(seed_image())), pipeline.signature
        )
        yield app
        shutdown_lifespans()  # schemathesis started the app's lifespan on its first request
    if REPORT:
        statuses = sum(STATUSES.values(), Counter())
        Path(REPORT).write_text(
            json.dumps(
                {"statuses": statuses, "by_database": STATUSES, "operations": OPERATIONS},
                indent=2,
                sort_keys=True,
            )
        )


@pytest.fixture(scope="module")
def api_schema(fuzzed_app: Any) -> Any:
    """The app's OpenAPI spec, loaded over ASGI (which starts the app), and its seeded data."""
    schema = schemathesis.openapi.from_asgi("/openapi.json", fuzzed_app)
    service = fuzzed_app.state.runtime.service
    service.create_atlas(ATLAS)
    service.create_submap(ATLAS, SUBMAP)
    for _ in range(2):
        service.ingest_frame(
            atlas_name=ATLAS, fields=FrameFields(SUBMAP, ROBOT), image_bytes=seed_image()
        )
    return schema


def hostile(value: Any, name: str) -> st.SearchStrategy[Any]:
    """The generated value, or a hostile one of its kind."""
    if name in JSON_FIELDS:
        return st.one_of(st.just(value), hostile_json_field())
    if isinstance(value, bool) or value is None:
        return st.just(value)
    if isinstance(value, int):
        return st.one_of(st.just(value), hostile_integers())
    if isinstance(value, str):
        return st.one_of(st.just(value), hostile_text())
    if isinstance(value, dict):
        return st.one_of(
            st.just(value),
            st.fixed_dictionaries({key: hostile(item, key) for key, item in value.items()}),
        )
    return st.just(value)


def steer_onto_existing_things(case: Any, features: bytes) -> st.SearchStrategy[Any]:
    """Half the time, swap generated names for ones that exist and the image for an upload;
    sometimes a field for a hostile value."""

    def maybe(original: Any, *known: Any) -> st.SearchStrategy[Any]:
        return st.sampled_from([original, *known])

    path = dict(case.path_parameters or {})
    known: dict[str, tuple[Any, ...]] = {
        # DELETE keeps generated names: deleting the seeded atlas would end the steering
        "atlas": (ATLAS,) if case.method.upper() != "DELETE" else (),
        "frame_id": (1, 2),
        "version": (1,),
        "job_id": (1,),
    }
    path_strategy = st.fixed_dictionaries(
        {
            name: st.one_of(maybe(value, *known.get(name, ())), hostile(value, name))
            for name, value in path.items()
        }
    )
    body_strategy: st.SearchStrategy[Any] = st.just(case.body)
    if isinstance(case.body, dict):
        body = case.body
        body_strategy = st.fixed_dictionaries(
            {
                **{name: hostile(value, name) for name, value in body.items()},
                **(
                    {"image": st.one_of(st.just(body["image"]), image_uploads())}
                    if "image" in body
                    else {}
                ),
                **(
                    {"features": st.one_of(st.just(body["features"]), feature_payloads(features))}
                    if "features" in body
                    else {}
                ),
                **({"submap": maybe(body["submap"], SUBMAP)} if "submap" in body else {}),
                **({"robot_id": maybe(body["robot_id"], ROBOT)} if "robot_id" in body else {}),
            }
        )

    def steered(values: tuple[dict[str, Any], Any]) -> Any:
        case.path_parameters, case.body = values
        return case

    return st.tuples(path_strategy, body_strategy).map(steered)


def stored_state(service: Any) -> dict[str, Any]:
    """Everything a request could write: row counts, jobs, active versions, index sizes."""
    with service.sessions() as session:
        counts = {
            model.__tablename__: session.scalar(select(func.count()).select_from(model))
            for model in (Atlas, Submap, Frame, FrameFeatureRow, ModelVersion, Job)
        }
        jobs = session.execute(select(Job.id, Job.status, Job.cancel_requested)).all()
        active = session.execute(
            select(ModelVersion.atlas_id, ModelVersion.version).where(ModelVersion.is_active)
        ).all()
    indexed = {atlas_id: state.index.size for atlas_id, state in service._loaded.items()}
    return {**counts, "jobs": sorted(jobs), "active": sorted(active), "indexed": indexed}


def operations() -> list[tuple[str, GenerationMode]]:
    """``METHOD /path`` of every operation of the spec (built without starting the app), with
    the schema-fitting mode, and the schema-violating one where there is an input to violate."""
    from service.api.app import create_app

    spec = create_app().openapi()
    found = []
    for path, item in spec["paths"].items():
        for method, operation in item.items():
            found.append((f"{method.upper()} {path}", GenerationMode.POSITIVE))
            if operation.get("parameters") or operation.get("requestBody"):
                found.append((f"{method.upper()} {path}", GenerationMode.NEGATIVE))
    return found


@pytest.mark.parametrize(("operation", "mode"), operations())
def test_no_server_errors_and_rejections_write_nothing(
    operation: str, mode: GenerationMode, api_schema: Any, fuzzed_app: Any
) -> None:
    method, path = operation.split(" ", 1)
    service = fuzzed_app.state.runtime.service
    database = fuzzed_app.state.fuzz_database
    features = fuzzed_app.state.fuzz_features
    cases = api_schema[path][method].as_strategy(generation_mode=mode)

    @settings(
        max_examples=EXAMPLES if database == "sqlite" else max(3, EXAMPLES // 3),
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
        phases=[Phase.explicit, Phase.generate],
    )
    @given(cases.flatmap(lambda case: steer_onto_existing_things(case, features)))
    def run(case: Any) -> None:
        before = stored_state(service)
        response = case.call()
        STATUSES[database][response.status_code] += 1
        OPERATIONS[operation] += 1
        assert response.status_code < 500, (response.status_code, response.text[:500])
        if response.status_code >= 400:
            body = response.json()
            assert isinstance(body["detail"], str) and body["detail"], body  # a message
            assert isinstance(body["error"], str), body  # the documented error shape
            assert stored_state(service) == before, (response.status_code, response.text[:300])

    try:
        run()
    except Unsatisfiable:
        if mode is GenerationMode.POSITIVE:
            raise
        pytest.skip(f"every input of {operation} fits its schema: nothing to violate")
