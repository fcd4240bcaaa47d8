"""Sequence scoring in the spirit of SeqSLAM: a place is scored by how well the robot's last few
frames match a stretch of a reference trajectory, not by its newest frame alone.

Each query frame's similarities are standardised against the whole map (z-scores, from
:class:`MapMoments`: exact mean and spread of one vector's cosine to every map vector in
``O(d^2)``), so a frame that resembles everything counts for little. A candidate reference ``c``
(aligned with the newest query frame) is scored at each relative speed ``v`` by summing the
z-scores of query frame ``age a`` against the reference ``round(a * v)`` places before ``c``
along its own sequence, divided by the square root of the frames used (so scores of sequences of
different lengths share one null distribution). Candidates come only from the few best matches
of each query frame, moved forward along their trajectories to the newest frame, and their
neighbours: the cost depends on L and k, never on the map's size.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from service.ml.sequences.trajectories import Trajectories

VectorLookup = Callable[[np.ndarray], np.ndarray]
"""Map frame indices (``M``) -> their unit vectors (``M x d``)."""


@dataclass(frozen=True)
class SequenceSettings:
    """Attributes:
    length: query frames used at most (L), the newest included.
    speeds: reference frames passed per query frame (SeqSLAM's velocity range).
    reverse: also try traversing the reference the other way.
    seeds: best map matches of each query frame that propose candidates.
    neighbourhood: reference frames either side of each proposed candidate also scored.
    """

    length: int = 10
    speeds: tuple[float, ...] = (0.8, 0.9, 1.0, 1.1, 1.25)
    reverse: bool = False
    seeds: int = 5
    neighbourhood: int = 1

    def __post_init__(self) -> None:
        if self.length < 1:
            raise ValueError(f"sequence length must be at least 1, got {self.length}")
        if not self.speeds or any(v <= 0 for v in self.speeds):
            raise ValueError(f"speeds must be positive, got {self.speeds}")
        if self.seeds < 1 or self.neighbourhood < 0:
            raise ValueError("seeds must be >= 1 and neighbourhood >= 0")

    @property
    def signed_speeds(self) -> np.ndarray:
        speeds = np.array(sorted(set(self.speeds)), dtype=np.float64)
        return np.concatenate([speeds, -speeds]) if self.reverse else speeds


class MapMoments:
    """First and second moments of the map's vectors, kept up to date as frames come and go.

    ``mean(q) = q . m`` and ``var(q) = q^T M q - mean(q)^2`` with ``m`` the mean vector and ``M``
    the mean outer product: each query frame's similarity row over the whole map, standardised
    without computing it. Rebuilt from the stored vectors at start; a cache, never the truth.
    """

    def __init__(self, dim: int) -> None:
        self.count = 0
        self._sum = np.zeros(dim, dtype=np.float64)
        self._outer = np.zeros((dim, dim), dtype=np.float64)
        self._normalised: tuple[np.ndarray, np.ndarray] | None = None  # float32, for BLAS

    @classmethod
    def of(cls, vectors: np.ndarray) -> MapMoments:
        moments = cls(vectors.shape[1])
        moments.add(vectors)
        return moments

    def add(self, vectors: np.ndarray) -> None:
        v = np.asarray(vectors, dtype=np.float64).reshape(-1, len(self._sum))
        self.count += len(v)
        self._sum += v.sum(axis=0)
        self._outer += v.T @ v
        self._normalised = None

    def remove(self, vectors: np.ndarray) -> None:
        v = np.asarray(vectors, dtype=np.float64).reshape(-1, len(self._sum))
        if len(v) > self.count:
            raise ValueError(f"removing {len(v)} vectors from a map of {self.count}")
        self.count -= len(v)
        self._sum -= v.sum(axis=0)
        self._outer -= v.T @ v
        self._normalised = None

    def row_stats(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``n x d`` query vectors -> mean and standard deviation (``n`` each) of each one's
        cosine similarity to every map vector (std floored to keep z finite)."""
        if self.count == 0:
            raise ValueError("the map is empty")
        if self._normalised is None:
            self._normalised = (
                (self._sum / self.count).astype(np.float32),
                (self._outer / self.count).astype(np.float32),
            )
        mean_vector, second_moment = self._normalised
        q = np.asarray(queries, dtype=np.float32)
        mean = (q @ mean_vector).astype(np.float64)
        second = ((q @ second_moment) * q).sum(axis=1, dtype=np.float64)
        std = np.sqrt(np.maximum(second - mean**2, 0.0))
        return mean, np.maximum(std, 1e-6)


@dataclass(frozen=True)
class SequenceMatch:
    """One reference place scored against the query sequence.

    Attributes:
        reference: map frame aligned with the newest query frame.
        score: summed z-scores along the alignment / sqrt(length) (higher is better).
        length: query frames that had a reference frame to align with.
        speed: relative speed of the best alignment (negative: reverse traversal).
        aligned: map frame aligned with each query frame, oldest first; -1 where none.
        similarity: plain cosine of the newest query frame and ``reference``.
    """

    reference: int
    score: float
    length: int
    speed: float
    aligned: tuple[int, ...]
    similarity: float


def propose_candidates(
    seeds: Sequence[np.ndarray],
    trajectories: Trajectories,
    settings: SequenceSettings,
    eligible: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Map frames worth scoring for the newest query frame.

    ``seeds[j]`` are the best map matches of query frame j (oldest first). A seed of the frame
    ``a`` steps old proposes the frames ``round(a * v)`` places after it, for every speed, plus
    their neighbours.
    """
    n = len(seeds)
    speeds = settings.signed_speeds
    spread = np.arange(-settings.neighbourhood, settings.neighbourhood + 1)
    found: list[np.ndarray] = []
    for j, frames in enumerate(seeds):
        frames = np.asarray(frames, dtype=np.int64)[: settings.seeds]
        if not len(frames):
            continue
        age = n - 1 - j
        ahead = np.unique(np.rint(age * speeds).astype(np.int64))
        shifts = (ahead[:, None] + spread[None, :]).ravel()
        found.append(trajectories.step(frames[:, None], shifts[None, :]).ravel())
    if not found:
        return np.zeros(0, np.int64)
    candidates = np.unique(np.concatenate(found))
    candidates = candidates[candidates >= 0]
    if eligible is not None and len(candidates):
        candidates = candidates[eligible(candidates)]
    return candidates


def score_candidates(
    queries: np.ndarray,
    candidates: np.ndarray,
    vectors: VectorLookup,
    trajectories: Trajectories,
    row_stats: tuple[np.ndarray, np.ndarray],
    settings: SequenceSettings,
    *,
    eligible: Callable[[np.ndarray], np.ndarray] | None = None,
    top: int | None = None,
) -> list[SequenceMatch]:
    """Score ``candidates`` (map frames aligned with the newest query frame), best first.

    Args:
        queries: ``n x d`` unit vectors of the query sequence, oldest first, newest last
            (only the last ``settings.length`` are used).
        vectors: looks up map frames' unit vectors.
        row_stats: mean and std of each query frame's similarity over the map
            (:meth:`MapMoments.row_stats`).
        eligible: map frames that may be aligned (e.g. not the asking robot's recent frames).
        top: keep this many matches (None: all).
    """
    queries = np.asarray(queries)[-settings.length :]
    mean, std = (np.asarray(s)[-settings.length :] for s in row_stats)
    candidates = np.asarray(candidates, dtype=np.int64)
    if not len(candidates) or not len(queries):
        return []
    n = len(queries)
    speeds = settings.signed_speeds
    ages = np.arange(n)  # age 0 = newest = row n-1
    offsets = -np.rint(speeds[:, None] * ages[None, :]).astype(np.int64)  # S x n
    aligned = trajectories.step(candidates[:, None, None], offsets[None, :, :])  # C x S x n
    if eligible is not None:
        flat = aligned.ravel()
        ok = flat >= 0
        ok[ok] = eligible(flat[ok])
        aligned = np.where(ok.reshape(aligned.shape), aligned, -1)
    used_frames, inverse = _unique_frames(aligned, len(trajectories))
    similarity = np.zeros((n, len(used_frames) + 1), dtype=np.float64)  # last column: none
    if len(used_frames):
        similarity[:, :-1] = np.asarray(queries, dtype=np.float32) @ vectors(used_frames).T
    z = (similarity - mean[:, None]) / std[:, None]  # n x U, rows oldest first
    rows = (n - 1 - ages)[None, None, :]
    z_aligned = np.where(aligned >= 0, z[rows, inverse], 0.0)
    length = (aligned >= 0).sum(axis=2)
    score = z_aligned.sum(axis=2) / np.sqrt(np.maximum(length, 1))
    score = np.where(aligned[:, :, 0] >= 0, score, -np.inf)  # the newest frame must align
    best_speed = np.argmax(score, axis=1)
    best = score[np.arange(len(candidates)), best_speed]
    order = np.argsort(-best, kind="stable")
    if top is not None:
        order = order[:top]
    newest_column = inverse[:, 0, 0]
    matches = []
    for c in order:
        if not np.isfinite(best[c]):
            continue
        s = best_speed[c]
        matches.append(
            SequenceMatch(
                reference=int(candidates[c]),
                score=float(best[c]),
                length=int(length[c, s]),
                speed=float(speeds[s]),
                aligned=tuple(int(f) for f in aligned[c, s, ::-1]),
                similarity=float(similarity[n - 1, newest_column[c]]),
            )
        )
    return matches


def _unique_frames(frames: np.ndarray, total: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct frames >= 0 of ``frames`` (sorted) and each entry's column among them
    (-1 entries get the column after the last). A mask over the map instead of a sort: linear
    in the map's size with a tiny constant, far cheaper than sorting the entries."""
    mask = np.zeros(total + 1, dtype=bool)
    mask[frames] = True  # -1 marks the extra last slot
    present = mask[:-1]
    used = np.flatnonzero(present)
    column = np.cumsum(present) - 1
    lookup = np.append(column, len(used))
    return used, lookup[frames]


def match_sequence(
    queries: np.ndarray,
    seeds: Sequence[np.ndarray],
    vectors: VectorLookup,
    trajectories: Trajectories,
    moments: MapMoments,
    settings: SequenceSettings,
    *,
    eligible: Callable[[np.ndarray], np.ndarray] | None = None,
    top: int | None = 10,
    row_stats: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[SequenceMatch]:
    """The whole step for one observation: propose candidates from every query frame's seeds,
    standardise against the map, score along the reference trajectories, best first.

    ``queries`` (``n x d``, oldest first) and ``seeds`` (one array of map frames per query
    frame, best first) are cut to the last ``settings.length`` frames. ``row_stats`` may bring
    the query frames' map statistics from a cache (else ``moments`` computes them).
    """
    queries = np.asarray(queries)[-settings.length :]
    seeds = list(seeds)[-settings.length :]
    if len(seeds) != len(queries):
        raise ValueError(f"{len(queries)} query frames but {len(seeds)} seed lists")
    candidates = propose_candidates(seeds, trajectories, settings, eligible)
    return score_candidates(
        queries,
        candidates,
        vectors,
        trajectories,
        moments.row_stats(queries) if row_stats is None else row_stats,
        settings,
        eligible=eligible,
        top=top,
    )
