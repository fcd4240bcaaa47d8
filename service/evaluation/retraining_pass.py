"""Retrained LoopNet in the evaluation: the heads trained few-shot on the stored vectors.

The same stored (D, R) vectors as the untrained rows go through :func:`train_heads` (the
retraining job's own code, with the job's default parameters) and are ranked again. Two
protocols, both with K shots per submap and test queries that no training step has seen:

- ``map``: the shots are reference (map) frames only. This is what a retraining job does on
  an atlas before the robot comes back; every query is a test query.
- ``revisit``: the paper's few-shot protocol. Besides K map shots, K frames per submap from the
  *query* condition are labelled with their submap (in the service: revisits confirmed as loop
  closures and inserted into the submap, e.g. through ``observe``); the model is trained on
  both, and tested on the remaining queries only. Validation (best epoch, early stopping) uses
  map frames only.

Training splits the frames as the job does (:func:`split_for_job`: shots and validation outside
held-out stretches) and each row says what the job's not-worse gate decided on those stretches,
and so which version the service would serve. Rankings are over the reference frames only. The starting rows are re-scored on the same test
queries, so each "before -> after" pair compares like with like. With a calibration (the
service path), the heads train on the calibrated branches and start from the calibrated service
row, as a retraining job starts from the latest calibration; the trained embedding's scores come
from the impostor model the job refits (:func:`retrained_impostor_model`, on the stored
references). Without a calibration the job keeps no impostor model: the rows rank by cosine.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from service.evaluation.calibrated_pass import CalibratedBranches, top1_spread
from service.evaluation.datasets import Dataset
from service.evaluation.metrics import Ranking, correct_matrix, rank_by_similarity
from service.evaluation.protocol import MethodResult, evaluate_ranking
from service.evaluation.service_pass import PassResult
from service.ml.calibration import Calibration, CalibrationInputs
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.held_out import compare_on_held_out, split_for_job
from service.ml.pipeline import embed_vectors
from service.ml.retrained_impostors import ProbeRefit, retrained_impostor_model
from service.ml.training import TrainingConfig, TrainingData, split_shots, train_heads

PROTOCOLS = ("map", "revisit")
MAP_ROBOT, QUERY_ROBOT = "map", "query"  # the two traversals, as two robots' sequences


@dataclass
class StartingPoint:
    """What the retrained heads start from: the references' and queries' branch vectors, the
    heads over them, and the row they are compared with (same test queries)."""

    references: tuple[np.ndarray, np.ndarray]
    queries: tuple[np.ndarray, np.ndarray]
    base: HeadsConfig
    before: MethodResult
    calibration: Calibration | None = None
    stored: CalibrationInputs | None = None

    @property
    def calibrated(self) -> bool:
        return self.calibration is not None

    @classmethod
    def of(
        cls, result: PassResult, before: MethodResult, calibrated: CalibratedBranches | None
    ) -> StartingPoint:
        """The calibrated branches when there is a calibration, else the stored (D, R)."""
        if calibrated is None:
            local, global_ = result.reference_vectors
            base = HeadsConfig(local.shape[1], global_.shape[1], alpha=result.preset.alpha)
            return cls(result.reference_vectors, result.query_vectors, base, before)
        if result.stored_references is None:
            raise RuntimeError("the service pass kept no stored references to refit scores on")
        calibration = calibrated.calibration
        return cls(
            calibrated.references,
            calibrated.queries,
            calibration.heads_config(),
            before,
            calibration,
            result.stored_references,
        )


@dataclass
class RetrainingRow:
    """One protocol and K: the untrained and the retrained method on the same test queries."""

    protocol: str
    shots: int
    train_frames: int
    test_queries: int
    before: MethodResult
    after: MethodResult
    classifier_submap_accuracy: float
    train_seconds: float
    epochs_run: int
    best_epoch: int
    shots_used: int = 0
    calibrated: bool = False
    gate: dict[str, Any] = field(default_factory=dict)

    @property
    def served(self) -> MethodResult:
        """What the service would answer with: the new version when the job's not-worse gate
        passes it, else the one it started from."""
        return self.after if self.gate.get("not_worse", True) else self.before

    def row(self) -> dict[str, Any]:
        return {
            "protocol": self.protocol,
            "shots": self.shots,
            "train_frames": self.train_frames,
            "test_queries": self.test_queries,
            "before": _summary(self.before),
            "after": _summary(self.after),
            "classifier_submap_accuracy": self.classifier_submap_accuracy,
            "train_seconds": self.train_seconds,
            "epochs_run": self.epochs_run,
            "best_epoch": self.best_epoch,
            "shots_used": self.shots_used,
            "starting_heads": self.best_epoch == 0,
            "calibrated_start": self.calibrated,
            "top1_spread": self.after.details.get("top1_spread"),
            "gate": self.gate,
            "served": "retrained" if self.served is self.after else "starting",
            "served_recall@1": self.served.recall[1],
        }


def _summary(method: MethodResult) -> dict[str, Any]:
    return {k: v for k, v in method.row().items() if k not in ("pr_curve", "details")}


def shots_used(submaps: np.ndarray, shots: np.ndarray) -> int:
    """The most map shots any submap gave (K beyond a submap's size minus one is not used)."""
    if len(shots) == 0:
        return 0
    return int(np.unique(submaps[shots], return_counts=True)[1].max())


def query_submaps(dataset: Dataset, submap_of: Sequence[int]) -> np.ndarray:
    """The submap each query revisits (its middle right reference's), -1 when unanswerable."""
    labels = np.full(len(dataset.queries), -1, dtype=np.int64)
    for i, query in enumerate(dataset.queries):
        if query.positives:
            positives = sorted(query.positives)
            labels[i] = submap_of[positives[len(positives) // 2]]
    return labels


def classifier_accuracy(
    heads: LoopNetHeads,
    queries: tuple[np.ndarray, np.ndarray],
    dataset: Dataset,
    submap_of: Sequence[int],
) -> float:
    """Share of answerable queries whose predicted submap (classification head) holds a right
    reference: the paper's submap accuracy, from the classifier rather than the nearest frame."""
    answerable = [i for i, q in enumerate(dataset.queries) if q.positives]
    if not answerable or heads.classifier is None:
        return float("nan")
    with torch.inference_mode():
        logits = heads.classify(torch.from_numpy(queries[0]), torch.from_numpy(queries[1]))
    predicted = np.asarray(heads.class_labels)[logits.argmax(dim=1).numpy()]
    submaps = np.asarray(submap_of)
    right = [
        bool((submaps[sorted(dataset.queries[i].positives)] == predicted[i]).any())
        for i in answerable
    ]
    return float(np.mean(right))


def _subset(dataset: Dataset, keep: np.ndarray) -> Dataset:
    return replace(dataset, queries=[dataset.queries[i] for i in keep])


def _rows(ranking: Ranking, keep: np.ndarray) -> Ranking:
    return Ranking(ranking.indices[keep], ranking.scores[keep])


def _scored(
    heads: LoopNetHeads,
    start: StartingPoint,
    ranking: Ranking,
    refit: ProbeRefit | None = None,
) -> tuple[Ranking, str]:
    """The ranking with the calibrated scores of the impostor model the job refits for the
    trained heads (``refit``: as :func:`retrained_impostor_model`), or with cosines where
    there is no calibration (nor, in the job, a score)."""
    if start.calibration is None or start.stored is None:
        return ranking, "cosine (uncalibrated start: the job keeps no impostor model)"
    impostors = retrained_impostor_model(heads, start.calibration, start.stored, refit)
    scored = Ranking(ranking.indices, impostors.score(ranking.scores))
    return scored, "calibrated: -log10 P(impostor cosine >= c), refitted as the job does"


def revisit_shots(revisited: np.ndarray, k_shots: int) -> np.ndarray:
    """``k_shots`` query-condition frames per revisited submap (``revisited``: each query's
    submap, -1 when unanswerable), as the revisit protocols pick them: query indices."""
    answerable = np.flatnonzero(revisited >= 0)
    picked, _ = split_shots(revisited[answerable], k_shots)
    return np.asarray(answerable[picked], dtype=np.int64)


def shot_data(
    start: StartingPoint, ref_submaps: np.ndarray, revisited: np.ndarray, k_shots: int | None
) -> tuple[np.ndarray, np.ndarray, TrainingData]:
    """The query shots (``k_shots`` query-condition frames per revisited submap, as the revisit
    protocol labels them; None: none, the map protocol), the test queries (every other one) and
    the training data: the references with the query shots appended as a second robot."""
    ref_local, ref_global = start.references
    query_local, query_global = start.queries
    n_refs = len(ref_submaps)
    query_shots = (
        np.zeros(0, dtype=np.int64) if k_shots is None else revisit_shots(revisited, k_shots)
    )
    test = np.setdiff1d(np.arange(len(revisited)), query_shots)
    # the references' ids as the atlas stored them (what a refitted impostor probe names its
    # frames by), the shots' after every one of them, in query order
    ref_ids = (
        np.asarray(start.stored.order, np.int64)
        if start.stored is not None and len(start.stored) == n_refs
        else np.arange(n_refs)
    )
    first_shot_id = int(ref_ids.max()) + 1 if n_refs else 0
    data = TrainingData(
        local=np.concatenate([ref_local, query_local[query_shots]]),
        global_=np.concatenate([ref_global, query_global[query_shots]]),
        submaps=np.concatenate([ref_submaps, revisited[query_shots]]),
        frame_ids=np.concatenate([ref_ids, first_shot_id + query_shots]),
        robots=np.array([MAP_ROBOT] * n_refs + [QUERY_ROBOT] * len(query_shots)),
    )
    return query_shots, test, data


def retraining_rows(
    dataset: Dataset,
    submap_of: Sequence[int],
    result: PassResult,
    start: StartingPoint,
    *,
    shots: Sequence[int],
    protocols: Sequence[str] = PROTOCOLS,
    params: Mapping[str, Any] | None = None,
    k: int = 10,
    extractor_label: str = "DISK",
) -> list[RetrainingRow]:
    """Train and evaluate one retrained model per (protocol, K) from ``start``, with the job's
    default parameters except ``params`` (``TrainingConfig`` fields)."""
    unknown = set(protocols) - set(PROTOCOLS)
    if unknown:
        raise ValueError(f"unknown retraining protocol(s) {sorted(unknown)}; use {PROTOCOLS}")
    ref_local, ref_global = start.references
    query_local, query_global = start.queries
    ref_submaps = np.asarray(submap_of, dtype=np.int64)
    n_refs = len(ref_submaps)
    revisited = query_submaps(dataset, submap_of)
    base = start.base
    untrained = start.before
    extraction_ms = np.add.reduce(
        [
            np.asarray(result.stage_ms[s][n_refs:])
            for s in ("decode", "local_features", "global_features")
        ]
    )
    map_data = TrainingData(
        ref_local, ref_global, ref_submaps, np.arange(n_refs), np.array([MAP_ROBOT] * n_refs)
    )
    rows: list[RetrainingRow] = []
    for protocol in protocols:
        for k_shots in shots:
            query_shots, test, data = shot_data(
                start, ref_submaps, revisited, None if protocol == "map" else k_shots
            )
            config = TrainingConfig(**{**(params or {}), "shots": k_shots})
            # the map's frames split as the job splits an atlas's; revisit shots all train
            split = split_for_job(map_data, k_shots)
            trained = train_heads(
                data,
                base,
                config,
                shot_idx=np.concatenate([split.shots, n_refs + np.arange(len(query_shots))]),
                validation_idx=split.validation,
            )
            heads = trained.heads
            gate = compare_on_held_out(
                LoopNetHeads(base).eval(), heads, data, split.held_out, config.positive_window
            )
            started = time.perf_counter()
            references = embed_vectors(heads, ref_local, ref_global)
            test_vectors = (query_local[test], query_global[test])
            ranking = rank_by_similarity(embed_vectors(heads, *test_vectors) @ references.T, k)
            per_query = (time.perf_counter() - started) * 1000.0 / max(len(test), 1)
            cosine_top = ranking.scores[:, 0].copy()
            ranking, score_text = _scored(heads, start, ranking)
            subset = _subset(dataset, test)
            right = correct_matrix(ranking, [q.positives for q in subset.queries])[:, 0]
            used = shots_used(ref_submaps, split.shots)
            name = f"retrained-{protocol}-k{k_shots}"
            shots_text = f"{used}" if used == k_shots else f"{used} (K={k_shots} asked)"
            start_text = "calibrated" if start.calibrated else "uncalibrated"
            label = f"LoopNet {extractor_label} {start_text}, retrained, {shots_text} " + (
                "map shots/submap" if protocol == "map" else "map + revisit shots/submap"
            )
            if int(trained.metrics["best_epoch"]) == 0:
                label += ": best epoch 0, i.e. the starting heads"
            after = evaluate_ranking(
                name,
                label,
                "retrained",
                ranking,
                subset,
                submap_of,
                query_ms=extraction_ms[test] + per_query,
                details={
                    "protocol": protocol,
                    "shots_per_submap": k_shots,
                    "training": {
                        key: trained.metrics[key]
                        for key in ("epochs_run", "best_epoch", "train_seconds", "shots")
                    },
                    "training_config": trained.metrics["config"],
                    "score": score_text,
                    "top1_spread": top1_spread(cosine_top, ranking.scores[:, 0], right),
                },
            )
            before = evaluate_ranking(
                f"untrained-{protocol}-k{k_shots}",
                untrained.label,
                "loopnet",
                _rows(untrained.ranking, test),
                subset,
                submap_of,
            )
            rows.append(
                RetrainingRow(
                    protocol=protocol,
                    shots=k_shots,
                    train_frames=int(len(split.shots) + len(query_shots)),
                    test_queries=int(len(test)),
                    before=before,
                    after=after,
                    classifier_submap_accuracy=classifier_accuracy(
                        heads, test_vectors, subset, submap_of
                    ),
                    train_seconds=float(trained.metrics["train_seconds"]),
                    epochs_run=int(trained.metrics["epochs_run"]),
                    best_epoch=int(trained.metrics["best_epoch"]),
                    shots_used=used,
                    calibrated=start.calibrated,
                    gate=gate,
                )
            )
    return rows
