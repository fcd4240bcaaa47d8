"""Every route of the OpenAPI spec x every caller, against one table of who may call what.

A route missing from ``RULES`` fails the suite, so a new route cannot ship without a rule: add
one line per new route (method, path as the spec writes it, rule). Path parameters other than
``{atlas}`` get ids that do not exist, whatever their name.

How the answers are read: each request is cheap (an empty body, ids that do not exist). Keys are
checked before FastAPI validates the body or looks anything up (the guard answers 401 before
reading the body; the role dependencies answer 403 before body validation), so for an allowed
caller the answer is whatever comes after auth (422 for the missing body, 404 for the unknown
id, 200...), and for a refused one it is 401 or 403. "Allowed" therefore means: neither 401
nor 403, and no server error.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.fleet.keys import Role, create_key
from service.storage.db import transaction
from tests.conftest import make_settings, wait_ready


@dataclass(frozen=True)
class Rule:
    """Who may call a route: ``role`` and above (None: anyone, no key); ``unscoped``: only keys
    for every atlas. On routes with ``{atlas}``, a scoped key must also cover that atlas."""

    role: Role | None
    unscoped: bool = False


OPEN = Rule(None)
ROBOT, OPERATOR, ADMIN = Rule(Role.robot), Rule(Role.operator), Rule(Role.admin)
UNSCOPED_ADMIN = Rule(Role.admin, unscoped=True)

RULES: dict[tuple[str, str], Rule] = {
    ("GET", "/v1/health"): OPEN,
    ("GET", "/v1/ready"): OPEN,
    ("GET", "/v1/atlases"): ROBOT,  # lists only the key's atlases
    ("POST", "/v1/atlases"): UNSCOPED_ADMIN,
    ("GET", "/v1/atlases/{atlas}"): ROBOT,
    ("DELETE", "/v1/atlases/{atlas}"): ADMIN,
    ("POST", "/v1/atlases/{atlas}/submaps"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/submaps"): ROBOT,
    ("DELETE", "/v1/atlases/{atlas}/submaps/{submap}"): OPERATOR,
    ("GET", "/v1/atlases/{atlas}/models"): OPERATOR,
    ("POST", "/v1/atlases/{atlas}/models/{version}/activate"): OPERATOR,
    ("POST", "/v1/atlases/{atlas}/frames"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/frames/{frame_id}"): ROBOT,
    ("DELETE", "/v1/atlases/{atlas}/frames/{frame_id}"): OPERATOR,
    ("POST", "/v1/atlases/{atlas}/frames:features"): ROBOT,
    ("POST", "/v1/atlases/{atlas}/query:features"): ROBOT,
    ("POST", "/v1/atlases/{atlas}/query"): ROBOT,
    ("POST", "/v1/atlases/{atlas}/observe"): ROBOT,
    ("POST", "/v1/atlases/{atlas}/jobs"): OPERATOR,
    ("GET", "/v1/atlases/{atlas}/jobs"): OPERATOR,
    ("GET", "/v1/atlases/{atlas}/jobs/{job_id}"): OPERATOR,
    ("POST", "/v1/atlases/{atlas}/jobs/{job_id}/cancel"): OPERATOR,
    ("GET", "/v1/atlases/{atlas}/loop-closures"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/pairs"): OPERATOR,
    ("POST", "/v1/atlases/{atlas}/pairs"): OPERATOR,
    ("DELETE", "/v1/atlases/{atlas}/pairs/{pair_id}"): OPERATOR,
    ("GET", "/v1/atlases/{atlas}/loop-closures/{closure_id}"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/loop-closures/{closure_id}/query-thumbnail"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/loop-closures/{closure_id}/matches"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/frames"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/robots"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/frames/{frame_id}/keypoints"): ROBOT,
    ("GET", "/v1/atlases/{atlas}/frames/{frame_id}/thumbnail"): ROBOT,
    ("GET", "/v1/whoami"): ROBOT,
    ("GET", "/metrics"): OPEN,  # LOOPNET_METRICS_PUBLIC=false: operator
    ("GET", "/v1/atlases/{atlas}/snapshot"): ADMIN,
    ("POST", "/v1/snapshots"): UNSCOPED_ADMIN,
    ("GET", "/v1/keys"): ADMIN,  # a scoped admin sees only keys within its atlases
    ("POST", "/v1/keys"): ADMIN,  # a scoped admin creates keys only within its atlases
    ("DELETE", "/v1/keys/{key_id}"): ADMIN,  # a scoped admin revokes only keys it sees
}

ATLAS, OTHER_ATLAS = "campus", "lab"


class PathValues(dict[str, str]):
    """``{atlas}`` is the atlas the scoped keys hold; any other parameter an unknown id."""

    def __missing__(self, _name: str) -> str:
        return "999999"


PATH_VALUES = PathValues(atlas=ATLAS, submap="s0")


@dataclass(frozen=True)
class Caller:
    label: str
    role: Role | None  # None: no key
    atlases: tuple[str, ...] = ()


CALLERS = [Caller("no key", None)] + [
    Caller(f"{role.name}{' scoped' if atlases else ''}", role, atlases)
    for role in Role
    for atlases in ((), (ATLAS,))
]
OUTSIDERS = [Caller(f"{role.name} scoped to another atlas", role, (OTHER_ATLAS,)) for role in Role]


def allowed(rule: Rule, caller: Caller, path: str) -> bool:
    if rule.role is None:
        return True
    if caller.role is None or caller.role < rule.role:
        return False
    if caller.atlases and rule.unscoped:
        return False
    return not ("{atlas}" in path and caller.atlases and ATLAS not in caller.atlases)


@pytest.fixture(scope="module")
def app_and_tokens(tmp_path_factory: pytest.TempPathFactory, pipeline) -> Iterator:  # type: ignore[no-untyped-def]
    data = Path(tmp_path_factory.mktemp("permissions")) / "data"
    settings = make_settings(data, auth="required", auth_failure_limit=100_000)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        wait_ready(client)
        sessions = client.app.state.runtime.sessions  # type: ignore[attr-defined]
        root = _key(sessions, Caller("root", Role.admin))
        for atlas in (ATLAS, OTHER_ATLAS):
            assert client.post("/v1/atlases", json={"name": atlas}, headers=root).status_code == 201
        tokens = {c.label: _key(sessions, c) for c in CALLERS + OUTSIDERS if c.role is not None}
        yield client, tokens


def _key(sessions, caller: Caller) -> dict[str, str]:  # type: ignore[no-untyped-def]
    assert caller.role is not None
    name = re.sub(r"[^a-z0-9]+", "-", caller.label)
    with transaction(sessions) as session:
        token = create_key(session, name=name, role=caller.role, atlases=list(caller.atlases))
    return {"Authorization": f"Bearer {token.token}"}


def test_every_route_has_a_rule(app_and_tokens) -> None:  # type: ignore[no-untyped-def]
    client, _ = app_and_tokens
    spec = client.app.openapi()  # type: ignore[attr-defined]
    routes = {(method.upper(), path) for path, ops in spec["paths"].items() for method in ops}
    assert routes - set(RULES) == set(), "routes without a rule in RULES"
    assert set(RULES) - routes == set(), "rules for routes that no longer exist"


def test_every_route_answers_every_caller_as_the_table_says(app_and_tokens) -> None:  # type: ignore[no-untyped-def]
    client, tokens = app_and_tokens
    spec = client.app.openapi()  # type: ignore[attr-defined]
    wrong = []
    for path, ops in spec["paths"].items():
        url = path.format_map(PATH_VALUES)
        for method in ops:
            rule = RULES[(method.upper(), path)]
            callers = CALLERS + (OUTSIDERS if "{atlas}" in path else [])
            for caller in callers:
                headers = tokens.get(caller.label, {})
                status = client.request(method.upper(), url, headers=headers).status_code
                expected = allowed(rule, caller, path)
                refused = 401 if caller.role is None else 403
                ok = (status not in (401, 403) and status < 500) if expected else status == refused
                if not ok:
                    want = "allowed" if expected else refused
                    wrong.append(
                        f"{method.upper()} {path} as {caller.label}: {status}, want {want}"
                    )
    assert not wrong, "\n".join(wrong)
