"""Classical loop-closure baselines, run in the same harness as LoopNet.

Each baseline describes one decoded frame at a time (``describe``), learns what it needs from
the reference frames only (``fit``), and scores queries against every reference (``score``:
``Q x R``, higher is more similar).
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from service.evaluation.baselines.bow_orb import BowOrbBaseline, OrbBowConfig
from service.evaluation.baselines.seqslam import SadThumbnailBaseline, ThumbnailConfig


class Baseline(Protocol):
    name: str
    label: str

    def describe(self, rgb: np.ndarray) -> Any: ...

    def fit(self, references: list[Any]) -> None: ...

    def score(self, queries: list[Any]) -> np.ndarray: ...

    def settings(self) -> dict[str, Any]: ...


BASELINES: dict[str, type[BowOrbBaseline] | type[SadThumbnailBaseline]] = {
    "bow-orb": BowOrbBaseline,
    "seqslam-sad": SadThumbnailBaseline,
}


def build_baseline(name: str, long_side: int) -> Baseline:
    """The baseline ``name``; ``long_side`` is the working size of keypoint-based ones."""
    if name == "bow-orb":
        return BowOrbBaseline(OrbBowConfig(long_side=long_side))
    if name == "seqslam-sad":
        return SadThumbnailBaseline(ThumbnailConfig())
    raise ValueError(f"unknown baseline {name!r}; choose one of {sorted(BASELINES)}")


__all__ = ["BASELINES", "Baseline", "BowOrbBaseline", "SadThumbnailBaseline", "build_baseline"]
