"""The closed sets of :mod:`service.domain.statuses` as the API's schemas type them: inline
``Literal``s in the OpenAPI spec (plain strings for the type checker), defined once."""

from __future__ import annotations

from typing import TYPE_CHECKING

from service.domain.statuses import (
    CalibrationState,
    JobKind,
    JobStatus,
    PlaceStatus,
    Role,
    literal_of,
)

if TYPE_CHECKING:
    CalibrationStateValue = str
    PlaceStatusValue = str
    JobKindValue = str
    JobStatusValue = str
    RoleName = str
else:
    CalibrationStateValue = literal_of(CalibrationState)
    PlaceStatusValue = literal_of(PlaceStatus)
    JobKindValue = literal_of(JobKind)
    JobStatusValue = literal_of(JobStatus)
    RoleName = literal_of(Role)
