"""The adaptation as served: the revisit protocol run through the service itself.

On a service pass's calibrated atlas (its own, one per K: the shots join it), K query-condition
frames per revisited submap join the atlas as a second robot's frames, each labelled as a
revisit pair with its partner reference through the pairs use case (as an operator labels one,
or as ``observe`` records a verified closure); an ``adapt`` job is then run by the job runner,
as a worker runs it (fit, gate, impostor model, re-embedding, activation), and the other
queries are answered through the service before and after it at the defaults (verification,
calibrated score, loop decision): :func:`served_answers`. So the before -> after rows are the
decision the service serves, not a threshold swept over a cosine.

The test queries are asked anonymously of the same atlas content before and after: the
references only (the shots leave the atlas once the job has run; answered by a shot, a frame
of their own condition a frame away, every query would be right before any adaptation).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from service.app.catalog import AtlasService
from service.app.ingest import FrameFields
from service.app.pairs import RevisitPairs
from service.evaluation.adaptation_pass import partner_of
from service.evaluation.datasets import Dataset
from service.evaluation.protocol import MethodResult
from service.evaluation.retraining_pass import RetrainingRow, query_submaps, revisit_shots
from service.evaluation.served_pass import ServedAnswers, served_answers, served_method
from service.evaluation.service_pass import ATLAS, run_job, run_service_pass, submap_name
from service.ml.features import FrameFeatures
from service.ml.pipeline import FeaturePipeline

PROTOCOL = "revisit-adapt-served"
SHOT_ROBOT = "revisits"


@dataclass
class ServedAdaptation:
    """One K: the shots (query indices), the test queries, the answers before and after the
    job, and the job's outcome (status, message, metrics)."""

    shots_per_submap: int
    shots: np.ndarray
    test: np.ndarray
    before: ServedAnswers
    after: ServedAnswers
    job: dict[str, Any] = field(default_factory=dict)


def adapt_as_served(
    service: AtlasService,
    atlas: str,
    queries: Sequence[FrameFeatures],
    frame_to_reference: dict[int, int],
    *,
    k: int,
    extractor: str,
    revisited: np.ndarray,
    partners: np.ndarray,
    k_shots: int,
    submap_names: dict[int, str],
    run_job: Any,
    params: dict[str, Any] | None = None,
) -> ServedAdaptation:
    """Add the shots and their pairs, answer the test queries, run an ``adapt`` job through
    ``run_job(kind, params) -> dict`` (the service pass's job runner), answer them again."""
    shots, test = revisit_shots(revisited, k_shots)
    asked = [queries[i] for i in test]
    before = served_answers(service, asked, frame_to_reference, k, atlas, extractor)
    reference_frame = {ref: frame for frame, ref in frame_to_reference.items()}
    pairs = RevisitPairs(service.sessions)
    shot_frames = []
    for order, q in enumerate(shots):
        frame = service.ingest_features(
            atlas_name=atlas,
            fields=FrameFields(submap_names[int(revisited[q])], SHOT_ROBOT, timestamp=float(order)),
            features=queries[q],
        )
        shot_frames.append(frame.id)
        pairs.label(atlas, frame.id, reference_frame[int(partners[q])])
    job = run_job("adapt", params or {})
    for frame_id in shot_frames:
        service.delete_frame(atlas, frame_id)
    after = served_answers(service, asked, frame_to_reference, k, atlas, extractor)
    return ServedAdaptation(k_shots, shots, test, before, after, job)


def served_adaptation_rows(
    adaptation: ServedAdaptation, dataset: Dataset, submap_of: Sequence[int], label: str
) -> tuple[MethodResult, MethodResult]:
    """The before and after rows (:func:`served_method`) on the test queries."""
    subset = replace(dataset, queries=[dataset.queries[i] for i in adaptation.test])
    k_shots = adaptation.shots_per_submap
    before = served_method(
        f"served-before-adapt-k{k_shots}",
        f"{label} (as served, before adapting)",
        adaptation.before,
        subset,
        submap_of,
    )
    after = served_method(
        f"served-adapted-k{k_shots}",
        f"{label} (as served, adapted from {len(adaptation.shots)} revisit pairs, "
        f"{k_shots}/submap)",
        adaptation.after,
        subset,
        submap_of,
    )
    return before, after


def served_adaptation_rows_for(
    dataset: Dataset,
    submap_of: Sequence[int],
    pipeline: FeaturePipeline,
    *,
    shots: Sequence[int],
    k: int,
    cache_dir: Path | None,
    calibration: dict[str, object],
    label: str,
) -> list[RetrainingRow]:
    """One calibrated service pass per K (features from the cache), each adapted as served;
    the rows before -> after on the same test queries, with the job's verdict as the gate."""
    revisited = query_submaps(dataset, submap_of)
    partners = partner_of(dataset)
    names = {int(s): submap_name(int(s)) for s in set(submap_of)}
    extractor = pipeline.preset.local.name
    rows: list[RetrainingRow] = []
    for k_shots in shots:

        def hook(
            service: AtlasService,
            queries: list[FrameFeatures],
            frame_to_reference: dict[int, int],
            k_shots: int = k_shots,
        ) -> ServedAdaptation:
            return adapt_as_served(
                service,
                ATLAS,
                queries,
                frame_to_reference,
                k=k,
                extractor=extractor,
                revisited=revisited,
                partners=partners,
                k_shots=k_shots,
                submap_names=names,
                run_job=lambda kind, params: run_job(service, kind, params),
            )

        result = run_service_pass(
            dataset,
            submap_of,
            pipeline,
            k=k,
            cache_dir=cache_dir,
            label=f"{extractor} adapted as served, K={k_shots}",
            calibration=calibration,
            then=hook,
        )
        adaptation: ServedAdaptation = result.then
        before, after = served_adaptation_rows(adaptation, dataset, submap_of, label)
        metrics = adaptation.job["metrics"]
        gate = {
            **metrics.get("held_out", {}),
            "activated": bool(metrics.get("activated", False)),
            "job": adaptation.job["message"] or adaptation.job["error"],
        }
        gate["not_worse"] = gate["activated"]
        gate["frames"] = gate.get("pairs", 0)  # what the report's gate column counts
        rows.append(
            RetrainingRow(
                protocol=PROTOCOL,
                shots=k_shots,
                train_frames=int(metrics.get("training_pairs", 0)),
                test_queries=int(len(adaptation.test)),
                before=before,
                after=after,
                classifier_submap_accuracy=float("nan"),
                train_seconds=float(metrics.get("fit_seconds", 0.0)),
                epochs_run=0,
                best_epoch=1,
                shots_used=k_shots,
                calibrated=True,
                gate=gate,
            )
        )
    return rows
