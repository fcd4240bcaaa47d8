"""Aggregators: a frame's set of local descriptors -> one vector (the local branch D).

A registry, so a model version names the aggregator it was calibrated with and ablations can
swap it: ``mean`` (the score-weighted mean every frame is stored with) and ``vlad`` (residuals
to a vocabulary learned on the atlas's own stored descriptors).
"""

from __future__ import annotations

from typing import Protocol, get_args

import numpy as np

from service.domain.statuses import AggregatorName
from service.ml.aggregators.mean import MeanAggregator
from service.ml.aggregators.vlad import VladAggregator, fit_vocabulary


class Aggregator(Protocol):
    """``N x d`` descriptors (+ ``N`` scores) of one frame -> one L2-normalised vector."""

    name: str

    @property
    def dim(self) -> int: ...

    def aggregate(self, descriptors: np.ndarray, scores: np.ndarray) -> np.ndarray: ...

    def state(self) -> dict[str, np.ndarray]: ...


AGGREGATORS: tuple[AggregatorName, ...] = get_args(AggregatorName)


def fit_aggregator(
    name: str,
    descriptor_sample: np.ndarray,
    *,
    words: int = 64,
    seed: int = 0,
) -> Aggregator:
    """An aggregator fitted (where it learns anything) on a sample of stored descriptors."""
    if name == "mean":
        return MeanAggregator(descriptor_sample.shape[1])
    if name == "vlad":
        return VladAggregator(fit_vocabulary(descriptor_sample, words=words, seed=seed))
    raise ValueError(f"unknown aggregator {name!r}; choose one of {list(AGGREGATORS)}")


def aggregator_from_state(name: str, state: dict[str, np.ndarray]) -> Aggregator:
    """Rebuild a saved aggregator from its :meth:`Aggregator.state`."""
    if name == "mean":
        return MeanAggregator(int(state["descriptor_dim"]))
    if name == "vlad":
        return VladAggregator(state["centroids"])
    raise ValueError(f"unknown aggregator {name!r}; choose one of {list(AGGREGATORS)}")


__all__ = [
    "AGGREGATORS",
    "AggregatorName",
    "Aggregator",
    "MeanAggregator",
    "VladAggregator",
    "aggregator_from_state",
    "fit_aggregator",
    "fit_vocabulary",
]
