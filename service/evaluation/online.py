"""Online single-trajectory evaluation (the paper's setting: City Centre, New College): one
robot's frames replayed in order; each frame asks about everything before it except its own
recent frames, then joins the map.

The application call is the service's own observe path
(:func:`service.evaluation.online_service.service_observations`: search, sequence scoring from
the database, insert); :func:`observe` keeps the same steps on an in-memory map (exact search,
all frames' matches proposing candidates) for synthetic checks of the metrics. Features come
from the evaluation's feature cache (the same files ``loopnet eval`` writes), so no CNN runs
twice.

Metrics: precision-recall of loop closures, swept over the cosine (L = 1) or the sequence's
margin over its best rival place (L > 1: what the service decides a sequence loop on; a frame
is a true positive when its answer is one of its ground-truth partners; recall divides by the frames that have a partner in the map), recall
at 100% precision, with and without temporal consistency, and per-frame latency of the call.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service.evaluation.feature_cache import CachedFeatures
from service.evaluation.loop_ground_truth import Trajectory
from service.evaluation.metrics import precision_recall, summary
from service.evaluation.online_features import trajectory_local, trajectory_vectors
from service.evaluation.online_report import write_report
from service.evaluation.online_served import (
    SERVED_SWEEP,
    SWEEPS,
    served_decisions,
    served_observations,
    served_replay,
)
from service.evaluation.online_service import service_observations
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.pipeline import FeaturePipeline, embed_vectors
from service.ml.sequences import (
    ConsistencySettings,
    MapMoments,
    SequenceSettings,
    Trajectories,
    consistent_scores,
    distinctiveness,
    match_sequence,
)


@dataclass(frozen=True)
class OnlineSettings:
    """Attributes:
    length: sequence length L (1: single frame).
    exclude_recent: the robot's own last N frames never answer (the service's default).
    seeds: best single-frame matches kept per frame (candidates of the sequence step).
    consistency: temporal consistency of the accepted loops.
    """

    length: int = 10
    exclude_recent: int = 20
    seeds: int = SequenceSettings().seeds
    consistency: ConsistencySettings = field(default_factory=ConsistencySettings)


@dataclass
class OnlineMap:
    """What the in-memory application holds: every frame's unit vector, the map's moments,
    the trajectory order, and each frame's best matches so far (a cache: always recomputable
    from the vectors)."""

    vectors: np.ndarray
    trajectories: Trajectories
    settings: OnlineSettings
    moments: MapMoments
    in_map: int = 0
    seeds: dict[int, tuple[np.ndarray, np.ndarray, int]] = field(default_factory=dict)

    def admit(self, until: int) -> None:
        """Frames ``in_map .. until-1`` join the map (they are no longer recent)."""
        if until > self.in_map:
            self.moments.add(self.vectors[self.in_map : until])
            self.in_map = until

    def best_matches(self, frame: int) -> np.ndarray:
        """The frame's ``seeds`` best map frames over the current map, updated incrementally
        (only frames that joined since the last call are compared)."""
        indices, sims, seen = self.seeds.get(
            frame, (np.zeros(0, np.int64), np.zeros(0, np.float32), 0)
        )
        if seen < self.in_map:
            new = self.vectors[seen : self.in_map] @ self.vectors[frame]
            indices = np.concatenate([indices, np.arange(seen, self.in_map)])
            sims = np.concatenate([sims, new])
            keep = np.argsort(-sims, kind="stable")[: self.settings.seeds]
            indices, sims = indices[keep], sims[keep]
            self.seeds[frame] = (indices, sims, self.in_map)
        return indices


@dataclass(frozen=True)
class Observation:
    reference: int  # best map frame, -1 when the map is empty
    score: float  # sequence margin over the best rival (L > 1) or cosine similarity (L = 1)
    length: int
    ms: float


def observe(state: OnlineMap, frame: int) -> Observation:
    """One frame on the in-memory map: ask with the robot's recent sequence, then insert."""
    start = time.perf_counter()
    state.admit(max(frame - state.settings.exclude_recent, 0))
    if state.in_map == 0:
        return Observation(-1, -np.inf, 0, (time.perf_counter() - start) * 1000.0)
    window = state.trajectories.recent(frame, state.settings.length)
    seeds = [state.best_matches(int(j)) for j in window]
    if state.settings.length == 1:
        best = int(seeds[-1][0])
        score = float(state.vectors[best] @ state.vectors[frame])
        return Observation(best, score, 1, (time.perf_counter() - start) * 1000.0)
    in_map = state.in_map
    matches = match_sequence(
        state.vectors[window],
        seeds,
        state.vectors.__getitem__,
        state.trajectories,
        state.moments,
        SequenceSettings(length=state.settings.length, seeds=state.settings.seeds),
        eligible=lambda frames: frames < in_map,
        top=None,
    )
    distinct = distinctiveness(matches, state.trajectories, state.settings.consistency.max_step)
    ms = (time.perf_counter() - start) * 1000.0
    if distinct is None:
        return Observation(-1, -np.inf, 0, ms)
    return Observation(matches[0].reference, distinct.margin, matches[0].length, ms)


def replay(
    trajectory: Trajectory,
    vectors: np.ndarray,
    settings: OnlineSettings,
    observations: list[Observation] | None = None,
) -> dict[str, Any]:
    """Metrics of the answers to the replayed trajectory: ``observations`` (the service's),
    or :func:`observe` on the in-memory map when None."""
    trajectories = Trajectories.single(len(vectors), trajectory.starts)
    if observations is None:
        state = OnlineMap(vectors, trajectories, settings, MapMoments(vectors.shape[1]))
        observations = [observe(state, t) for t in range(len(vectors))]
    references = np.array([o.reference for o in observations], np.int64)
    scores = np.array([o.score for o in observations], np.float64)
    correct = np.array(
        [o.reference in loops for o, loops in zip(observations, trajectory.loops, strict=True)]
    )
    answerable = trajectory.answerable(settings.exclude_recent)
    rows: dict[str, Any] = {}
    consistency = settings.consistency
    for required in sorted({1, consistency.required}):
        accept_at = consistent_scores(
            references,
            scores,
            trajectories,
            ConsistencySettings(required=required, max_step=consistency.max_step),
            trajectory.starts,
        )
        decided = np.isfinite(accept_at)  # the others are never accepted as loops
        curve = precision_recall(accept_at[decided], correct[decided], answerable)
        rows[f"k={required}"] = {
            "consistency_required": required,
            "auc_pr": curve.auc,
            "recall_at_100_precision": curve.recall_at_full_precision,
            "threshold_at_100_precision": curve.threshold_at_full_precision,
            "best_match_right": float(correct.sum() / max(answerable, 1)),
        }
    return {
        "frames": len(vectors),
        "answerable": answerable,
        "settings": asdict(settings),
        "decisions": rows,
        "latency_ms": summary([o.ms for o in observations]),
        "mean_length_used": float(np.mean([o.length for o in observations])),
        "latency_note": "the observe call only (search + sequence scoring); CNNs not included",
    }


def unit_embeddings(features: CachedFeatures, alpha: float) -> np.ndarray:
    heads = LoopNetHeads(
        HeadsConfig(
            local_dim=features.local.shape[1], global_dim=features.global_.shape[1], alpha=alpha
        )
    ).eval()
    return embed_vectors(heads, features.local, features.global_)


@dataclass(frozen=True)
class OnlineConfig:
    """One replay run: the trajectory, the features and the settings swept.

    Attributes:
        methods: (name, extractor, alpha) of each descriptor replayed (retrieval rows:
            untrained heads, no verification, no calibration).
        lengths: sequence lengths L of the retrieval rows (1 = single frame).
        served_lengths: sequence lengths L of the ``loopnet-<extractor>-served`` rows (one per
            extractor and L: the service's defaults, calibration at the milestones during the
            replay; :mod:`service.evaluation.online_served`).
        served_adapt_after: for each N, the same served rows again with automatic adaptation
            after every N revisit pairs instead of the service's default (0: off;
            ``loopnet-<extractor>-served-adaptN``).
    """

    trajectory: Trajectory
    output: Path
    methods: tuple[tuple[str, str, float], ...]
    lengths: tuple[int, ...]
    preset: str = "default"
    long_side: int | None = None
    cache_dir: Path | None = None
    exclude_recent: int = 20
    consistency: int = 3
    command: str = ""
    served_lengths: tuple[int, ...] = (10,)
    served_adapt_after: tuple[int, ...] = ()


def run_online(config: OnlineConfig) -> dict[str, Any]:
    """Replay the trajectory once per method and L, then once per extractor and served L as
    served; write online.json and online.md."""
    from service.ml.presets import resolve_preset

    rows = []
    features_text = []
    pipelines: dict[str, FeaturePipeline] = {}
    for name, extractor, alpha in config.methods:
        if extractor not in pipelines:
            preset = resolve_preset(config.preset, extractor=extractor, long_side=config.long_side)
            pipelines[extractor] = FeaturePipeline(preset)
        pipeline = pipelines[extractor]
        features = trajectory_vectors(config.trajectory, pipeline, config.cache_dir)
        vectors = unit_embeddings(features, alpha)
        features_text.append(
            f"{name}: {extractor} at long side {pipeline.preset.local.long_side} + "
            f"{pipeline.preset.backbone.name}, untrained heads at alpha {alpha:g}"
        )
        for length in config.lengths:
            settings = _settings(config, length)
            answers = service_observations(
                config.trajectory,
                features,
                pipeline,
                alpha=alpha,
                length=length,
                exclude_recent=config.exclude_recent,
                consistency=config.consistency,
            )
            observations = [Observation(*answer) for answer in answers]
            rows.append(
                {"method": name, **replay(config.trajectory, vectors, settings, observations)}
            )
    for extractor, pipeline in pipelines.items():
        if config.served_lengths:
            features_text.append(
                f"loopnet-{extractor}-served: the service's defaults (alpha "
                f"{pipeline.preset.alpha:g}, verification, decision, calibration at milestones)"
            )
        for length in config.served_lengths:
            rows.append(_served_row(config, extractor, pipeline, length))
            for pairs in config.served_adapt_after:
                rows.append(_served_row(config, extractor, pipeline, length, pairs))
    report = {
        "command": config.command,
        "trajectory": config.trajectory.name,
        "ground_truth": config.trajectory.ground_truth,
        "features": "; ".join(features_text),
        "adapter": "AtlasService.observe_features (the service's observe path, SQLite)",
        "rows": rows,
    }
    write_report(report, config.output)
    return report


def _settings(config: OnlineConfig, length: int) -> OnlineSettings:
    return OnlineSettings(
        length=length,
        exclude_recent=config.exclude_recent,
        consistency=ConsistencySettings(required=config.consistency),
    )


def _served_row(
    config: OnlineConfig,
    extractor: str,
    pipeline: FeaturePipeline,
    length: int,
    adapt_after_pairs: int | None = None,
) -> dict[str, Any]:
    """The ``loopnet-<extractor>-served`` row at L: the replay as served, swept by
    :func:`replay` (k=1, and with the protocol's consistency) over the decision's logit among
    the answers the service could close (``sweeps`` adds the same over every answer, by
    probability and by logit), plus the operating point at the defaults and the jobs run
    during the replay."""
    trajectory = config.trajectory
    features = trajectory_vectors(trajectory, pipeline, config.cache_dir)
    local = trajectory_local(trajectory, pipeline, config.cache_dir)
    served = served_replay(
        trajectory,
        features,
        local,
        pipeline,
        length=length,
        exclude_recent=config.exclude_recent,
        consistency=config.consistency,
        adapt_after_pairs=adapt_after_pairs,
    )
    vectors = unit_embeddings(features, pipeline.preset.alpha)
    adapting = f"-adapt{adapt_after_pairs}" if adapt_after_pairs is not None else ""
    row: dict[str, Any] = {"method": f"loopnet-{extractor}-served{adapting}"}
    for score in SWEEPS:
        observations = [Observation(*a) for a in served_observations(served, score)]
        swept = replay(trajectory, vectors, _settings(config, length), observations)
        if score == SERVED_SWEEP:
            row.update(swept)
        row.setdefault("sweeps", {})[score] = swept["decisions"]
    row["latency_note"] = (
        "the observe call as served (search, sequence, verification, decision); CNNs and the "
        "jobs run between frames not included"
    )
    return {**row, **served_decisions(trajectory, served, config.exclude_recent)}
