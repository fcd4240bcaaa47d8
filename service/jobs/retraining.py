"""A retraining job from start to finish, as the worker runs it (and the runner of every job
kind: a calibration job is in :mod:`service.jobs.calibration`).

Train new heads on the atlas's stored features (through the active version's calibration, when
it has one), compare them with the active heads on whole stretches of the route that no step of
training saw (:mod:`service.ml.held_out`), save them
as the next model version, re-embed every frame into a new index file beside the old one, and
only then, in one transaction, make the version active (when it is not worse, or the settings
force it) and the job succeeded, logged in the change feed: each API process's follower thread
loads the new version and swaps its in-memory state atomically. A failed or cancelled job
removes its files and leaves the
active version as it was.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.app import change_feed
from service.app import model_versions as models_store
from service.config import Settings
from service.index import AtlasIndex
from service.index.builder import add_stored_frames, load_model_inputs
from service.index.store import fill_version_table
from service.jobs.kinds import KINDS
from service.ml.active_model import ActiveModel
from service.ml.adaptation import NoUsefulPairs
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.held_out import compare_on_held_out, split_for_job
from service.ml.retrained_impostors import ProbeRefit, retrained_impostor_model
from service.ml.training import (
    TrainingCancelled,
    TrainingConfig,
    TrainingData,
    train_heads,
)
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.feature_store import load_calibration_inputs
from service.storage.models import Atlas, Job, JobStatus

if TYPE_CHECKING:
    from service.ml.calibration import Calibration

log = logging.getLogger(__name__)

REPORT_SECONDS = 2.0  # at most one progress write per this many seconds while re-embedding


class JobRunner:
    """Runs one job id against the database; reports progress and honours cancellation."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.settings = settings
        self.sessions = sessions

    def run(self, job_id: int) -> None:
        """Run the job and log one line with its id, atlas and outcome."""
        with transaction(self.sessions) as session:
            job = jobs.start_job(session, job_id=job_id)
            if job is None:
                found = session.get(Job, job_id)
                status = found.status if found else "unknown"
                log.info("job %d: not run, it is %s", job_id, status)
                return
            kind, atlas_id, params = job.kind, job.atlas_id, dict(job.params)
            atlas = session.get(Atlas, atlas_id)
            atlas_name = atlas.name if atlas else f"#{atlas_id}"
        log.info("job %d (%s of atlas '%s'): started", job_id, kind, atlas_name)
        job_kind = KINDS.get(kind)
        if job_kind is None:
            self._finish(job_id, JobStatus.FAILED, f"unknown job kind {kind!r}")
            log.error("job %d (atlas '%s'): failed, unknown kind %r", job_id, atlas_name, kind)
            return
        files: list[Any] = []
        try:
            version = job_kind.run(self, job_id, atlas_id, params, files)
        except TrainingCancelled as exc:
            self._cleanup(files)
            self._finish(job_id, JobStatus.CANCELLED, str(exc))
            log.info("job %d (atlas '%s'): cancelled (%s)", job_id, atlas_name, exc)
        except NoUsefulPairs as exc:  # refused, nothing changed: the reason is the message
            self._cleanup(files)
            self._finish(job_id, JobStatus.FAILED, f"refused: {exc}")
            log.info("job %d (atlas '%s'): refused (%s)", job_id, atlas_name, exc)
        except Exception as exc:
            log.exception("job %d (atlas '%s'): failed", job_id, atlas_name)
            self._cleanup(files)
            self._finish(
                job_id, JobStatus.FAILED, f"{type(exc).__name__}: {exc}", traceback.format_exc()
            )
        else:
            log.info(
                "job %d (atlas '%s'): succeeded, model version %d recorded",
                job_id,
                atlas_name,
                version,
            )

    def _progress(self, job_id: int, percent: float, message: str) -> bool:
        with transaction(self.sessions) as session:
            return jobs.report_progress(session, job_id=job_id, progress=percent, message=message)

    def _finish(self, job_id: int, status: str, message: str, error: str | None = None) -> None:
        with transaction(self.sessions) as session:
            job = jobs.get_job(session, job_id=job_id)
            jobs.finish_job(
                session, job=job, status=status, message=message, error=error or message
            )

    @staticmethod
    def _cleanup(files: list[Any]) -> None:
        for path in files:
            path.unlink(missing_ok=True)

    def retrain(self, job_id: int, atlas_id: int, params: dict[str, Any], files: list[Any]) -> int:
        config = TrainingConfig(**params)
        self._progress(job_id, 1, "loading stored features")
        with self.sessions() as session:
            active = repo.active_model_version(session, atlas_id=atlas_id)
            active_heads = models_store.load_heads(active, self.settings.models_dir)
            active_config = models_store.VersionConfig.of(active)
            # retraining starts from the latest calibration: the heads read its branches
            calibration = models_store.load_calibration(active, self.settings.models_dir)
            stored = load_model_inputs(session, atlas_id, calibration)
        if len(stored) == 0:
            raise ValueError("the atlas has no frames to train on")
        base = active_config.heads
        config.check_fits(base)
        base = HeadsConfig(
            local_dim=base.local_dim,
            global_dim=base.global_dim,
            alpha=base.alpha,
            hidden_dim=base.hidden_dim,
        )

        def on_epoch(fraction: float, message: str) -> None:
            self._progress(job_id, 5 + 70 * fraction, f"training: {message}")

        def cancelled() -> bool:
            with self.sessions() as session:
                return jobs.get_job(session, job_id=job_id).cancel_requested

        data = TrainingData(
            stored.local, stored.global_, stored.submaps, stored.ids, np.asarray(stored.robots)
        )
        split = split_for_job(data, config.shots)
        result = train_heads(
            data,
            base,
            config,
            progress=on_epoch,
            should_stop=cancelled,
            shot_idx=split.shots,
            validation_idx=split.validation,
        )
        gate = compare_on_held_out(
            active_heads, result.heads, data, split.held_out, config.positive_window
        )
        activate = gate["not_worse"] or self.settings.retrain_activate_worse
        version, weights, version_calibration = self.write_version_files(
            job_id, atlas_id, result.heads, calibration, active_config, files, progress=76
        )

        metrics: dict[str, Any] = {**result.metrics, "held_out": gate, "activated": activate}
        if activate:
            self._progress(job_id, 78, f"re-embedding {len(stored)} frames from stored features")
            if cancelled():
                raise TrainingCancelled("cancelled before re-embedding")
            model = ActiveModel(result.heads, calibration)
            metrics.update(self._reembed(job_id, atlas_id, version, model, len(stored), files))
        verdict = _verdict(gate, activate)
        self._progress(job_id, 95, "recording the new model version")
        self.publish(
            job_id,
            atlas_id,
            models_store.VersionConfig(
                result.heads.config,
                trained=True,
                training=asdict(config),
                job_id=job_id,
                calibration=version_calibration,
            ),
            metrics,
            weights_path=str(weights.relative_to(self.settings.models_dir)),
            activate=activate,
            message=f"model version {version} {verdict}",
        )
        return version

    def write_version_files(
        self,
        job_id: int,
        atlas_id: int,
        heads: LoopNetHeads,
        calibration: Calibration | None,
        active_config: models_store.VersionConfig,
        files: list[Any],
        *,
        progress: float,
        impostor_refit: ProbeRefit | None = None,
    ) -> tuple[int, Path, dict[str, Any] | None]:
        """The next version's number, its heads' weights file and, on a calibrated atlas, its
        calibration with the impostor model refitted on the new heads (a trained embedding
        changes what a cosine means; refitted as the calibration fitted it, unseen frames
        against seen ones; ``impostor_refit``: heads fitted on the atlas, refitted without
        the probe's held-out frames). Every file written is appended to ``files``."""
        with self.sessions() as session:
            version = 1 + max(
                v.version for v in repo.list_model_versions(session, atlas_id=atlas_id)
            )
        weights = models_store.weights_file(self.settings.models_dir, atlas_id, version)
        files.append(weights)
        heads.save(weights)
        if calibration is None or active_config.calibration is None:
            return version, weights, None
        self._progress(job_id, progress, "refitting the impostor model")
        with self.sessions() as session:
            inputs = load_calibration_inputs(session, atlas_id)
        calibration.impostors = retrained_impostor_model(heads, calibration, inputs, impostor_refit)
        del inputs
        path = models_store.calibration_file(self.settings.models_dir, atlas_id, version)
        files.append(path)
        calibration.save(path)
        return (
            version,
            weights,
            {**active_config.calibration, "path": str(path.relative_to(self.settings.models_dir))},
        )

    def publish(
        self,
        job_id: int,
        atlas_id: int,
        config: models_store.VersionConfig,
        metrics: dict[str, Any],
        *,
        weights_path: str | None,
        activate: bool,
        message: str,
    ) -> None:
        """In one transaction: the new model version (active or not) and the job's success;
        a cancellation requested meanwhile wins."""
        with transaction(self.sessions) as session:
            job = jobs.get_job(session, job_id=job_id)
            if job.cancel_requested:
                raise TrainingCancelled("cancelled before activation")
            created = repo.create_model_version(
                session,
                atlas_id=atlas_id,
                config=config.to_json(),
                metrics=metrics,
                weights_path=weights_path,
                activate=activate,
            )
            jobs.finish_job(
                session,
                job=job,
                status=JobStatus.SUCCEEDED,
                message=message,
                metrics=metrics,
                model_version=created.version,
            )
            if activate:  # every API process's follower thread swaps to it
                change_feed.record_activation(session, atlas_id=atlas_id, version=created.version)

    def _reembed(
        self,
        job_id: int,
        atlas_id: int,
        version: int,
        model: ActiveModel,
        frames: int,
        files: list[Any],
    ) -> dict[str, Any]:
        """Embed every stored frame with ``model`` into the version's index file."""
        started = time.perf_counter()
        index = AtlasIndex(model.dim)
        last_report = started

        def on_chunk(done: int) -> None:
            """Progress, throttled: it is also the heartbeat that tells a live job from a dead
            worker's (``job_stale_seconds``)."""
            nonlocal last_report
            if time.perf_counter() - last_report >= REPORT_SECONDS:
                last_report = time.perf_counter()
                self._progress(
                    job_id, 78 + 16 * done / max(frames, 1), f"re-embedding: {done}/{frames} frames"
                )

        # fp32 like ingest, restore and reconcile: a frame's vector must not depend on which path
        # embedded it (bf16 re-embedding is in the benchmarks, not in the service)
        with self.sessions() as session:
            add_stored_frames(session, atlas_id, model, index, progress=on_chunk)
        index_path = models_store.index_file(self.settings.index_dir, atlas_id, version)
        files.append(index_path)
        index.save(index_path)
        fill_version_table(self.settings.vector_store, self.sessions, atlas_id, version, model)
        return {
            "reembed_seconds": round(time.perf_counter() - started, 3),
            "indexed_frames": index.size,
        }


def _verdict(gate: dict[str, Any], activated: bool) -> str:
    if gate["change"] is None:
        return "is active (no held-out frames to compare on)"
    change = (
        f"held-out stretches ({gate['frames']} frames) retrieval accuracy "
        f"{gate['active']:.3f} -> {gate['new']:.3f}, mean average precision "
        f"{gate['map_active']:.3f} -> {gate['map_new']:.3f}"
    )
    if activated:
        return f"is active ({change})" if gate["not_worse"] else f"is active, forced ({change})"
    return f"was not activated: worse than the active version ({change})"
