"""The *pairs* protocol: adaptation from the pairs the service's own ``observe`` verified.

The revisit protocol (:mod:`service.evaluation.adaptation_pass`) hands the adaptation its pairs
from the ground truth. Here the service finds them, as it does for a fleet: K query-condition
frames per revisited submap (the revisit protocols' shots) are observed, as served (default
verification and decision), by a second robot asking about the map's frames, into the service
pass's calibrated atlas. Every verified closure ``observe`` records is a revisit pair, right or
wrong; the ground truth only counts how many were right. A real ``adapt`` job (job runner, the
job's default parameters) learns from them and its gate decides. The remaining queries are
answered as served, anonymously, before (the pass's served answers) and after, once the
observed frames are deleted again (so over the map's frames only, as before): ``after`` with
the job's version (activated for the measurement when the gate kept it back), ``served`` with
whichever version the gate left active. The atlas is then put back (the starting version
active), so each K starts from the same atlas and the later passes see none of it.

With the source ``labelled`` the same run measures the revisit protocol *as served*: the
shots are stored and each is labelled as a pair with its partner reference (the ground-truth
pairs :mod:`service.evaluation.adaptation_pass` hands to ``adapt_heads``, here through the
pairs use case, the job runner and the served decision).

With the source ``stream`` the robot drives: the first P % of the queries, in their order (a
traversal's route order), are observed one second apart in one submap, so its sequence and
trajectory contrast work as they do for a fleet's robot, and every closure observe keeps
(verified, or a loop of its sequence) is a pair. The test queries are the rest of the drive:
places the job never saw a pair of, so what it learned must be the change of condition. They
are answered twice more, as the rest of a drive (observed in order by a robot with the
service's default sequence), once by the starting version and once by the job's: what the
adaptation does to the loops a robot closes.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from service.app.catalog import AtlasService
from service.app.ingest import FrameFields
from service.app.pairs import RevisitPairs
from service.app.revisit_pairs import pair_frames, pair_sources
from service.config import Settings
from service.domain.pairs import PairFilter
from service.evaluation.adaptation_pass import partner_of
from service.evaluation.datasets import Dataset
from service.evaluation.protocol import MethodResult
from service.evaluation.retraining_pass import _subset, query_submaps, revisit_shots
from service.evaluation.score_honesty import impostor_exceedance
from service.evaluation.served_jobs import run_job_now
from service.evaluation.served_pass import (
    PARTS,
    QUERY_SUBMAP,
    ServedAnswers,
    as_stored,
    served_answers,
    served_method,
    served_settings,
)
from service.ml.features import FrameFeatures
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction

PROTOCOL = "pairs-observe"
REVISIT_ROBOT = "revisits"
# where the pairs come from: what observe verified (K frames per submap), each shot labelled
# with its partner reference (the revisit protocol's ground-truth pairs, as an operator labels
# them), or what observe kept while the robot drove the first P % of the queries in order
SOURCES = ("observe", "labelled", "stream")
STREAM_SUBMAP = "revisit-stream"


@dataclass
class ObservedPairs:
    """One K: what ``observe`` recorded, what the job made of it, the answers before and after.

    Attributes:
        shots: K frames per revisited submap; for ``stream``, the percent of the queries driven.
        source: where the pairs came from (:data:`SOURCES`).
        observed: query indices observed or labelled (K per revisited submap, or the drive's).
        test: the other query indices, the test queries.
        statuses: the observations' answers by status (``loop``, ``new_place``, ...).
        pairs: ``P x 2`` (query index, reference index) of the pairs observe recorded.
        right: per pair, whether the reference is a right one for the query (ground truth).
        job: the adapt job's status, message, version, whether it was activated, its metrics.
        before: the test queries as served on the starting atlas.
        after: the test queries with the job's version; None when the job made none.
        sources: the recorded pairs by source (``observe``: verified, ``sequence``: a loop
            the robot's sequence decided, ``operator``: labelled).
        drive_before, drive_after: ``stream`` only, the test queries observed in order as a
            drive (default sequence), by the starting and by the job's version.
        honesty_before, honesty_after: the share of the test queries' impostor pairs that
            score at least 2 and 3 under each version (:mod:`score_honesty`).
    """

    shots: int
    source: str
    observed: np.ndarray
    test: np.ndarray
    statuses: dict[str, int]
    pairs: np.ndarray
    right: np.ndarray
    job: dict[str, Any]
    before: ServedAnswers
    after: ServedAnswers | None = None
    sources: dict[str, int] = field(default_factory=dict)
    drive_before: ServedAnswers | None = None
    drive_after: ServedAnswers | None = None
    honesty_before: dict[str, float] = field(default_factory=dict)
    honesty_after: dict[str, float] = field(default_factory=dict)

    @property
    def activated(self) -> bool:
        return bool(self.job.get("activated"))

    @property
    def served(self) -> ServedAnswers:
        """What the service answers once the job is done: its version when the gate activated
        it, else the one it started from."""
        return self.after if self.activated and self.after is not None else self.before


def observed_pairs_runs(
    service: AtlasService,
    *,
    atlas: str,
    dataset: Dataset,
    submap_of: Sequence[int],
    queries: Sequence[FrameFeatures],
    frame_to_reference: dict[int, int],
    before: ServedAnswers,
    k: int,
    shots: Sequence[int],
    source: str = "observe",
) -> list[ObservedPairs]:
    """One run of the protocol per K, each from the atlas as it was (``before``: the pass's
    served answers to every query on it). ``source`` "labelled": the shots are stored and
    each is labelled as a pair with its partner reference instead of being observed;
    "stream": each K is a percent of the queries, driven in order (:func:`_stream`)."""
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    extractor = service.pipeline.preset.local.name
    revisited = query_submaps(dataset, submap_of)
    partners = partner_of(dataset)
    reference_frame = {ref: frame for frame, ref in frame_to_reference.items()}
    runs = []
    for k_shots in shots:
        if source == "stream":
            observed = _stream(len(queries), k_shots)
        else:
            observed = revisit_shots(revisited, k_shots)
        test = np.setdiff1d(np.arange(len(queries)), observed)
        with service.sessions() as session:
            found = repo.get_atlas(session, name=atlas)
            atlas_id, starting = found.id, repo.active_model_version(session, atlas_id=found.id)
            starting_version = starting.version
        tested = [queries[q] for q in test]
        test_positives = [dataset.queries[q].positives for q in test]
        honesty_before = impostor_exceedance(
            service, atlas_id, tested, test_positives, frame_to_reference
        )
        honesty_after: dict[str, float] = {}
        submap_name = {
            int(q): STREAM_SUBMAP if source == "stream" else f"revisit-{int(revisited[q]):05d}"
            for q in observed
        }
        submaps = sorted(set(submap_name.values()))
        for submap in submaps:
            service.create_submap(atlas, submap)
        query_of: dict[int, int] = {}
        labels = RevisitPairs(service.sessions)
        statuses: Counter[str] = Counter()
        try:
            with served_settings(service, extractor):
                for q in observed:
                    fields = FrameFields(submap_name[int(q)], REVISIT_ROBOT, timestamp=float(q))
                    features = replace(queries[q], local=as_stored(queries[q].local))
                    if source == "labelled":
                        frame = service.ingest_features(
                            atlas_name=atlas, fields=fields, features=features
                        )
                        labels.label(atlas, frame.id, reference_frame[int(partners[q])])
                        statuses["labelled"] += 1
                    else:
                        answer, frame = service.observe_features(
                            atlas_name=atlas,
                            fields=fields,
                            features=features,
                            k=k,
                            query_filter=service.query_filter(
                                robot_id=REVISIT_ROBOT, robots="others", timestamp=float(q)
                            ),
                        )
                        statuses[answer.status] += 1
                    query_of[frame.id] = int(q)
            with service.sessions() as session:
                where = PairFilter(robots=(REVISIT_ROBOT,))
                recorded = pair_frames(session, atlas_id=atlas_id, where=where)
                sources = pair_sources(session, atlas_id=atlas_id, where=where)
            pairs = np.array(
                [(query_of[a], frame_to_reference.get(b, -1)) for _, a, b in recorded], np.int64
            ).reshape(-1, 2)
            right = np.array([ref in dataset.queries[q].positives for q, ref in pairs], dtype=bool)
            job = _adapt(service, atlas_id)
            # the test queries ask as before, anonymously, the map's frames only: the observed
            # frames go once the job has learned from them (an asking robot would also bring
            # its own trajectory into the decision)
            _delete(service, atlas, submaps)
            after = drive_before = drive_after = None
            if source == "stream":  # the rest of the drive, with the starting version
                service.activate_version(atlas, starting_version)
                service.catch_up()
                drive_before = _drive(service, tested, frame_to_reference, k, atlas, extractor)
            if job["version"] is not None:
                # measured with the job's version also when the gate kept it back
                service.activate_version(atlas, job["version"])
                service.catch_up()
                after = served_answers(service, tested, frame_to_reference, k, atlas, extractor)
                honesty_after = impostor_exceedance(
                    service, atlas_id, tested, test_positives, frame_to_reference
                )
                if source == "stream":
                    drive_after = _drive(service, tested, frame_to_reference, k, atlas, extractor)
        finally:  # the atlas as it was: the starting version, no observed frame or pair
            service.activate_version(atlas, starting_version)
            _delete(service, atlas, submaps)
            service.catch_up()
        runs.append(
            ObservedPairs(
                k_shots,
                source,
                observed,
                test,
                dict(statuses),
                pairs,
                right,
                job,
                before.subset(test),
                after,
                sources,
                drive_before,
                drive_after,
                honesty_before,
                honesty_after,
            )
        )
    return runs


def _drive(
    service: AtlasService,
    queries: list[FrameFeatures],
    frame_to_reference: dict[int, int],
    k: int,
    atlas: str,
    extractor: str,
) -> ServedAnswers:
    """``queries`` observed in order by a robot with the service's default sequence length,
    over the map's frames; its frames (and the pairs they made) are deleted again."""
    length = Settings(data_dir=service.settings.data_dir).sequence_length
    try:
        return served_answers(
            service, queries, frame_to_reference, k, atlas, extractor, sequence_length=length
        )
    finally:
        _delete(service, atlas, [QUERY_SUBMAP])


def _stream(queries: int, percent: int) -> np.ndarray:
    """The first ``percent`` % of the queries (at least one, never all: some must be left to
    test on)."""
    if not 0 < percent < 100:
        raise ValueError(f"a stream drives between 1 and 99 % of the queries, got {percent}")
    return np.arange(min(max(1, queries * percent // 100), queries - 1))


def _delete(service: AtlasService, atlas: str, submaps: list[str]) -> None:
    """The observed frames' submaps with their frames and pairs (those still there)."""
    with service.sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        there = {s.name for s, _ in repo.list_submaps_with_counts(session, atlas=found)}
    for submap in submaps:
        if submap in there:
            service.delete_submap(atlas, submap)


def _adapt(service: AtlasService, atlas_id: int) -> dict[str, Any]:
    """An ``adapt`` job with the job's default parameters, run by the job runner."""
    with transaction(service.sessions) as session:
        job_id = jobs.create_job(session, atlas_id=atlas_id, kind="adapt", params={}).id
    job = run_job_now(service, job_id)
    metrics = dict(job.metrics)
    return {
        "status": job.status,
        "message": job.message,
        "version": job.model_version,
        "activated": bool(metrics.get("activated", False)),
        "gate": metrics.get("held_out"),
        "metrics": {k: v for k, v in metrics.items() if k not in ("held_out",)},
    }


def observed_pairs_rows(
    run: ObservedPairs, dataset: Dataset, submap_of: Sequence[int], label: str
) -> tuple[list[MethodResult], dict[str, Any]]:
    """The run's served rows on the test queries (before, after, served) and its report row."""
    subset = _subset(dataset, run.test)
    protocol = f"pairs-{run.source}"
    name = f"{protocol}-k{run.shots}"
    origin = {
        "observe": f"observe verified ({run.shots}/submap)",
        "labelled": f"labelled from ground truth ({run.shots}/submap)",
        "stream": f"observe kept on a drive over the first {run.shots} % of the queries",
    }[run.source]
    methods = {
        "before": served_method(
            f"{name}-before",
            f"{label} (as served) before",
            run.before,
            subset,
            submap_of,
        )
    }
    if run.after is not None:
        methods["after"] = served_method(
            f"{name}-after",
            f"{label} adapted from {len(run.pairs)} pairs {origin}",
            run.after,
            subset,
            submap_of,
        )
    for side, drive in (("before", run.drive_before), ("after", run.drive_after)):
        if drive is not None:
            version = "the starting version" if side == "before" else "the job's version"
            methods[f"drive-{side}"] = served_method(
                f"{name}-drive-{side}",
                f"{label} (as served, observe, L={drive.sequence_length}), the rest of the "
                f"drive with {version}",
                drive,
                subset,
                submap_of,
            )
    served = methods["after"] if run.activated and "after" in methods else methods["before"]
    row = {
        "protocol": protocol,
        "shots": run.shots,
        "observed": len(run.observed),
        "statuses": run.statuses,
        "pairs": len(run.pairs),
        "pairs_right": int(run.right.sum()),
        "pair_sources": run.sources,
        "test_queries": len(run.test),
        "job": run.job,
        "served": "adapted" if served is not methods["before"] else "starting",
        **{
            f"{key}_{side}": value
            for side, method in (*methods.items(), ("served", served))
            for key, value in _figures(method).items()
        },
        **{f"impostors_{key}_before": value for key, value in run.honesty_before.items()},
        **{f"impostors_{key}_after": value for key, value in run.honesty_after.items()},
        **{
            f"loops_{side}": methods[side].details["operating_point"]
            for side in ("drive-before", "drive-after")
            if side in methods
        },
    }
    return list(methods.values()), row


def _figures(method: MethodResult) -> dict[str, float]:
    """R@1, R@100%P and the wrong and the right best answers' median score excess (the
    decision's score part: calibrated score - log10 of the atlas's frames; NaN where no such
    answer had one): an adapted version's score must keep its meaning for both."""
    parts = np.asarray(method.details["per_query_parts"], np.float64).reshape(-1, len(PARTS))
    right = np.asarray(method.details["per_query_right"], bool)
    scores = parts[:, PARTS.index("score")]

    def median(chosen: np.ndarray) -> float:
        found = scores[chosen & np.isfinite(scores)]
        return float(np.median(found)) if len(found) else float("nan")

    return {
        "recall@1": method.recall[1],
        "recall_at_100_precision": method.recall_at_full_precision,
        "wrong_score_median": median(~right),
        "right_score_median": median(right),
    }


__all__ = ["PROTOCOL", "SOURCES", "ObservedPairs", "observed_pairs_rows", "observed_pairs_runs"]
