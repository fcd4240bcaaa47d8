"""The closed sets the service answers with and stores: one definition each, which the API's
schemas, the database rows and the code share."""

from __future__ import annotations

import enum
from typing import Any, Literal

# How a frame's local descriptors become one vector (see service.ml.aggregators).
AggregatorName = Literal["vlad", "mean"]


class PlaceStatus(enum.StrEnum):
    """What one observation concluded."""

    LOOP = "loop"  # passed, and consistent with the previous required - 1 observations
    CANDIDATE = "candidate"  # passed, not yet consistent
    NEW_PLACE = "new_place"  # nothing passed


class JobKind(enum.StrEnum):
    """What a job does (each kind has its parameters and its runner)."""

    RETRAIN = "retrain"
    CALIBRATE = "calibrate"


class JobStatus(enum.StrEnum):
    """Where a job stands; the row stores the value."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


class CalibrationState(enum.StrEnum):
    """Whether an atlas's active model version carries a calibration."""

    UNCALIBRATED = "uncalibrated"
    CALIBRATED = "calibrated"


class Role(enum.IntEnum):
    """What an API key may do; a higher role may do what a lower one may."""

    robot = 1
    operator = 2
    admin = 3


def literal_of(values: type[enum.Enum]) -> Any:
    """``Literal[...]`` of an enum's values (of its names for an ``IntEnum``), for the API's
    schemas: the OpenAPI spec lists the set inline, as a hand-written ``Literal`` would."""
    members = list(values)
    if isinstance(members[0], enum.IntEnum):
        return Literal[tuple(m.name for m in members)]  # type: ignore[valid-type]
    return Literal[tuple(m.value for m in members)]  # type: ignore[valid-type]
