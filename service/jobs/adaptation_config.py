"""An adaptation job's parameters: what the API validates at submit and the worker runs with
(kept apart from the job's code so that the API's schemas load no numerical library)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from service.domain.pairs import MIN_ADAPTATION_PAIRS, PairFilter

AdaptMethod = Literal["whitening", "whitening+pairs", "pairs"]
ADAPT_METHODS: tuple[AdaptMethod, ...] = ("whitening", "whitening+pairs", "pairs")
DEFAULT_METHOD: AdaptMethod = "whitening+pairs"
METHOD_TEXT = {
    "whitening": "learned whitening from revisit pairs",
    "whitening+pairs": "learned whitening, then a listwise loss over the pairs",
    "pairs": "a listwise loss over the pairs from the calibrated input",
}


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class AdaptConfig:
    """Parameters of one adaptation job: which pairs, how the whitening is regularised, and
    whether a listwise loss over the pairs fine-tunes it."""

    method: AdaptMethod = Field(
        default=DEFAULT_METHOD,
        description="whitening: the closed-form learned whitening; whitening+pairs: then "
        "fine-tuned with a listwise loss over the pairs, hard negatives from the atlas; "
        "pairs: the loss alone, from the calibrated input.",
    )

    robots: tuple[str, ...] = Field(
        default=(), description="Only pairs with a frame of one of these robots; empty: all."
    )
    submaps: tuple[str, ...] = Field(
        default=(), description="Only pairs with a frame in one of these submaps; empty: all."
    )
    since: datetime | None = Field(default=None, description="Only pairs recorded from then.")
    until: datetime | None = Field(default=None, description="Only pairs recorded before then.")
    shrinkage: float | None = Field(
        default=None,
        ge=0,
        le=1,
        description="Weight of the identity in the pairs' covariance; unset: Ledoit-Wolf's.",
    )
    max_dims: int | None = Field(
        default=None, ge=2, le=4096, description="Axes kept; unset: all of the fused input."
    )
    min_pairs: int = Field(
        default=MIN_ADAPTATION_PAIRS,
        ge=2,
        le=100_000,
        description="Fewer usable pairs: the job is refused.",
    )
    window: int = Field(
        default=2, ge=0, le=1000, description="Frames of one robot this close are one place."
    )
    # set by the automatic trigger: the newest pair the job was queued for
    through_pair: int | None = Field(default=None, ge=0)
    automatic: bool = False

    def pair_filter(self) -> PairFilter:
        return PairFilter(self.robots, self.submaps, self.since, self.until)

    @property
    def whitens(self) -> bool:
        """Whether the learned whitening is fitted (else the loss starts from the input)."""
        return self.method != "pairs"

    @property
    def trains_on_pairs(self) -> bool:
        """Whether the listwise loss over the pairs fine-tunes the start."""
        return self.method != "whitening"
