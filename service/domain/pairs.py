"""Which revisit pairs a job or a listing takes (a plain value: no I/O)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime


@dataclass(frozen=True)
class PairFilter:
    """Which pairs a job (or a listing) takes: ``robots`` on either side, created in
    ``[since, until)``, either frame in one of ``submaps``; unset: no condition."""

    robots: tuple[str, ...] = ()
    submaps: tuple[str, ...] = ()
    since: datetime | None = None
    until: datetime | None = None
