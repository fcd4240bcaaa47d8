"""The online replay's application call: one robot's frames through the service's own observe
path (:meth:`AtlasService.observe_features`: search, sequence scoring from the database, then
the insert), on a temporary SQLite atlas, from the evaluation's cached features.

Frames keep their order as timestamps one second apart; where the trajectory starts a new run
(a second traversal) the clock jumps well past the service's sequence gap, so the service cuts
the sequence there as the trajectory does.

:func:`replay_atlas` and :func:`observe_frame` are the one replay loop's pieces: the retrieval
rows (:func:`service_observations`: no verification, no calibration) and the served row
(:mod:`service.evaluation.online_served`) both drive them.
"""

from __future__ import annotations

import copy
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from service.app.catalog import AtlasService
from service.app.ingest import FrameFields
from service.app.results import QueryResult
from service.config import Settings
from service.evaluation.feature_cache import CachedFeatures
from service.evaluation.loop_ground_truth import Trajectory
from service.ml.features import FrameFeatures
from service.ml.pipeline import FeaturePipeline

ATLAS, SUBMAP, ROBOT = "online", "route", "robot"
RUN_GAP_SECONDS = 10_000.0  # between two runs of the trajectory: always a new sequence


def frame_times(trajectory: Trajectory, count: int) -> np.ndarray:
    """One second per frame, and a long pause before each new run."""
    runs = np.cumsum(np.asarray(trajectory.starts, dtype=bool)[:count])
    return np.arange(count, dtype=np.float64) + RUN_GAP_SECONDS * runs


def replay_settings(
    data_dir: Path,
    *,
    exclude_recent: int,
    consistency: int,
    served: bool,
    adapt_after_pairs: int | None = None,
) -> Settings:
    """The replay atlas's settings: the protocol's exclusion (the robot's last frames, not
    seconds) and consistency. ``served``: everything else at the service's defaults
    (verification, the loop decision, calibration milestones, automatic adaptation);
    otherwise retrieval only (no verification, no automatic calibration or adaptation).
    ``adapt_after_pairs``: automatic adaptation after that many revisit pairs
    (``LOOPNET_ADAPT_AFTER_PAIRS``; 0: off; None: as ``served`` says)."""
    overrides: dict[str, Any] = {} if served else {"verify_top": 0, "calibration_milestones": ""}
    if adapt_after_pairs is not None or not served:
        overrides["adapt_after_pairs"] = adapt_after_pairs or 0
    return Settings(
        data_dir=data_dir,
        exclude_recent_frames=exclude_recent,
        exclude_recent_seconds=0.0,
        consistency_frames=consistency,
        torch_threads=torch.get_num_threads(),  # the caller's own, kept
        **overrides,
    )


@contextmanager
def replay_atlas(
    trajectory: Trajectory,
    pipeline: FeaturePipeline,
    *,
    alpha: float,
    exclude_recent: int,
    consistency: int,
    served: bool,
    adapt_after_pairs: int | None = None,
) -> Iterator[AtlasService]:
    """A started service on a temporary SQLite atlas (``ATLAS``, one submap) whose untrained
    heads fuse at ``alpha``; stopped and deleted on exit."""
    from service.runtime import Runtime

    # the atlas's untrained heads fuse at the method's alpha (a copy: the CNNs are shared)
    pipeline = copy.copy(pipeline)
    pipeline.preset = replace(pipeline.preset, alpha=alpha)
    with tempfile.TemporaryDirectory(prefix="loopnet-online-") as data_dir:
        settings = replay_settings(
            Path(data_dir),
            exclude_recent=exclude_recent,
            consistency=consistency,
            served=served,
            adapt_after_pairs=adapt_after_pairs,
        )
        runtime = Runtime(settings, pipeline)
        runtime.start(background=False)
        try:
            service = runtime.service
            service.create_atlas(ATLAS, description=f"online replay of {trajectory.name}")
            service.create_submap(ATLAS, SUBMAP)
            yield service
        finally:
            runtime.stop()


def observe_frame(
    service: AtlasService,
    features: FrameFeatures,
    timestamp: float,
    *,
    k: int,
    length: int,
    exclude_recent: int,
) -> tuple[QueryResult, int, float]:
    """One frame through ``POST /observe``'s use case: ``(answer, stored frame id, ms)``."""
    start = time.perf_counter()
    result, frame = service.observe_features(
        atlas_name=ATLAS,
        fields=FrameFields(SUBMAP, ROBOT, timestamp=timestamp),
        features=features,
        k=k,
        query_filter=service.query_filter(
            robot_id=ROBOT,
            timestamp=timestamp,
            exclude_recent_frames=exclude_recent,
            exclude_recent_seconds=0.0,
        ),
        sequence_length=length if length > 1 else 0,
    )
    return result, frame.id, (time.perf_counter() - start) * 1000.0


def service_observations(
    trajectory: Trajectory,
    features: CachedFeatures,
    pipeline: FeaturePipeline,
    *,
    alpha: float,
    length: int,
    exclude_recent: int,
    consistency: int,
) -> list[tuple[int, float, int, float]]:
    """``(reference, score, length, ms)`` for every frame in order, retrieval only: the
    reference is the frame index the service answered (-1: none), the score the sequence's
    margin over its best rival place (L > 1) or the cosine."""
    count = len(features.local)
    times = frame_times(trajectory, count)
    dim = pipeline.local.descriptor_dim
    index_of: dict[int, int] = {}
    answers: list[tuple[int, float, int, float]] = []
    with replay_atlas(
        trajectory,
        pipeline,
        alpha=alpha,
        exclude_recent=exclude_recent,
        consistency=consistency,
        served=False,
    ) as service:
        for t in tqdm(range(count), desc=f"observe: {trajectory.name}", unit="frame"):
            frame_features, _ = features.frame(t, dim)
            result, frame_id, ms = observe_frame(
                service,
                frame_features,
                float(times[t]),
                k=1,
                length=length,
                exclude_recent=exclude_recent,
            )
            index_of[frame_id] = t
            if result.sequence is not None:
                answer = result.sequence
                # the sequence decides on its margin over the best rival place
                answers.append((index_of[answer.frame_id], answer.margin, answer.length, ms))
            elif result.match is not None:
                answers.append((index_of[result.match.frame_id], result.match.similarity, 1, ms))
            else:
                answers.append((-1, -np.inf, 0, ms))
    return answers
