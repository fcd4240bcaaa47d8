"""Sequence rows of the harness (``--sequence L``): every query scored in dataset order through
:mod:`service.ml.sequences`, the code the service's observe path calls, on the same stored
vectors as the single-frame rows.

Query i's sequence is queries ``i - L + 1 .. i`` of its own run (a jump in the frame numbers
starts a new run); the map's frames are one trajectory per run of consecutive reference frames.
Seeds are each query frame's best map matches by exact cosine (what the service's index
returns); the map's similarity statistics come from :class:`MapMoments`, once per query (the
service's cache of a robot's recent frames), so the timed step is what a warm observe adds.
Places are ranked by sequence score; the loop-closure sweep (AUC-PR, recall at 100% precision)
runs on the best place's *margin* over its best rival (:mod:`service.ml.sequences.distinctiveness`),
what the service decides a sequence loop on: the ranking's scores are the sequence scores minus
the rival's, so their order is the score's and the first column is the margin.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from service.evaluation.datasets import Dataset
from service.evaluation.metrics import Ranking
from service.evaluation.protocol import MethodResult, evaluate_ranking
from service.ml.sequences import (
    ConsistencySettings,
    MapMoments,
    SequenceSettings,
    Trajectories,
    distinctiveness,
)

RIVAL_WINDOW = ConsistencySettings().max_step  # the service's "another place" along a trajectory


def frame_numbers(labels: Sequence[str]) -> np.ndarray | None:
    """Frame numbers from the dataset's place labels, where every label is one."""
    try:
        return np.array([int(label) for label in labels], dtype=np.int64)
    except ValueError:
        return None


def run_starts(numbers: np.ndarray | None, count: int) -> np.ndarray:
    """Where a run of consecutive frames starts (by frame number; dataset order otherwise)."""
    starts = np.zeros(count, dtype=bool)
    if count:
        starts[0] = True
    if numbers is not None and count > 1:
        starts[1:] = np.diff(numbers) != 1
    return starts


def dataset_trajectories(dataset: Dataset) -> tuple[Trajectories, np.ndarray]:
    """The map as trajectories, and where each query's run starts."""
    reference_numbers = np.array([r.order for r in dataset.references], dtype=np.int64)
    trajectories = Trajectories.single(
        len(dataset.references), run_starts(reference_numbers, len(dataset.references))
    )
    query_starts = run_starts(
        frame_numbers([q.place for q in dataset.queries]), len(dataset.queries)
    )
    return trajectories, query_starts


def sequence_ranking(
    reference: np.ndarray,
    query: np.ndarray,
    trajectories: Trajectories,
    query_starts: np.ndarray,
    settings: SequenceSettings,
    k: int,
) -> tuple[Ranking, np.ndarray, np.ndarray]:
    """Rank every query by sequence score, minus the best rival's (so the first column is
    the margin); also the length used and the per-query milliseconds.

    ``reference`` and ``query`` are unit vectors (``R x d``, ``Q x d``).
    """
    from service.ml.sequences import match_sequence

    similarity = query @ reference.T
    seeds_all = np.argsort(-similarity, axis=1, kind="stable")[:, : settings.seeds]
    moments = MapMoments.of(reference)
    # each query's map statistics once, as the service caches them for a robot's recent frames
    mean, std = moments.row_stats(query)
    first = np.maximum.accumulate(np.where(query_starts, np.arange(len(query)), 0))
    indices = np.full((len(query), k), -1, dtype=np.int64)
    scores = np.full((len(query), k), -np.inf)
    lengths = np.zeros(len(query), dtype=np.int64)
    elapsed = np.zeros(len(query))
    lookup = reference.__getitem__
    for i in range(len(query)):
        start = time.perf_counter()
        window = slice(max(first[i], i - settings.length + 1), i + 1)
        matches = match_sequence(
            query[window],
            list(seeds_all[window]),
            lookup,
            trajectories,
            moments,
            settings,
            top=None,
            row_stats=(mean[window], std[window]),
        )
        distinct = distinctiveness(matches, trajectories, RIVAL_WINDOW)
        elapsed[i] = (time.perf_counter() - start) * 1000.0
        rival = matches[0].score - distinct.margin if distinct is not None else 0.0
        matches = matches[:k]
        indices[i, : len(matches)] = [m.reference for m in matches]
        scores[i, : len(matches)] = [m.score - rival for m in matches]
        lengths[i] = matches[0].length if matches else 0
    return Ranking(indices, scores), lengths, elapsed


def sequence_methods(
    base: Sequence[tuple[MethodResult, np.ndarray, np.ndarray]],
    dataset: Dataset,
    submap_of: Sequence[int],
    lengths: Sequence[int],
    k: int,
    settings: SequenceSettings | None = None,
) -> list[MethodResult]:
    """A ``<method>+seqL`` row for each single-frame method (with its reference and query unit
    vectors) and each L."""
    trajectories, query_starts = dataset_trajectories(dataset)
    template = settings or SequenceSettings()
    rows = []
    for method, reference, query in base:
        for length in lengths:
            chosen = replace(template, length=length)
            ranking, used, ms = sequence_ranking(
                reference, query, trajectories, query_starts, chosen, k
            )
            suffix, words = "", ""
            if chosen.contrast_window:
                suffix += f"-lc{chosen.contrast_window}"
                words += f", local contrast {chosen.contrast_window}"
            if chosen.seed_frames:  # the service's default is every frame's matches
                suffix += f"-seeds{chosen.seed_frames}"
                words += f", matches of the newest {chosen.seed_frames} frames propose"
            rows.append(
                evaluate_ranking(
                    f"{method.name}+seq{length}{suffix}",
                    f"{method.label} + sequence L={length}{words}",
                    "sequence",
                    ranking,
                    dataset,
                    submap_of,
                    query_ms=ms,
                    details={
                        "sequence": {
                            "length": length,
                            "speeds": list(chosen.speeds),
                            "reverse": chosen.reverse,
                            "seeds": chosen.seeds,
                            "neighbourhood": chosen.neighbourhood,
                            "candidates": chosen.candidates,
                            "seed_frames": chosen.seed_frames,
                            "contrast_window": chosen.contrast_window,
                        },
                        "mean_length_used": float(used.mean()) if len(used) else 0.0,
                        "loop_confidence": f"margin over the best rival more than {RIVAL_WINDOW} "
                        "frames away (sequence score minus the rival's)",
                        "query_ms_note": "sequence scoring only (added to the method's query)",
                    },
                )
            )
    return rows
