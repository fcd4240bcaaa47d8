"""Which revisit pairs a job or a listing takes (a plain value: no I/O)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

MIN_ADAPTATION_PAIRS = 10
"""Fewest usable pairs an adaptation job takes by default: the job's parameter and the
automatic trigger (which must not queue a job that could only be refused) share it."""


@dataclass(frozen=True)
class PairFilter:
    """Which pairs a job (or a listing) takes: ``robots`` on either side, created in
    ``[since, until)``, either frame in one of ``submaps``; unset: no condition."""

    robots: tuple[str, ...] = ()
    submaps: tuple[str, ...] = ()
    since: datetime | None = None
    until: datetime | None = None
