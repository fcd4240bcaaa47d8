"""The ``<method>-served`` row: every query answered as ``POST /query`` answers it at the
service's defaults (verification with the default matcher and count, the calibrated score
once the atlas is calibrated, the loop decision), and its PR sweep over the one number the
service thresholds, ``decision.loop_probability``, among the answers the service could close
(``decision.closable``: no threshold makes an unverified match a loop, so the sweep never
accepts the others; they count only in the recall's denominator). The sweep over the
probability alone, every answer in it (the figure before stop 38), stays in the row's details.

The pass runs in the service pass's temporary atlas after its calibration (when the dataset
is large enough to calibrate); verification reads the references' keypoints back from the
atlas's feature store, as a served query does.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from service.app import model_versions
from service.app.catalog import AtlasService
from service.app.filters import QueryFilter
from service.app.ingest import FrameFields
from service.app.results import QueryResult
from service.app.verify import CandidateVerification, verification_config
from service.config import Settings
from service.evaluation.datasets import Dataset
from service.evaluation.metrics import Ranking, correct_matrix, precision_recall
from service.evaluation.protocol import MethodResult, evaluate_ranking
from service.evaluation.served_jobs import JobRun, queued_jobs, run_queued
from service.evaluation.served_sweep import (
    answered_frames,
    confirmed_rows,
    swept_probability,
    swept_score,
)
from service.ml.features import FrameFeatures, LocalFeatures
from service.storage import repository as repo

PARTS = ("inliers", "inlier_ratio", "rival", "score", "sequence")
# the settings a served answer takes at their defaults (the harness's atlas turns them off)
DEFAULTS = (
    "verify_top",
    "matcher",
    "verify_min_inliers",
    "verify_ratio",
    "verify_scale_tolerance",
    "ransac_threshold_px",
    "loop_probability_min",
    "sequence_length",
    "consistency_frames",
)
QUERY_ROBOT, QUERY_SUBMAP = "queries", "queries"


@dataclass
class ServedAnswers:
    """Per query: the served ranking (column 0 scored by
    :func:`service.evaluation.served_sweep.swept_score`), the status, the decision's parts
    (NaN: absent) and the milliseconds of heads + search + verification + decision."""

    ranking: Ranking
    status: list[str]
    parts: np.ndarray  # Q x len(PARTS)
    query_ms: np.ndarray
    threshold: float
    verification: dict[str, Any] = field(default_factory=dict)
    sequence_length: int = 0
    # per query, its answer's candidates in served order: (reference, similarity, score,
    # inliers, inlier ratio, zoom), NaN where absent, to study the re-rank offline
    candidates: list[list[list[float]]] = field(default_factory=list)
    # per query, the probability whether or not the answer is closable (0: no decision)
    probability_alone: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # per query, whether some threshold makes it a loop (decision.closable, or the sequence
    # passed)
    closable: list[bool] = field(default_factory=list)
    # per query, the robot's sequence (reference, margin, length, passed; NaN: none)
    sequences: list[list[float]] = field(default_factory=list)
    # per query, the sequence's aligned_z (each frame's own evidence, oldest first; []: none)
    sequence_z: list[list[float]] = field(default_factory=list)
    # the jobs the observations queued, each run before the next query (see served_answers),
    # and the revisit pairs after which they queued an adaptation (0: never)
    jobs: list[JobRun] = field(default_factory=list)
    adapt_after_pairs: int = 0

    def subset(self, keep: np.ndarray) -> ServedAnswers:
        """The answers of the queries ``keep`` (indices), in that order."""
        return replace(
            self,
            ranking=Ranking(self.ranking.indices[keep], self.ranking.scores[keep]),
            status=[self.status[i] for i in keep],
            parts=self.parts[keep],
            candidates=[self.candidates[i] for i in keep] if self.candidates else [],
            query_ms=self.query_ms[keep],
            probability_alone=self.probability_alone[keep],
            closable=[self.closable[i] for i in keep],
            sequences=[self.sequences[i] for i in keep] if self.sequences else [],
            sequence_z=[self.sequence_z[i] for i in keep] if self.sequence_z else [],
        )


def at_served_defaults(settings: Settings) -> Settings:
    """``settings`` with :data:`DEFAULTS` at the service's defaults."""
    defaults = Settings(data_dir=settings.data_dir)
    return settings.model_copy(update={name: getattr(defaults, name) for name in DEFAULTS})


@contextmanager
def served_settings(service: AtlasService, extractor: str) -> Iterator[Settings]:
    """The service's queries (and observations) with :data:`DEFAULTS` at their defaults while
    the block runs (the harness's atlas turns verification off); the settings in force."""
    settings = at_served_defaults(service.settings)
    queries_api = service.queries
    before = (queries_api.verification, queries_api.settings)
    queries_api.verification = CandidateVerification(
        verification_config(settings, extractor), service.inference
    )
    queries_api.settings = settings
    try:
        yield settings
    finally:
        queries_api.verification, queries_api.settings = before


def served_answers(
    service: AtlasService,
    queries: Sequence[FrameFeatures],
    frame_to_reference: dict[int, int],
    k: int,
    atlas: str,
    extractor: str,
    sequence_length: int = 0,
    query_filter: QueryFilter | None = None,
    adapt_after_pairs: int = 0,
) -> ServedAnswers:
    """Ask every query through the service with the default verification switched on.

    ``sequence_length`` 0: anonymous queries (``POST /query``), over the frames
    ``query_filter`` allows (None: all). Otherwise the queries are one robot's observations
    (``POST /observe``, one second apart, asking about the other robots' frames only, so the
    references): each is answered with its sequence of that length and consistency, then joins
    the atlas; call it last, after every anonymous pass. ``adapt_after_pairs`` (observations
    only; 0: off) queues an adaptation job after that many revisit pairs the observations
    kept, as the service does, and runs it before the next observation, as a worker would
    between two frames: the row then measures the atlas the service would be serving.
    """
    if sequence_length:
        service.create_submap(atlas, QUERY_SUBMAP)
    indices, parts, query_ms, alone = [], [], [], []
    scores: list[list[float]] = []
    status: list[str] = []
    closable: list[bool] = []
    candidates: list[list[list[float]]] = []
    sequences: list[list[float]] = []
    sequence_z: list[list[float]] = []
    ran: list[JobRun] = []
    adapting = adapt_after_pairs if sequence_length else 0
    row_of: dict[int, int] = {}  # the robot's stored frames' rows (observations)
    with served_settings(service, extractor) as settings, queued_jobs(service, adapting) as queued:
        config = service.queries.verification.config
        for i, features in enumerate(queries):
            features = replace(features, local=as_stored(features.local))
            start = time.perf_counter()
            if sequence_length:
                fields = FrameFields(QUERY_SUBMAP, QUERY_ROBOT, timestamp=float(i))
                answer, frame = service.observe_features(
                    atlas_name=atlas,
                    fields=fields,
                    features=features,
                    k=k,
                    query_filter=service.query_filter(
                        robot_id=QUERY_ROBOT, robots="others", timestamp=float(i)
                    ),
                    sequence_length=sequence_length,
                )
                for row in confirmed_rows(answer, row_of):  # earlier frames' loops, late
                    scores[row] = [x - scores[row][0] + 1.0 for x in scores[row]]  # p -> 1.0
                    closable[row], status[row] = True, "loop"
                row_of[frame.id] = i
            else:
                answer = service.query_features(
                    atlas_name=atlas, features=features, k=k, query_filter=query_filter
                )
            query_ms.append((time.perf_counter() - start) * 1000.0)
            found = [frame_to_reference.get(f, -1) for f in answered_frames(answer)][:k]
            pad = k - len(found)
            p, eligible = swept_score(answer)
            alone.append(swept_probability(answer, closable_only=False))
            closable.append(eligible)
            indices.append(found + [-1] * pad)
            scores.append([p] + [p - 1.0 - i for i in range(len(found) - 1)] + [-np.inf] * pad)
            status.append(answer.status)
            parts.append(decision_parts(answer))
            candidates.append(candidate_rows(answer, frame_to_reference))
            sequences.append(sequence_row(answer, frame_to_reference))
            sequence_z.append(list(answer.sequence.aligned_z) if answer.sequence else [])
            while queued:
                ran.append(run_queued(service, queued.pop(0), frame=i))
    return ServedAnswers(
        Ranking(np.array(indices, np.int64), np.array(scores, np.float64)),
        status,
        np.array(parts, np.float64).reshape(len(parts), len(PARTS)),
        np.array(query_ms, np.float64),
        settings.loop_probability_min,
        {
            "matcher": config.matcher,
            "top": config.top,
            "min_inliers": config.min_inliers,  # the matcher's default, before calibration
            "fitted_min_inliers": fitted_min_inliers(service, atlas),
        },
        sequence_length,
        candidates,
        np.array(alone, np.float64),
        closable,
        sequences,
        sequence_z,
        ran,
        adapting,
    )


def fitted_min_inliers(service: AtlasService, atlas: str) -> dict[str, Any] | None:
    """The active version's calibrated minimum inliers and the impostors it came from (None
    before the atlas's first calibration)."""
    with service.sessions() as session:
        atlas_id = repo.get_atlas(session, name=atlas).id
        version = repo.active_model_version(session, atlas_id=atlas_id)
        calibration = model_versions.VersionConfig.of(version).calibration or {}
    fitted = calibration.get("min_inliers")
    return dict(fitted) if fitted else None


def candidate_rows(answer: QueryResult, frame_to_reference: dict[int, int]) -> list[list[float]]:
    """The answer's candidates in served order as (reference index or -1, similarity,
    calibrated score, inliers, inlier ratio, zoom), NaN where a candidate lacks one."""

    def number(value: float | None) -> float:
        return float("nan") if value is None else round(float(value), 4)

    return [
        [
            float(frame_to_reference.get(c.frame_id, -1)),
            number(c.similarity),
            number(c.score),
            number(c.inliers),
            number(c.inlier_ratio),
            number(c.scale),
        ]
        for c in answer.candidates
    ]


def sequence_row(answer: QueryResult, frame_to_reference: dict[int, int]) -> list[float]:
    """The robot's sequence as (reference index or -1, margin, length, passed), NaN without
    one: what a choice of ``sequence_margin_min`` is read from."""
    sequence = answer.sequence
    if sequence is None:
        return [float("nan")] * 4
    return [
        float(frame_to_reference.get(sequence.frame_id, -1)),
        float(sequence.margin),
        float(sequence.length),
        float(sequence.passed),
    ]


def decision_parts(answer: QueryResult) -> list[float]:
    """The decision's inputs (uncentred), NaN where absent."""
    decision = answer.decision
    if decision is None:
        return [np.nan] * len(PARTS)
    return [decision.parts.get(name, np.nan) for name in PARTS]


def as_stored(local: LocalFeatures) -> LocalFeatures:
    """Descriptors rounded to float16, as the feature store (and the feature cache) gives
    them back: a rerun from the cache answers the same."""
    return LocalFeatures(
        local.keypoints, local.descriptors.astype(np.float16).astype(np.float32), local.scores
    )


def served_method(
    name: str,
    label: str,
    served: ServedAnswers,
    dataset: Dataset,
    submap_of: Sequence[int],
) -> MethodResult:
    """The served row: PR over the loop_probability of closable answers (no threshold makes
    the others loops) and the operating point at the defaults."""
    method = evaluate_ranking(
        name,
        label,
        "served",
        served.ranking,
        dataset,
        submap_of,
        query_ms=served.query_ms,
        eligible=np.asarray(served.closable, bool),
    )
    positives = [q.positives for q in dataset.queries]
    right = correct_matrix(served.ranking, positives)[:, 0]
    answerable = sum(1 for p in positives if p)
    alone = precision_recall(served.probability_alone, right, answerable)
    method.details = {
        "operating_point": loop_counts(served.status, right, answerable, served.threshold),
        "recall_at_100_precision_probability_alone": alone.recall_at_full_precision,
        "verification": served.verification,
        "parts": PARTS,
        "per_query_parts": np.round(served.parts, 4).tolist(),
        "per_query_status": served.status,
        "per_query_candidates": served.candidates,
        "per_query_sequence": served.sequences,
        "per_query_sequence_z": served.sequence_z,
        "jobs": [asdict(job) for job in served.jobs],
        "per_query_closable": [int(c) for c in served.closable],
        "per_query_right": right.astype(int).tolist(),
    }
    return method


def loop_counts(
    status: Sequence[str], right: np.ndarray, answerable: int, threshold: float
) -> dict[str, float | int]:
    """The operating point at the defaults: an answer is a loop when its status is ``loop``;
    precision, recall (over the ``answerable`` queries), false loops per 1,000 answers, and
    right answers the service called ``new_place``."""
    loops = np.array([s == "loop" for s in status], bool)
    right = np.asarray(right, bool)
    true_loops, false_loops = int(np.sum(loops & right)), int(np.sum(loops & ~right))
    return {
        "threshold": threshold,
        "loops": int(loops.sum()),
        "precision": true_loops / max(int(loops.sum()), 1),
        "recall": true_loops / max(answerable, 1),
        "false_loops": false_loops,
        "false_loops_per_1000": 1000.0 * false_loops / max(len(loops), 1),
        "right_called_new_place": int(
            sum(1 for s, r in zip(status, right, strict=True) if r and s == "new_place")
        ),
    }
