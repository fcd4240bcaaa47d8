"""The numerical pieces of a calibration's fit: aggregating frames into one matrix, branch
spreads and the standardised fusion weight, held-out stretches, samples and rotations."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from service.ml.aggregation import l2_normalize
from service.ml.aggregators import Aggregator
from service.ml.impostors import sequence_positions


def aggregate_frames(
    aggregator: Aggregator, descriptors: Sequence[np.ndarray], scores: Sequence[np.ndarray]
) -> np.ndarray:
    """``n x aggregator.dim`` raw local vectors of ``n`` frames, each written straight into
    one array (a 10,000-frame VLAD matrix is 650 MB: no list of rows to stack). Descriptors go
    to the aggregator as stored (float16), which converts them itself."""
    out = np.empty((len(descriptors), aggregator.dim), np.float32)
    for row, (d, s) in enumerate(zip(descriptors, scores, strict=True)):
        out[row] = aggregator.aggregate(np.asarray(d), np.asarray(s, np.float32))
    return out


class StageClock:
    """Wall and CPU seconds of consecutive stages, each closed by :meth:`lap`."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._mark = (time.perf_counter(), time.process_time())

    def lap(self, stage: str) -> None:
        """Close ``stage``: the seconds since the previous lap (or the clock's start)."""
        now = (time.perf_counter(), time.process_time())
        self.wall[stage] = now[0] - self._mark[0]
        self.cpu[stage] = now[1] - self._mark[1]
        self._mark = now


def standardised_alpha(alpha: float, spread: tuple[float, float] | None) -> float:
    """The weight ``a`` of ``[a D, (1 - a) R]`` under which each branch's cosine divided by its
    impostor spread gets the share ``alpha^2 : (1 - alpha)^2`` (``alpha`` itself without spreads,
    or at 0 and 1)."""
    if spread is None or alpha in (0.0, 1.0):
        return alpha
    local, global_ = spread
    ratio = alpha / (1.0 - alpha) * float(np.sqrt(global_ / local))
    return ratio / (1.0 + ratio)


def cosine_weights(a: float) -> tuple[float, float]:
    """Each branch's share of the fused cosine that ``[a D, (1 - a) R]`` gives (unit branches)."""
    total = a * a + (1.0 - a) ** 2
    return a * a / total, (1.0 - a) ** 2 / total


def impostor_spread(cosines: np.ndarray) -> float:
    """Standard deviation of impostor cosines (floored: a constant branch must not divide by 0)."""
    return max(float(np.std(cosines)) if len(cosines) else 0.0, 1e-4)


def spread_of(value: object) -> tuple[float, float] | None:
    """The spreads as saved (None in calibrations saved before they were measured)."""
    if value is None:
        return None
    if not (isinstance(value, list) and len(value) == 2):
        raise ValueError(f"bad branch spreads {value!r}")
    local, global_ = (float(v) for v in value)
    if not (local > 0.0 and global_ > 0.0):
        raise ValueError(f"bad branch spreads {value!r}")
    return local, global_


def held_out_stretches(robots: Sequence[str], order: np.ndarray, share: float) -> np.ndarray:
    """A mask of about ``share`` of the frames, in stretches as long as the impostor gap (a
    twentieth of each robot's sequence, at least 5 frames): every ``1 / share``-th stretch."""
    _, rank, gap = sequence_positions(robots, order)
    period = max(2, int(round(1.0 / share)))
    held = (rank // gap) % period == period // 2
    if not held.any() or held.all():  # too short a sequence for stretches: single frames
        held = np.arange(len(rank)) % period == 0
    return np.asarray(held, bool)


def rotated_onto(source: np.ndarray, target: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``source`` rows mapped into ``target``'s coordinates by the orthogonal map that best
    carries ``source[rows]`` to ``target[rows]`` (orthogonal Procrustes), unit again."""
    u, _, vt = np.linalg.svd(target[rows].T @ source[rows], full_matrices=False)
    return l2_normalize(source @ (u @ vt).T)


def rows_of(matrix: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``matrix``'s distinct ``rows`` in storage order: ``matrix`` itself, not a copy, when
    they are all of them (a whitening does not depend on the order of its vectors)."""
    return matrix if len(rows) == len(matrix) else matrix[np.sort(rows)]


def descriptor_sample(
    descriptors: Sequence[np.ndarray], size: int, rng: np.random.Generator
) -> np.ndarray:
    """Up to ``size`` descriptors drawn evenly across frames (float32), in one pass."""
    per_frame = max(1, int(np.ceil(size / max(len(descriptors), 1))))
    chunks, dim = [], 0
    for d in descriptors:  # one pass: a job reads each frame's blob once here
        dim = d.shape[1]
        if len(d) == 0:
            continue
        take = rng.choice(len(d), size=min(per_frame, len(d)), replace=False)
        chunks.append(np.asarray(d[np.sort(take)], np.float32))
    if not chunks:
        return np.zeros((0, dim), np.float32)
    sample = np.concatenate(chunks)
    if len(sample) > size:
        sample = sample[rng.choice(len(sample), size=size, replace=False)]
    return sample
