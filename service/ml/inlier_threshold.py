"""Verification's minimum inliers, calibrated per atlas from its own look-alikes.

How many RANSAC inliers a wrong candidate reaches depends on the images (size, texture,
repetitive structure) and on the keypoint budget, so a fixed minimum chosen on one dataset does
not transfer. The atlas's hard impostors are the wrong candidates a query meets: for a sample
of frames, the most similar frame (by the calibrated embedding) that is not the same place by
sequence alone, nor part of the frame's stay (:mod:`service.ml.stays`: a robot that stood still
longer than the sequence gap shows one place in all of it, and on Nordland the frames of stops
made the minimum 256-267 inliers at 128-512 frames, so that nothing verified). The minimum is set just above a high quantile of their inliers, never below a
floor where RANSAC agreement happens by chance.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from service.ml.impostors import sequence_positions
from service.ml.stays import StayRule

FLOOR = 15  # fewer inliers can agree on a fundamental matrix by chance
QUANTILE = 0.99  # robust to the few true revisits among far-apart frames
NEAR_DUPLICATE = 0.25  # of the keypoints as inliers: two views of one spot, not a look-alike


@dataclass(frozen=True)
class InlierThreshold:
    """The calibrated minimum and the operating point it came from."""

    matcher: str
    min_inliers: int
    impostors: int  # hard impostor pairs verified
    impostor_quantile: float  # their inliers at QUANTILE
    impostor_max: int
    accepted_impostors: int  # of them at or above the minimum
    one_stop_pairs: int = 0  # pairs of one robot's frames left out: it never left the place
    impostor_median: float = 0.0
    impostor_highest: tuple[int, ...] = ()  # the ten most inliers, for an operator asking why

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def hard_impostors(
    embeddings: np.ndarray,
    robots: Sequence[str],
    order: np.ndarray,
    *,
    frames: int = 200,
    seed: int = 0,
    stays: StayRule | None = None,
    same_place: np.ndarray | None = None,
) -> list[tuple[int, int]]:
    """``(i, j)``: for up to ``frames`` sampled frames ``i``, the most similar frame ``j`` of
    another robot, or of the same robot at least a twentieth of its frames (5 or more) away
    and outside ``i``'s stay (with ``stays``: a robot standing still for longer than that gap
    shows one place in all of it, and its own frames of the stop are no impostors; without a
    calibrated score to read stays by, only the gap applies). ``same_place``: ``m x 2``
    frames known to show one place (the fleet's revisit pairs): another robot's frames
    within the gap of ``i``'s known partners are its place, not its impostors (in a fleet
    the most similar frame of another robot is most often the true revisit)."""
    n = len(embeddings)
    codes, rank, gap = sequence_positions(robots, np.asarray(order))
    links = np.zeros((0, 2), np.int64) if same_place is None else np.asarray(same_place)
    links = np.concatenate([links, links[:, ::-1]]).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.permutation(n)[:frames])
    pairs = []
    for i in chosen:
        similarity = embeddings @ embeddings[i]
        same_place = (codes == codes[i]) & (np.abs(rank - rank[i]) < gap[i])
        for partner in links[links[:, 0] == i, 1]:
            same_place |= (codes == codes[partner]) & (np.abs(rank - rank[partner]) < gap)
        if stays is not None:
            same_place[_stay_both_ways(stays, embeddings, codes, rank, int(i))] = True
        similarity[same_place] = -np.inf
        j = int(np.argmax(similarity))
        if np.isfinite(similarity[j]):
            pairs.append((int(i), j))
    return pairs


def _stay_both_ways(
    rule: StayRule, embeddings: np.ndarray, codes: np.ndarray, rank: np.ndarray, i: int
) -> np.ndarray:
    """Frame ``i``'s stay both ways along its robot's sequence (row indices)."""
    robot = np.flatnonzero(codes == codes[i])
    by_rank = robot[np.argsort(rank[robot], kind="stable")]
    at = int(np.flatnonzero(by_rank == i)[0])
    sides = (by_rank[:at][::-1], by_rank[at + 1 :])  # nearest first before i, then after
    rows = [rule.stay(_reader(side), embeddings[i], lambda r: embeddings[r]) for side in sides]
    return np.concatenate(rows)


def midpoints(robots: Sequence[str], order: np.ndarray, pairs: list[tuple[int, int]]) -> list[int]:
    """For each pair of one robot's frames, the frame halfway between them along its sequence
    (-1 for a pair of two robots, or of neighbours with nothing in between)."""
    codes, rank, _ = sequence_positions(robots, np.asarray(order))
    at = {(int(c), int(r)): i for i, (c, r) in enumerate(zip(codes, rank, strict=True))}
    found = []
    for i, j in pairs:
        low, high = sorted((int(rank[i]), int(rank[j])))
        same = codes[i] == codes[j] and high - low > 1
        found.append(at[(int(codes[i]), (low + high) // 2)] if same else -1)
    return found


def one_stop(pair_inliers: int, midpoint_inliers: int, keypoints: int) -> bool:
    """Whether a pair of one robot's frames shows one place it never left: the pair is a near
    duplicate (``NEAR_DUPLICATE`` of the fewer keypoints are inliers) and the frame halfway
    between them matches the first at least half as well. A look-alike elsewhere is no near
    duplicate, or has unrelated frames in between; frames along a straight route overlap (the
    middle one matches better than the far one) but are no near duplicates (on
    gardenspoint_cohog200, 15-22 inliers of 275-392 keypoints). The embedding need not see a
    stop: on Nordland's dark stops, frames 250 inliers apart had calibrated cosines of 0.15-0.4.
    """
    return near_duplicate(pair_inliers, keypoints) and midpoint_inliers >= pair_inliers / 2


def near_duplicate(pair_inliers: int, keypoints: int) -> bool:
    """Two views of one spot: ``NEAR_DUPLICATE`` of the fewer keypoints (at least FLOOR) are
    inliers; only such a pair is worth checking halfway (:func:`one_stop`)."""
    return pair_inliers >= max(FLOOR, NEAR_DUPLICATE * keypoints)


def _reader(rows: np.ndarray) -> Callable[[int, int], np.ndarray]:
    """``(offset, limit)`` -> a slice of ``rows`` (a side of a frame's sequence, nearest first)."""
    return lambda offset, limit: rows[offset : offset + limit]


def fit_inlier_threshold(
    matcher: str, inliers: Sequence[int], one_stop_pairs: int = 0
) -> InlierThreshold:
    """The minimum just above the impostors' high quantile (at least :data:`FLOOR`)."""
    values = np.asarray(inliers, np.int64)
    if len(values) == 0:
        raise ValueError("no impostor pairs to calibrate the minimum inliers on")
    quantile = float(np.quantile(values, QUANTILE))
    minimum = max(FLOOR, int(np.floor(quantile)) + 1)
    return InlierThreshold(
        matcher=matcher,
        min_inliers=minimum,
        impostors=len(values),
        impostor_quantile=round(quantile, 2),
        impostor_max=int(values.max()),
        accepted_impostors=int((values >= minimum).sum()),
        one_stop_pairs=one_stop_pairs,
        impostor_median=float(np.median(values)),
        impostor_highest=tuple(int(v) for v in np.sort(values)[::-1][:10]),
    )
