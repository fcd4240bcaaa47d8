"""What a calibration fits and what it fits on: its configuration, the stored features it
reads back, and the impostor probe its score model is fitted on (plain values, no fitting)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from service.domain.statuses import AggregatorName
from service.ml.whitening import WhiteningConfig

if TYPE_CHECKING:
    from service.ml.calibration import Calibration

VLAD_SIZE = 16_384  # values of a raw VLAD vector (words x descriptor dim) when words is None


@dataclass(frozen=True)
class CalibrationConfig:
    """What a calibration fits, and with how much data.

    Attributes:
        aggregator: ``vlad`` or ``mean`` (see :mod:`service.ml.aggregators`).
        words: VLAD vocabulary size; None: ``VLAD_SIZE // descriptor dim`` (DISK 128 words,
            XFeat 256), so every extractor's VLAD has the same length.
        local, global_: each branch's reduction and whitening.
        alpha: the fusion weight of the local branch.
        descriptor_sample: descriptors the vocabulary is learned on, at most.
        fit_frames: frames each whitening is fitted on, at most (sampled).
        impostor_pairs: impostor pairs the score model is fitted on, at most.
        impostor_holdout: share of the fitting frames left out of a second, probe whitening
            so that impostor pairs pair unseen frames with seen ones, as queries do.
        seed: every sample and the k-means start from it (a calibration is reproducible).
    """

    aggregator: AggregatorName = "vlad"
    words: int | None = None
    local: WhiteningConfig = field(default_factory=lambda: WhiteningConfig(max_dims=512))
    global_: WhiteningConfig = field(default_factory=lambda: WhiteningConfig(max_dims=512))
    alpha: float = 0.5
    descriptor_sample: int = 100_000
    fit_frames: int = 20_000
    impostor_pairs: int = 100_000
    impostor_holdout: float = 0.2
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must lie in [0, 1], got {self.alpha}")
        if self.words is not None and self.words < 1:
            raise ValueError(f"words must be at least 1, got {self.words}")

    def words_for(self, descriptor_dim: int) -> int:
        """The vocabulary size for descriptors of ``descriptor_dim`` values."""
        return self.words if self.words is not None else max(8, VLAD_SIZE // descriptor_dim)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CalibrationConfig:
        return cls(
            **{
                **data,
                "local": WhiteningConfig(**data["local"]),
                "global_": WhiteningConfig(**data["global_"]),
            }
        )


@dataclass
class CalibrationInputs:
    """Stored features of an atlas's frames, as a calibration job reads them back.

    Attributes:
        descriptors: per frame, ``N_i x d`` local descriptors (float16 as stored is fine).
        scores: per frame, ``N_i`` detection scores.
        global_vectors: ``n x C`` backbone vectors R.
        robots: per frame, the robot that recorded it.
        order: per frame, its place in its robot's sequence (frame id or timestamp).
        same_place: ``m x 2`` row indices of frames known to show one place (the atlas's
            revisit pairs), never sampled as impostors; empty: none known.
    """

    descriptors: Sequence[np.ndarray]
    scores: Sequence[np.ndarray]
    global_vectors: np.ndarray
    robots: Sequence[str]
    order: np.ndarray
    same_place: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))

    def __post_init__(self) -> None:
        n = len(self.global_vectors)
        if (
            not len(self.descriptors)
            == len(self.scores)
            == len(self.robots)
            == len(self.order)
            == n
        ):
            raise ValueError(
                f"calibration inputs disagree on the frame count: {len(self.descriptors)} "
                f"descriptor sets, {len(self.scores)} score sets, {n} global vectors, "
                f"{len(self.robots)} robots, {len(self.order)} order keys"
            )

    def __len__(self) -> int:
        return len(self.global_vectors)


@dataclass
class ImpostorProbe:
    """Branch vectors of an atlas's frames and the impostor pairs a score model is fitted on.

    Every pair's ``first`` frame was held out of the whitenings that made these branches and
    its ``second`` was not, as a query meets stored frames; ``in_sample``: an atlas too small
    for that, whose pairs are in-sample pairs of the calibrated branches. ``held``: the mask
    of frames held out of the probe's fit (None when in-sample), which heads fitted on the
    atlas must not see either.
    """

    local_branch: np.ndarray
    global_branch: np.ndarray
    first: np.ndarray
    second: np.ndarray
    in_sample: bool
    held: np.ndarray | None = None


@dataclass
class FittedCalibration:
    """A fitted calibration and the branch vectors of the frames it was fitted on
    (so the job re-embeds those frames without aggregating them twice)."""

    calibration: Calibration
    local_branch: np.ndarray
    global_branch: np.ndarray
    timings_s: dict[str, float]
    cpu_s: dict[str, float]  # per stage too: on a shared machine, what a quiet one would take
