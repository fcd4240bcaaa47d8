"""A robot's current stay: its newest frames that still show the place it is asking about.

A robot that stands still (a train at a station, a robot waiting at a door) keeps sending frames
of one place. The recent-frame exclusion (``exclude_recent_frames`` / ``_seconds``) covers a
fixed window; once the robot has stood longer than that, its own frames from the start of the
stop fall outside it and verify perfectly: a loop with itself that odometry already knows, which
a SLAM back end must not receive. A loop with its own past needs evidence that the robot left
the place in between.

The stay is read from the robot's frames newest first: each is compared with the query frame
by its calibrated score against impostors, which must reach ``loop_score_min`` (a similarity that
rare among pairs of different places shows the same place; no ``log10(frames)`` is added, as
each frame is judged on its own, not as the best of a search), and
the walk ends at the first ``BREAK`` frames in a row that do not resemble the query (the robot
was elsewhere then). Everything newer than that is the stay and never matches; everything older
may. On an uncalibrated model version there is no bar that says "as alike as the same place"
(the cosine of unrelated frames may exceed any fixed threshold), so no stay is recognised and
only the recent-frame exclusion applies.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy.orm import Session

from service.app.filters import QueryFilter
from service.app.sequence_map import SequenceMap, SequenceMaps
from service.app.state import LoadedAtlas
from service.config import Settings
from service.storage import repository as repo

# Consecutive frames unlike the query that end a stay: one odd frame (a person passing in front
# of the camera) is not evidence that the robot left.
BREAK = 2
# The walk reads the robot's frames in blocks, doubling from the first: a moving robot's stay
# ends within the first block, a stopped robot's is read up to MAX_FRAMES back.
FIRST_BLOCK = 32
MAX_FRAMES = 4096


def current_stay(
    *,
    own_frames: Callable[[int, int], np.ndarray],
    query: np.ndarray,
    vectors: Callable[[np.ndarray], np.ndarray],
    resembles: Callable[[np.ndarray], np.ndarray],
    max_frames: int = MAX_FRAMES,
) -> np.ndarray:
    """Ids of the robot's newest frames that form its current stay (newest first).

    Args:
        own_frames: ``(offset, limit)`` -> the robot's frame ids newest first (ids grow with
            arrival), ``limit`` of them from ``offset``.
        query: the query frame's (unit) vector.
        vectors: the index's stored vectors of frame ids (rows in the same order).
        resembles: for an array of cosine similarities to the query, whether each frame shows
            the query's place.
        max_frames: read no further back than this many of the robot's frames.
    """
    stay: list[int] = []
    pending: list[int] = []  # unlike frames not yet known to lie inside the stay
    offset, block = 0, FIRST_BLOCK
    while offset < max_frames:
        ids = own_frames(offset, min(block, max_frames - offset))
        if not len(ids):
            break
        alike = resembles(vectors(ids) @ np.asarray(query, np.float32))
        for frame_id, same in zip(ids.tolist(), alike.tolist(), strict=True):
            if not same:
                pending.append(frame_id)
                if len(pending) >= BREAK:
                    return np.array(stay, np.int64)
                continue
            stay += [*pending, frame_id]  # an odd frame between two alike ones belongs to it
            pending = []
        offset += len(ids)
        block *= 2
    return np.array(stay, np.int64)


def robot_stay(
    session: Session,
    state: LoadedAtlas,
    maps: SequenceMaps,
    settings: Settings,
    query: np.ndarray,
    query_filter: QueryFilter,
) -> np.ndarray:
    """The asking robot's current stay for a query frame's vector: empty without a robot whose
    own frames may match, with ``exclude_stay`` off, or on an uncalibrated version."""
    robot = query_filter.robot_id
    if robot is None or query_filter.robots == "others" or not settings.exclude_stay:
        return np.zeros(0, np.int64)
    if not state.model.scores:
        return np.zeros(0, np.int64)  # no bar says "as alike as the same place"
    bar = settings.loop_score_min

    def resembles(similarities: np.ndarray) -> np.ndarray:
        """As rare among impostor pairs as the loop score's minimum (one frame, not a search's
        best: no log10(frames))."""
        alike = np.zeros(len(similarities), bool)
        known = np.isfinite(similarities)
        scores = state.model.score(similarities[known].astype(np.float64))
        alike[known] = np.asarray(scores) >= bar
        return alike

    def own_frames(offset: int, limit: int) -> np.ndarray:
        return repo.robot_frames_newest_first(
            session, atlas_id=state.atlas_id, robot_id=robot, offset=offset, limit=limit
        )

    with maps.hold(session, state) as view:  # the index's vectors, cached per process
        return current_stay(
            own_frames=own_frames,
            query=query,
            vectors=lambda ids: _held_vectors(view, ids),
            resembles=resembles,
        )


def _held_vectors(view: SequenceMap, ids: np.ndarray) -> np.ndarray:
    """The map's vectors of ``ids``; rows of NaN for frames the index does not hold yet (a
    replica catching up): they resemble nothing."""
    positions = view.positions(ids)
    rows = np.full((len(ids), view.vectors.shape[1]), np.nan, np.float32)
    held = positions >= 0
    rows[held] = view.lookup(positions[held])
    return rows
