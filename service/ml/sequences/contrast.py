"""Trajectory contrast: a frame's vector less the mean of the frames its robot took just before.

Along one traversal much of what a global descriptor encodes changes slowly: the season, the
weather, the light, the camera. Subtracting the mean of the robot's previous ``window`` frames
of the same sequence keeps what sets this place apart from the stretch around it (SeqSLAM's
local contrast enhancement, applied to the embedding rather than to the difference matrix), so
frames of two traversals under different conditions compare on what they show, not on how the
day looked. Causal on both sides: a stored frame is contrasted with the frames before it, as a
query can only be.

The window (10 frames) was chosen on the first halves of the development sets' queries
(nordland_64x32 XFeat, gardenspoint_cohog200 DISK: calibrated single-frame R@1 0.32 -> 0.51 and
0.915 -> 0.965 on the whole sets); the figures are in benchmarks/RESULTS.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.ml.sequences.trajectories import Trajectories

DEFAULT_CONTRAST_FRAMES = 10
BLOCK = 4096  # frames contrasted at once


def context_positions(trajectories: Trajectories, frames: np.ndarray, window: int) -> np.ndarray:
    """``len(frames) x window``: the frames taken just before each of ``frames`` in its
    sequence, nearest first, -1 where the sequence has fewer."""
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    offsets = -np.arange(1, window + 1, dtype=np.int64)
    return trajectories.step(frames[:, None], offsets[None, :])


def contrast(vectors: np.ndarray, context_means: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Unit ``vectors - context_means`` (float32); zero rows where a frame has no context
    (``counts`` 0) or nothing is left after the subtraction: such a frame never looks alike."""
    difference = np.asarray(vectors, np.float32) - np.asarray(context_means, np.float32)
    difference[np.asarray(counts) == 0] = 0.0
    norms = np.linalg.norm(difference, axis=1, keepdims=True)
    return np.where(norms > 1e-6, difference / np.maximum(norms, 1e-12), 0.0).astype(np.float32)


def contrasted_frames(
    vectors_at: Callable[[np.ndarray], np.ndarray],
    trajectories: Trajectories,
    frames: np.ndarray,
    window: int,
) -> np.ndarray:
    """The contrasted vectors of ``frames`` (positions), each against its own context;
    ``vectors_at(positions)`` gives the frames' unit vectors. Summed one step back at a time,
    so memory stays at two ``block x dim`` arrays whatever the window."""
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    out = []
    for start in range(0, len(frames), BLOCK):
        chunk = frames[start : start + BLOCK]
        own = vectors_at(chunk)
        sums = np.zeros(own.shape, np.float32)
        counts = np.zeros(len(chunk), np.int64)
        for back in range(1, window + 1):
            before = trajectories.step(chunk, np.full(len(chunk), -back))
            held = before >= 0
            if not held.any():
                break
            sums[held] += vectors_at(before[held])
            counts += held
        out.append(contrast(own, sums / np.maximum(counts, 1)[:, None], counts))
    return np.concatenate(out) if out else np.zeros((0, 0), np.float32)


def contrasted_query(newest: np.ndarray, before: np.ndarray) -> np.ndarray | None:
    """The newest frame's contrasted vector against ``before`` (its robot's previous frames'
    unit vectors, at most the window); None without any."""
    if len(before) == 0:
        return None
    mean = np.asarray(before, np.float32).mean(axis=0, keepdims=True)
    vector = contrast(np.asarray(newest, np.float32)[None], mean, np.array([len(before)]))[0]
    return vector if np.any(vector) else None
