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
    seeds: best map matches of each query frame that vote for candidates.
    neighbourhood: reference frames either side of each vote's landing place also voted for.
    candidates: places scored exactly: those with the most votes (summed z-scores of the
        seeds that land on them along one speed: a sparse pre-score of the same sum).
    seed_frames: query frames, newest first, whose seeds vote (0: all). The service uses 1:
        the newest frame's own search hits, so no past frame is searched again and two
        replicas at one revision propose the same candidates.
    contrast_window: 0: each similarity is standardised against the whole map (z-score of
        the query frame's row); w > 0: against the w + 1 reference frames around the aligned
        one along its trajectory (SeqSLAM's local contrast enhancement; OpenSeqSLAM uses 10).
    """

    length: int = 10
    speeds: tuple[float, ...] = (0.8, 0.9, 1.0, 1.1, 1.25)
    reverse: bool = False
    seeds: int = 50
    neighbourhood: int = 1
    candidates: int = 64
    seed_frames: int = 0
    contrast_window: int = 0

    def __post_init__(self) -> None:
        if self.length < 1:
            raise ValueError(f"sequence length must be at least 1, got {self.length}")
        if not self.speeds or any(v <= 0 for v in self.speeds):
            raise ValueError(f"speeds must be positive, got {self.speeds}")
        if (
            self.seeds < 1
            or self.neighbourhood < 0
            or self.candidates < 1
            or self.contrast_window < 0
            or self.seed_frames < 0
        ):
            raise ValueError(
                "seeds and candidates must be >= 1; neighbourhood, seed_frames and "
                "contrast_window >= 0"
            )

    @property
    def signed_speeds(self) -> np.ndarray:
        speeds = np.array(sorted(set(self.speeds)), dtype=np.float64)
        return np.concatenate([speeds, -speeds]) if self.reverse else speeds


class MapMoments:
    """First and second moments of the map's vectors, kept up to date as frames come and go.

    ``mean(q) = q . m`` and ``var(q) = q^T M q - mean(q)^2`` with ``m`` the mean vector and ``M``
    the mean outer product: each query frame's similarity row over the whole map, standardised
    without computing it. Frames added or removed since the last fold are kept aside and
    counted exactly (``(q . p)^2`` each), so one insertion costs ``O(d)`` and the ``d x d``
    update runs once per ``fold_every`` frames. Rebuilt from the stored vectors at start: a
    cache, never the truth.
    """

    def __init__(self, dim: int, fold_every: int = 256) -> None:
        self.count = 0
        self.fold_every = fold_every
        self._sum = np.zeros(dim, dtype=np.float64)
        self._outer = np.zeros((dim, dim), dtype=np.float64)
        self._pending: list[np.ndarray] = []
        self._signs: list[float] = []

    @classmethod
    def of(cls, vectors: np.ndarray) -> MapMoments:
        moments = cls(vectors.shape[1])
        moments.add(vectors)
        return moments

    def _change(self, vectors: np.ndarray, sign: float) -> None:
        v = np.asarray(vectors, dtype=np.float64).reshape(-1, len(self._sum))
        self.count += int(sign) * len(v)
        self._sum += sign * v.sum(axis=0)
        if len(v) >= self.fold_every:
            self._outer += sign * (v.T @ v)
        else:
            self._pending.extend(v)
            self._signs.extend([sign] * len(v))
            if len(self._pending) >= self.fold_every:
                self._fold()

    def _fold(self) -> None:
        pending = np.stack(self._pending)
        self._outer += pending.T @ (pending * np.array(self._signs)[:, None])
        self._pending, self._signs = [], []

    def add(self, vectors: np.ndarray) -> None:
        self._change(vectors, 1.0)

    def remove(self, vectors: np.ndarray) -> None:
        if len(np.atleast_2d(vectors)) > self.count:
            raise ValueError(f"removing {len(vectors)} vectors from a map of {self.count}")
        self._change(vectors, -1.0)

    def row_stats(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``n x d`` query vectors -> mean and standard deviation (``n`` each) of each one's
        cosine similarity to every map vector (std floored to keep z finite)."""
        if self.count <= 0:
            raise ValueError("the map is empty")
        q = np.asarray(queries, dtype=np.float64).reshape(-1, len(self._sum))
        mean = q @ self._sum / self.count
        second = ((q @ self._outer) * q).sum(axis=1)
        if self._pending:
            dots = q @ np.stack(self._pending).T
            second += (dots**2) @ np.array(self._signs)
        second /= self.count
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
        aligned_z: every query frame's standardised similarity with its aligned map frame (the
            score's terms), oldest first; 0 where none aligned.
    """

    reference: int
    score: float
    length: int
    speed: float
    aligned: tuple[int, ...]
    similarity: float
    aligned_z: tuple[float, ...]

    @property
    def newest_z(self) -> float:
        """The newest frame's term: how much that frame alone favours ``reference``."""
        return self.aligned_z[-1] if self.aligned_z else 0.0


def propose_candidates(
    seeds: Sequence[np.ndarray],
    trajectories: Trajectories,
    settings: SequenceSettings,
    eligible: Callable[[np.ndarray], np.ndarray] | None = None,
    seed_scores: Sequence[np.ndarray] | None = None,
) -> np.ndarray:
    """Map frames worth scoring for the newest query frame, most voted first.

    ``seeds[j]`` are the best map matches of query frame j (oldest first), ``seed_scores[j]``
    their z-scores (None: one vote each). A seed of the frame ``a`` steps old votes for the
    frames ``round(a * v)`` places after it (and their neighbours), for every speed; a place's
    votes are summed per speed, and the ``settings.candidates`` places with the best speed's
    sum are kept.
    """
    n = len(seeds)
    speeds = settings.signed_speeds
    spread = np.arange(-settings.neighbourhood, settings.neighbourhood + 1)
    keys: list[np.ndarray] = []
    weights: list[np.ndarray] = []
    for j, frames in enumerate(seeds):
        frames = np.asarray(frames, dtype=np.int64)[: settings.seeds]
        if not len(frames):
            continue
        score = (
            np.ones(len(frames))
            if seed_scores is None
            else np.asarray(seed_scores[j], dtype=np.float64)[: len(frames)]
        )
        age = n - 1 - j
        ahead = np.rint(age * speeds).astype(np.int64)  # S
        shifts = ahead[:, None] + spread[None, :]  # S x W
        landed = trajectories.step(frames[:, None, None], shifts[None, :, :])  # s x S x W
        speed_index = np.broadcast_to(np.arange(len(speeds))[None, :, None], landed.shape)
        ok = landed >= 0
        keys.append(landed[ok] * len(speeds) + speed_index[ok])
        weights.append(np.broadcast_to(score[:, None, None], landed.shape)[ok])
    if not keys:
        return np.zeros(0, np.int64)
    unique_keys, inverse = np.unique(np.concatenate(keys), return_inverse=True)
    votes = np.bincount(inverse, weights=np.concatenate(weights))
    frames = unique_keys // len(speeds)
    if eligible is not None and len(frames):
        allowed = eligible(frames)
        frames, votes = frames[allowed], votes[allowed]
    order = np.lexsort((frames, -votes))  # best vote first; a frame keeps its best speed
    frames = frames[order]
    _, first = np.unique(frames, return_index=True)
    return frames[np.sort(first)][: settings.candidates]


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
    half = settings.contrast_window // 2
    around = aligned[..., None]
    if half:  # every aligned frame's window along its trajectory: C x S x n x (2 half + 1)
        around = trajectories.step(around, np.arange(-half, half + 1))
        around = np.where(aligned[..., None] >= 0, around, -1)
        if eligible is not None:
            flat = around.ravel()
            ok = flat >= 0
            ok[ok] = eligible(flat[ok])
            around = np.where(ok.reshape(around.shape), around, -1)
    used_frames, inverse = _unique_frames(around, len(trajectories))
    similarity = np.zeros((n, len(used_frames) + 1), dtype=np.float64)  # last column: none
    if len(used_frames):
        similarity[:, :-1] = np.asarray(queries, dtype=np.float32) @ vectors(used_frames).T
    rows = (n - 1 - ages)[None, None, :]
    if half:
        window_sims = similarity[rows[..., None], inverse]  # C x S x n x W
        inside = around >= 0
        count = np.maximum(inside.sum(axis=3), 1)
        local_mean = np.where(inside, window_sims, 0.0).sum(axis=3) / count
        local_var = (
            np.where(inside, (window_sims - local_mean[..., None]) ** 2, 0.0).sum(axis=3) / count
        )
        centre = similarity[rows, inverse[..., half]]
        z_aligned = (centre - local_mean) / np.maximum(np.sqrt(local_var), 1e-3)
        z_aligned = np.where(aligned >= 0, z_aligned, 0.0)
        inverse = inverse[..., half]
    else:
        inverse = inverse[..., 0]
        z = (similarity - mean[:, None]) / std[:, None]  # n x U, rows oldest first
        z_aligned = np.where(aligned >= 0, z[rows, inverse], 0.0)
    length = (aligned >= 0).sum(axis=2)
    score = z_aligned.sum(axis=2) / np.sqrt(np.maximum(length, 1))
    score = np.where(aligned[:, :, 0] >= 0, score, -np.inf)  # the newest frame must align
    # equal scores (short sequences align alike at nearby speeds): the speed nearest 1 wins
    preference = np.argsort(np.abs(np.log(np.abs(speeds))), kind="stable")
    best_speed = preference[np.argmax(score[:, preference], axis=1)]
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
                aligned_z=tuple(float(z) for z in z_aligned[c, s, ::-1]),
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
    stats = moments.row_stats(queries) if row_stats is None else row_stats
    seed_lists = [np.asarray(f, dtype=np.int64)[: settings.seeds] for f in seeds]
    if settings.seed_frames:
        older = max(len(seed_lists) - settings.seed_frames, 0)
        seed_lists = [np.zeros(0, np.int64)] * older + seed_lists[older:]
    sizes = [len(f) for f in seed_lists]
    seed_scores: list[np.ndarray] = []
    if sum(sizes):
        seed_vectors = vectors(np.concatenate(seed_lists))
        rows = np.repeat(np.arange(len(seed_lists)), sizes)
        sims = np.einsum("nd,nd->n", seed_vectors, np.asarray(queries)[rows])
        z = (sims - stats[0][-len(queries) :][rows]) / stats[1][-len(queries) :][rows]
        seed_scores = np.split(z, np.cumsum(sizes)[:-1])
    candidates = propose_candidates(
        seed_lists, trajectories, settings, eligible, seed_scores or None
    )
    return score_candidates(
        queries,
        candidates,
        vectors,
        trajectories,
        stats,
        settings,
        eligible=eligible,
        top=top,
    )
