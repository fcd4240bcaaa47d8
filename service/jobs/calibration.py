"""A calibration job: fit the atlas's calibration on its stored features, then publish it as a
model version whose heads read the calibrated branches.

The vocabulary, the branch whitenings and the impostor model are fitted on every stored frame
(no labels); the frames are embedded from the branch vectors the fit computed, into a new
index file beside the active one, and the version becomes active in one transaction with the
job's success, like a retrained one: rollback is activating the previous version.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.app import model_versions as models_store
from service.app.verify import verification_config
from service.config import Settings
from service.index import AtlasIndex
from service.index.store import fill_version_table
from service.ml.active_model import ActiveModel
from service.ml.aggregators import AGGREGATORS
from service.ml.calibration import Calibration, CalibrationConfig, CalibrationInputs
from service.ml.heads import LoopNetHeads
from service.ml.impostors import frames_for_impostor_model
from service.ml.inlier_threshold import (
    InlierThreshold,
    fit_inlier_threshold,
    hard_impostors,
    midpoints,
    near_duplicate,
    one_stop,
)
from service.ml.pipeline import embed_vectors
from service.ml.stays import ELSEWHERE_SCORE, StayRule
from service.ml.training import TrainingCancelled
from service.ml.verification import Verifier, View
from service.storage import jobs
from service.storage import repository as repo
from service.storage.feature_store import load_calibration_inputs, load_local_features
from service.storage.models import Atlas

if TYPE_CHECKING:
    from service.jobs.retraining import JobRunner

# fewer frames cannot whiten two branches nor give the impostor model its distinct pairs (11)
MIN_FRAMES = max(10, frames_for_impostor_model())


def calibration_config(params: dict[str, Any]) -> CalibrationConfig:
    """The fit's configuration from a job's parameters (ValueError on a bad one)."""
    known = {"aggregator", "words", "alpha"}
    unknown = set(params) - known - {"milestone"}
    if unknown:
        raise ValueError(f"unknown calibration parameters: {sorted(unknown)}")
    config = CalibrationConfig(**{k: v for k, v in params.items() if k in known})
    if config.aggregator not in AGGREGATORS:
        raise ValueError(f"aggregator must be one of {sorted(AGGREGATORS)}")
    if config.words is not None and not 2 <= config.words <= 1024:
        raise ValueError(f"words must lie in [2, 1024], got {config.words}")
    return config


def run_calibration(
    runner: JobRunner, job_id: int, atlas_id: int, params: dict[str, Any], files: list[Any]
) -> int:
    """Fit, embed, publish; returns the new (active) model version."""
    config = calibration_config(params)
    runner._progress(job_id, 1, "reading stored descriptors")
    with runner.sessions() as session:
        inputs = load_calibration_inputs(session, atlas_id)
    if len(inputs) < MIN_FRAMES:
        raise ValueError(f"a calibration needs at least {MIN_FRAMES} frames, got {len(inputs)}")
    runner._progress(job_id, 10, f"fitting the calibration on {len(inputs)} frames")
    started = time.perf_counter()
    fitted = Calibration.fit(inputs, config)
    fit_seconds = time.perf_counter() - started
    calibration = fitted.calibration
    with runner.sessions() as session:
        if jobs.get_job(session, job_id=job_id).cancel_requested:
            raise TrainingCancelled("cancelled after fitting")
        version = 1 + max(v.version for v in repo.list_model_versions(session, atlas_id=atlas_id))
    path = models_store.calibration_file(runner.settings.models_dir, atlas_id, version)
    files.append(path)
    calibration.save(path)

    runner._progress(job_id, 80, f"embedding {len(inputs)} frames")
    started = time.perf_counter()
    heads = LoopNetHeads(calibration.heads_config()).eval()
    index = AtlasIndex(heads.config.fused_dim)
    embeddings = embed_vectors(heads, fitted.local_branch, fitted.global_branch)
    index.add(inputs.order, embeddings, list(inputs.robots))
    index.wait_rebuilt()
    index_path = models_store.index_file(runner.settings.index_dir, atlas_id, version)
    files.append(index_path)
    index.save(index_path)
    model = ActiveModel(heads, calibration)
    fill_version_table(runner.settings.vector_store, runner.sessions, atlas_id, version, model)
    threshold = None
    if runner.settings.verify_top > 0:
        runner._progress(job_id, 90, "calibrating the minimum inliers on hard impostors")
        stays = StayRule(
            calibration.score,
            alike=runner.settings.loop_score_min,
            elsewhere=min(ELSEWHERE_SCORE, runner.settings.loop_score_min),
        )
        threshold = calibrate_min_inliers(
            runner.settings, runner.sessions, atlas_id, embeddings, inputs, stays
        )
    metrics: dict[str, Any] = {
        "frames_at_fit": len(inputs),
        "fit_seconds": round(fit_seconds, 3),
        "stage_seconds": {k: round(v, 3) for k, v in fitted.timings_s.items()},
        "reembed_seconds": round(time.perf_counter() - started, 3),
        "indexed_frames": index.size,
        "dim": calibration.dim,
        "config": config.to_dict(),
        "verification": threshold.to_json() if threshold is not None else None,
    }
    runner.publish(
        job_id,
        atlas_id,
        models_store.VersionConfig(
            heads.config,
            job_id=job_id,
            calibration={
                "path": str(path.relative_to(runner.settings.models_dir)),
                "version": version,
                "frames_at_fit": len(inputs),
                "min_inliers": threshold.to_json() if threshold is not None else None,
            },
        ),
        metrics,
        weights_path=None,
        activate=True,
        message=f"model version {version} (calibrated on {len(inputs)} frames) is active",
    )
    return version


def calibrate_min_inliers(
    settings: Settings,
    sessions: sessionmaker[Session],
    atlas_id: int,
    embeddings: np.ndarray,
    inputs: CalibrationInputs,
    stays: StayRule | None = None,
) -> InlierThreshold:
    """Verify the atlas's hard impostors with the service's matcher and set the minimum
    inliers above them (see :mod:`service.ml.inlier_threshold`); ``stays``: the new version's
    scores, so a robot's frames of one stop are not each other's impostors."""
    order = np.asarray(inputs.order)
    pairs = hard_impostors(
        embeddings, inputs.robots, order, stays=stays, same_place=inputs.same_place
    )
    halfway = midpoints(inputs.robots, order, pairs)
    wanted = sorted(
        {int(order[i]) for pair in pairs for i in pair} | {int(order[m]) for m in halfway if m >= 0}
    )
    with sessions() as session:
        atlas = session.get(Atlas, atlas_id)
        if atlas is None:
            raise ValueError(f"atlas {atlas_id} was deleted")
        extractor = atlas.feature_signature["local"]["name"]
        stored = load_local_features(session, wanted)
        frames = repo.frames_by_id(session, frame_ids=wanted)
    config = verification_config(settings, extractor)
    verifier = Verifier(config)

    def view(frame: int) -> View:
        return View(stored[frame], (frames[frame].width, frames[frame].height))

    inliers, stops = [], 0
    for (i, j), middle in zip(pairs, halfway, strict=True):
        a, b = int(order[i]), int(order[j])
        if a not in stored or b not in stored:
            continue  # deleted meanwhile
        found = verifier.verify(view(a), view(b)).inliers
        m = int(order[middle]) if middle >= 0 else None
        keypoints = min(stored[a].count, stored[b].count)
        if (
            near_duplicate(found, keypoints)  # else no need to verify the halfway frame
            and m in stored
            and one_stop(found, verifier.verify(view(a), view(m)).inliers, keypoints)
        ):
            stops += 1  # the robot never left: the same place, no impostor
            continue
        inliers.append(found)
    return fit_inlier_threshold(config.matcher, inliers, one_stop_pairs=stops)
