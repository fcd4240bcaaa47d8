"""A similarity score with a fixed meaning: how rarely two different places look this alike.

At calibration an atlas's own *impostor* pairs are sampled: stored frames that cannot be the
same place without any label, namely frames of one robot far apart in its sequence, and frames
of different robots except near the places the fleet verified as revisits (its revisit pairs).
A second robot driving the first's route makes a few percent of the cross-robot pairs true
matches, whose cosines would fill the very tail the score is read from; the odd unrecorded
loop closure left among far-apart frames is rare enough to leave it almost untouched. The
pairs' cosines give the impostor distribution, and a cosine ``c`` maps to

    score(c) = -log10 P(impostor cosine >= c)

so score 3 means "one impostor pair in a thousand is this similar", on every atlas and every
model version. The survival function is empirical up to the top ``tail_fraction`` of impostor
cosines and an exponential tail beyond (peaks over threshold), so scores above the largest
sampled impostor stay finite and ordered.

Small atlases have few distinct impostor pairs: pairs are never counted twice, and the tail's
scale is never below what a normal distribution with the body's median and spread gives beyond
the tail's start; where fewer than 50 pairs lie in the tail, twice that (measured impostor
tails are heavier than normal ones on the development sets), so a handful of pairs
cannot make every match look astronomically rare.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np


def sequence_positions(
    robots: Sequence[str], order: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: its robot's code, its rank in that robot's sequence, and the gap (a
    twentieth of the robot's frames, at least 5) beyond which two of its frames are taken for
    different places."""
    codes = np.unique(np.asarray(robots), return_inverse=True)[1].reshape(-1)
    rank = np.empty(len(codes), np.int64)
    sizes = np.bincount(codes)
    for code in range(len(sizes)):
        members = np.flatnonzero(codes == code)
        rank[members[np.argsort(order[members], kind="stable")]] = np.arange(len(members))
    return codes, rank, np.maximum(MIN_GAP, sizes // 20)[codes]


def impostor_pairs(
    robots: Sequence[str],
    order: np.ndarray,
    *,
    pairs: int = 200_000,
    min_gap: int | None = None,
    seed: int = 0,
    first_from: np.ndarray | None = None,
    same_place: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` of frames that are not the same place by sequence alone.

    ``order`` ranks each frame within its robot's sequence (frame ids or timestamps). Pairs of
    one robot need at least ``min_gap`` frames between them (default: a twentieth of the
    robot's frames, at least 5); pairs of different robots are kept, except where
    ``same_place`` (``m x 2`` indices of frames known to show one place: the fleet's revisit
    pairs) says otherwise: a pair whose frame lies within that gap of a known partner of the
    other is the same place. With ``first_from`` (a mask), every pair's first frame is inside
    the mask and its second outside.
    """
    n = len(robots)
    if n < 2:
        raise ValueError(f"impostor pairs need at least 2 frames, got {n}")
    codes, rank, gap = sequence_positions(robots, order)
    if min_gap is not None:
        gap = np.full(n, min_gap, np.int64)
    rng = np.random.default_rng(seed)
    if first_from is None:
        first, second = rng.integers(0, n, size=(2, pairs * 2))
    else:
        inside, outside = np.flatnonzero(first_from), np.flatnonzero(~first_from)
        if len(inside) == 0 or len(outside) == 0:
            raise ValueError("first_from must leave frames on both sides")
        first = inside[rng.integers(0, len(inside), pairs * 2)]
        second = outside[rng.integers(0, len(outside), pairs * 2)]
    keep = (codes[first] != codes[second]) | (np.abs(rank[first] - rank[second]) >= gap[first])
    if same_place is not None and len(same_place):
        keep &= ~_near_partner(first, second, codes, rank, gap, same_place)
    first, second = _distinct(first[keep], second[keep], n)
    if len(first) == 0:
        raise ValueError("no frame pairs are far enough apart to serve as impostors")
    order_kept = rng.permutation(len(first))[:pairs]
    return first[order_kept], second[order_kept]


def _near_partner(
    first: np.ndarray,
    second: np.ndarray,
    codes: np.ndarray,
    rank: np.ndarray,
    gap: np.ndarray,
    same_place: np.ndarray,
) -> np.ndarray:
    """Per pair: whether one frame has a known partner (``same_place``) of the other's robot
    less than that robot's gap from the other along its sequence. Vectorised: each link
    becomes a sortable key (frame, partner's robot, partner's rank), and a pair asks whether
    a key falls in its frame's window."""
    links = np.asarray(same_place, np.int64).reshape(-1, 2)
    source = np.concatenate([links[:, 0], links[:, 1]])
    partner = np.concatenate([links[:, 1], links[:, 0]])
    robots = int(codes.max()) + 1
    span = 4 * (len(codes) + 1)  # rank +- gap, shifted positive, never reaches the next key

    def key(frame: np.ndarray, robot: np.ndarray, position: np.ndarray) -> np.ndarray:
        return np.asarray((frame * robots + robot) * span + position + 2 * (len(codes) + 1))

    known = np.sort(key(source, codes[partner], rank[partner]))

    def near(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        low = key(a, codes[b], rank[b] - gap[b] + 1)
        high = key(a, codes[b], rank[b] + gap[b] - 1)
        return np.asarray(
            np.searchsorted(known, high, "right") > np.searchsorted(known, low, "left")
        )

    either: np.ndarray = near(first, second) | near(second, first)
    return either


def _distinct(first: np.ndarray, second: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each unordered pair once: on a small atlas sampling repeats the few pairs there are,
    and a repeated pair would count as independent evidence."""
    low, high = np.minimum(first, second), np.maximum(first, second)
    _, keep = np.unique(low * n + high, return_index=True)
    return first[keep], second[keep]


@dataclass
class ImpostorModel:
    """The impostor cosines' survival function, stored as quantiles plus an exponential tail.

    Attributes:
        quantiles: ``Q`` ascending cosines at probabilities ``levels``.
        levels: ``Q`` cumulative probabilities in [0, 1 - tail_fraction].
        tail_start: the cosine where the exponential tail begins.
        tail_fraction: impostor pairs above ``tail_start``.
        tail_scale: the tail's mean excess (cosine units).
        pairs: impostor pairs the model was fitted on.
    """

    quantiles: np.ndarray
    levels: np.ndarray
    tail_start: float
    tail_fraction: float
    tail_scale: float
    pairs: int

    @classmethod
    def fit(cls, cosines: np.ndarray, *, tail_fraction: float = 0.01) -> ImpostorModel:
        """Fit on the cosines of distinct impostor pairs (at least ``MIN_PAIRS``)."""
        values = np.sort(np.asarray(cosines, np.float64))
        if len(values) < MIN_PAIRS:
            raise ValueError(
                f"an impostor model needs at least {MIN_PAIRS} distinct pairs, got {len(values)}"
            )
        tail_start = float(np.quantile(values, 1.0 - tail_fraction))
        excess = values[values > tail_start] - tail_start
        # never lighter than a normal tail; with too few pairs in the tail to measure it,
        # as heavy as the development sets' tails were
        heavier = 1.0 if len(excess) >= MIN_TAIL_PAIRS else HEAVIER_THAN_NORMAL
        tail_scale = max(
            float(excess.mean()) if len(excess) else 0.0,
            heavier * _normal_excess(values, tail_start),
        )
        levels = np.linspace(0.0, 1.0 - tail_fraction, 513)
        return cls(
            quantiles=np.quantile(values, levels),
            levels=levels,
            tail_start=tail_start,
            tail_fraction=tail_fraction,
            tail_scale=max(tail_scale, 1e-6),
            pairs=len(values),
        )

    def p_value(self, cosines: np.ndarray | float) -> np.ndarray:
        """P(impostor cosine >= c), elementwise."""
        c = np.asarray(cosines, np.float64)
        body = 1.0 - np.interp(c, self.quantiles, self.levels, left=0.0)
        excess = np.maximum(c - self.tail_start, 0.0)  # the tail only applies above its start
        tail = self.tail_fraction * np.exp(-excess / self.tail_scale)
        return np.where(c >= self.tail_start, np.minimum(tail, self.tail_fraction), body)

    def score(self, cosines: np.ndarray | float) -> np.ndarray:
        """``-log10 p_value`` (0 or more): higher is a rarer impostor similarity.

        Computed in log space in the tail, so it keeps growing (and ordering matches)
        beyond any sampled impostor instead of saturating.
        """
        c = np.asarray(cosines, np.float64)
        body = -np.log10(np.maximum(self.p_value(c), 1e-300))
        tail = -np.log10(self.tail_fraction) + (c - self.tail_start) / (
            self.tail_scale * np.log(10.0)
        )
        scores: np.ndarray = np.maximum(np.where(c >= self.tail_start, tail, body), 0.0)
        return scores

    def state(self) -> dict[str, np.ndarray]:
        return {
            "quantiles": self.quantiles,
            "levels": self.levels,
            "tail": np.array([self.tail_start, self.tail_fraction, self.tail_scale, self.pairs]),
        }

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> ImpostorModel:
        tail = np.asarray(state["tail"], np.float64)
        return cls(
            quantiles=np.asarray(state["quantiles"], np.float64),
            levels=np.asarray(state["levels"], np.float64),
            tail_start=float(tail[0]),
            tail_fraction=float(tail[1]),
            tail_scale=float(tail[2]),
            pairs=int(tail[3]),
        )


MIN_PAIRS = 20
MIN_GAP = 5  # frames of one robot at least this far apart are different places


def frames_for_impostor_model() -> int:
    """The fewest frames of one robot that give ``MIN_PAIRS`` distinct impostor pairs: ``n``
    frames at least ``MIN_GAP`` apart pair up ``(n - MIN_GAP) (n - MIN_GAP + 1) / 2`` ways."""
    n = MIN_GAP + 1
    while (n - MIN_GAP) * (n - MIN_GAP + 1) // 2 < MIN_PAIRS:
        n += 1
    return n


MIN_TAIL_PAIRS = 50  # pairs beyond the tail's start needed to measure its scale
HEAVIER_THAN_NORMAL = 2.0  # empirical / normal mean excess on the dev sets: 2.2 (DISK), 2.3 (XFeat)


def _normal_excess(values: np.ndarray, start: float) -> float:
    """Mean excess beyond ``start`` of a normal with the sorted ``values``' median and
    (quantile-based) spread: the least a tail can weigh."""
    median = float(np.quantile(values, 0.5))
    spread = max(float(np.quantile(values, 0.84) - np.quantile(values, 0.16)) / 2.0, 1e-4)
    z = (start - median) / spread
    normal = NormalDist()
    survival = max(1.0 - normal.cdf(z), 1e-300)
    return spread * normal.pdf(z) / survival - (start - median)


def pair_cosines(vectors: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Cosines of the unit ``vectors``' row pairs ``(first[i], second[i])``, in blocks."""
    step = 16_384
    return np.concatenate(
        [
            np.einsum("ij,ij->i", vectors[first[i : i + step]], vectors[second[i : i + step]])
            for i in range(0, len(first), step)
        ]
    )


def loop_score_threshold(score_min: float, frames: int) -> float:
    """The score the best of ``frames`` candidates must reach so that a query with no true
    revisit passes with probability ``10**-score_min`` at most: each impostor pair passes score
    ``s`` with probability ``10**-s`` (the calibration's meaning), the best of ``frames`` about
    ``frames`` times as often. One setting then means the same on small and large atlases."""
    return round(score_min + math.log10(max(frames, 1)), 4)
