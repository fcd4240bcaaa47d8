"""Temporal consistency of loop closures (as DBoW2): a place is accepted as a loop only when the
last ``required`` observations of one robot all passed and all point at one stretch of one
reference trajectory; until then it is a candidate. When the newest observation passes nothing,
the robot is in a new place, said explicitly.

The state is the robot's last few hypotheses, which the caller can always recompute from stored
frames and vectors (or keep in a cache): the functions here are pure.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.domain.statuses import PlaceStatus as PlaceStatus
from service.ml.sequences.trajectories import Trajectories


@dataclass(frozen=True)
class ConsistencySettings:
    """Attributes:
    required: consecutive agreeing observations for a loop (DBoW2's k; 1 = no check).
    max_step: largest move along the reference trajectory between two consecutive
        observations that still counts as the same place (frames).
    """

    required: int = 3
    max_step: int = 3

    def __post_init__(self) -> None:
        if self.required < 1 or self.max_step < 0:
            raise ValueError("required must be >= 1 and max_step >= 0")


@dataclass(frozen=True)
class Hypothesis:
    """One observation's best reference frame and whether it passed the decision threshold."""

    reference: int
    passed: bool


@dataclass(frozen=True)
class PlaceDecision:
    status: PlaceStatus
    consistent: int  # consecutive agreeing passed observations, the newest included
    reference: int | None  # the newest hypothesis' frame (None when nothing passed)


def agree(earlier: int, later: int, trajectories: Trajectories, max_step: int) -> bool:
    """Whether two map positions are one place: on one reference trajectory, at most
    ``max_step`` frames apart along it."""
    if trajectories.sequence[earlier] != trajectories.sequence[later]:
        return False
    return abs(int(trajectories.rank[later]) - int(trajectories.rank[earlier])) <= max_step


def decide(
    recent: Sequence[Hypothesis | None],
    trajectories: Trajectories,
    settings: ConsistencySettings,
) -> PlaceDecision:
    """The newest observation's verdict from the robot's recent hypotheses (oldest first, the
    newest last; None where an observation had no candidate at all)."""
    newest = recent[-1] if recent else None
    if newest is None or not newest.passed:
        return PlaceDecision(PlaceStatus.NEW_PLACE, 0, None)
    consistent = 1
    later = newest
    for earlier in reversed(recent[:-1]):
        if consistent >= settings.required:
            break
        if earlier is None or not earlier.passed:
            break
        if not agree(earlier.reference, later.reference, trajectories, settings.max_step):
            break
        consistent += 1
        later = earlier
    status = PlaceStatus.LOOP if consistent >= settings.required else PlaceStatus.CANDIDATE
    return PlaceDecision(status, consistent, newest.reference)


def consistent_scores(
    references: np.ndarray,
    scores: np.ndarray,
    trajectories: Trajectories,
    settings: ConsistencySettings,
    starts: np.ndarray | None = None,
) -> np.ndarray:
    """For a stream of observations (best reference and score each, in order), the score each
    would be accepted as a loop at: the lowest score of its last ``required`` observations when
    they agree, else -inf. Accepting where this is >= t is exactly :func:`decide` with
    "passed" meaning score >= t, so one array gives the whole precision-recall sweep.

    ``starts`` marks observations that begin a new query sequence (nothing before them counts).
    """
    references = np.asarray(references, dtype=np.int64)
    scores = np.asarray(scores, dtype=np.float64)
    n = len(scores)
    cut = np.zeros(n, dtype=bool) if starts is None else np.asarray(starts, dtype=bool)
    out = np.where(references >= 0, scores, -np.inf)
    run = np.ones(n, dtype=np.int64)
    for i in range(1, n):
        if (
            not cut[i]
            and references[i] >= 0
            and references[i - 1] >= 0
            and agree(references[i - 1], references[i], trajectories, settings.max_step)
        ):
            run[i] = run[i - 1] + 1
    k = settings.required
    result = np.full(n, -np.inf)
    for i in range(n):
        if references[i] >= 0 and run[i] >= k:
            result[i] = out[i - k + 1 : i + 1].min()
    return result
