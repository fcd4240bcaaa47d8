"""The online replay as served: one robot's frames through ``POST /observe``'s use case with
every setting at the service's defaults (verification with the default matcher of the
cached keypoints, the loop decision's ``loop_probability``, sequences and consistency), and
the calibration the service runs at its milestones run during the replay (and, when asked,
the adaptation it queues after every N revisit pairs its observations kept).

A frame whose insert makes the atlas reach a milestone queues a calibration job
(:mod:`service.app.milestones`), as in the service; here the job runs at once in this process
with the job runner's own code (:func:`service.evaluation.served_jobs.run_job_now`), as a
worker would between two frames, and the next frame is answered by the calibrated model
version. The row's PR sweep runs over ``loop_probability`` (what the service thresholds) and
its operating point is the service's own ``status == "loop"`` (a frame whose pending loop a later
frame confirmed counts as one).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from tqdm import tqdm

from service.evaluation.feature_cache import CachedFeatures
from service.evaluation.loop_ground_truth import Trajectory
from service.evaluation.online_service import frame_times, observe_frame, replay_atlas
from service.evaluation.served_jobs import JobRun, queued_jobs, run_queued
from service.evaluation.served_pass import PARTS, decision_parts, loop_counts
from service.evaluation.served_sweep import (
    SEQUENCE_LOOP_LOGIT,
    answered_frames,
    confirmed_rows,
    decision_logit,
    loop_probability,
    swept_logit,
)
from service.ml.features import LocalFeatures
from service.ml.pipeline import FeaturePipeline

ANSWERS = 5  # candidates an observation returns (the API's default k)


@dataclass
class ServedReplay:
    """Per frame, in order: the frame index answered first (-1: none), its loop probability
    (0 without a decision), the decision's logit (-inf without one) and the same for closable
    answers only (-inf for one no threshold makes a loop, above every decision for a loop by
    the robot's sequence: served_sweep.swept_logit), status, decision parts (NaN:
    absent), sequence length used, the model version that answered, the frames of its current
    stay left out and the call's milliseconds; then the jobs run meanwhile."""

    references: list[int] = field(default_factory=list)
    probability: list[float] = field(default_factory=list)
    logits: list[float] = field(default_factory=list)
    closable_logits: list[float] = field(default_factory=list)
    status: list[str] = field(default_factory=list)
    parts: list[list[float]] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)
    stays: list[int] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    jobs: list[JobRun] = field(default_factory=list)
    threshold: float = 0.0
    verification: dict[str, Any] = field(default_factory=dict)


def served_replay(
    trajectory: Trajectory,
    features: CachedFeatures,
    local: list[LocalFeatures],
    pipeline: FeaturePipeline,
    *,
    length: int,
    exclude_recent: int,
    consistency: int,
    adapt_after_pairs: int | None = None,
) -> ServedReplay:
    """Observe every frame as the service at its defaults answers it (fusion at the preset's
    alpha), running each job a frame queues before the next frame; ``adapt_after_pairs``
    sets automatic adaptation's number of pairs (0: off; None: the service's default)."""
    count = len(features.local)
    times = frame_times(trajectory, count)
    dim = pipeline.local.descriptor_dim
    index_of: dict[int, int] = {}
    out = ServedReplay()
    with (
        replay_atlas(
            trajectory,
            pipeline,
            alpha=pipeline.preset.alpha,
            exclude_recent=exclude_recent,
            consistency=consistency,
            served=True,
            adapt_after_pairs=adapt_after_pairs,
        ) as service,
        queued_jobs(service) as queued,
    ):  # a worker that runs each job at once
        config = service.queries.verification.config
        out.threshold = service.settings.loop_probability_min
        out.verification = {"matcher": config.matcher, "top": config.top}
        desc = f"observe as served: {trajectory.name}"
        for t in tqdm(range(count), desc=desc, unit="frame"):
            frame_features = replace(features.frame(t, dim)[0], local=local[t])
            answer, frame_id, ms = observe_frame(
                service,
                frame_features,
                float(times[t]),
                k=ANSWERS,
                length=length,
                exclude_recent=exclude_recent,
            )
            for row in confirmed_rows(answer, index_of):  # earlier frames' loops, late
                out.closable_logits[row], out.status[row] = SEQUENCE_LOOP_LOGIT, "loop"
            index_of[frame_id] = t
            first = answered_frames(answer)
            out.references.append(index_of.get(first[0], -1) if first else -1)
            out.probability.append(loop_probability(answer))
            out.logits.append(decision_logit(answer))
            out.closable_logits.append(swept_logit(answer))
            out.status.append(answer.status)
            out.parts.append(decision_parts(answer))
            out.lengths.append(answer.sequence.length if answer.sequence is not None else 1)
            out.versions.append(answer.model_version)
            out.stays.append(answer.stay_frames)
            out.ms.append(ms)
            while queued:
                out.jobs.append(run_queued(service, queued.pop(0), t))
    return out


# the row's own sweep first: the decision's logit (ordered as loop_probability, which ties at
# 1.0 once rounded) over the answers the service could close (a loop by the robot's sequence at
# every threshold); then over every answer
SERVED_SWEEP = "decision logit, closable answers"
SWEEPS = {
    SERVED_SWEEP: "closable_logits",
    "decision.loop_probability": "probability",
    "decision logit": "logits",
}


def served_observations(
    served: ServedReplay, score: str = SERVED_SWEEP
) -> list[tuple[int, float, int, float]]:
    """``(reference, score, length, ms)`` per frame, the retrieval rows' shape, so one sweep
    (:func:`service.evaluation.online.replay`) scores both; no answer: -inf. ``score``: one of
    ``SWEEPS`` (the logit orders what the rounded probability ties at 1.0)."""
    scores = getattr(served, SWEEPS[score])
    return [
        (r, p if r >= 0 else -np.inf, n, ms)
        for r, p, n, ms in zip(served.references, scores, served.lengths, served.ms, strict=True)
    ]


def served_decisions(
    trajectory: Trajectory, served: ServedReplay, exclude_recent: int
) -> dict[str, Any]:
    """The served row's extra fields: the operating point at the defaults (status ``loop``),
    the jobs run during the replay, and each frame's answer (for reading the misses)."""
    right = np.array(
        [r in loops for r, loops in zip(served.references, trajectory.loops, strict=True)]
    )
    answerable = trajectory.answerable(exclude_recent)
    return {
        "score": SERVED_SWEEP,
        "operating_point": loop_counts(served.status, right, answerable, served.threshold),
        "verification": served.verification,
        "jobs": [asdict(job) for job in served.jobs],
        "parts": PARTS,
        "per_frame": {
            "reference": served.references,
            "loop_probability": np.round(served.probability, 4).tolist(),
            "logit": np.round(served.logits, 3).tolist(),
            "closable": np.isfinite(served.closable_logits).astype(int).tolist(),
            "status": served.status,
            "right": right.astype(int).tolist(),
            "model_version": served.versions,
            "stay_frames": served.stays,
            "parts": np.round(np.array(served.parts, np.float64), 4).tolist(),
        },
    }
