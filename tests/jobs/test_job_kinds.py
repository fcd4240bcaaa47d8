"""Every job kind is defined once (service/jobs/kinds.py) and reachable from the API: the
API's request names its parameters, the registry reads what the API sends with its defaults."""

from __future__ import annotations

import pytest

from service.api.schemas_admin import JOB_PARAMS, JobIn
from service.domain.statuses import JobKind
from service.errors import InvalidInput
from service.jobs.kinds import KINDS, kind_of


def test_every_kind_has_one_entry_and_an_api_field() -> None:
    assert set(KINDS) == {k.value for k in JobKind} == set(JOB_PARAMS)


@pytest.mark.parametrize("kind", [k.value for k in JobKind])
def test_the_api_defaults_of_each_kind_are_what_its_runner_reads(kind: str) -> None:
    params = JobIn.model_validate({"kind": kind}).job_params()
    assert kind_of(kind).parse(params) is not None


def test_an_unknown_kind_is_refused_with_the_kinds_there_are() -> None:
    with pytest.raises(InvalidInput, match="unknown job kind 'reticulate'.*retrain"):
        kind_of("reticulate")


def test_bad_parameters_are_refused_before_anything_is_written() -> None:
    with pytest.raises(InvalidInput, match="invalid job parameters"):
        kind_of("retrain").parse({"epochs": -1})
    with pytest.raises(InvalidInput, match="invalid job parameters"):
        kind_of("adapt").parse({"min_pairs": 1})
    with pytest.raises(InvalidInput):
        kind_of("calibrate").parse({"aggregator": "fisher"})
