"""The public API stays as recorded: a change of the OpenAPI spec must be deliberate.

To make an intended change, regenerate ``openapi_baseline.json`` with::

    python -c "import json; from service.api.app import create_app; \
print(json.dumps(create_app().openapi(), indent=1, sort_keys=True))" \
> tests/api/openapi_baseline.json
"""

from __future__ import annotations

import json
from pathlib import Path

from service.api.app import create_app

BASELINE = Path(__file__).with_name("openapi_baseline.json")


def test_openapi_spec_matches_the_recorded_baseline() -> None:
    current = json.loads(json.dumps(create_app().openapi()))
    baseline = json.loads(BASELINE.read_text())
    assert current == baseline
