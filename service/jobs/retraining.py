"""A retraining job from start to finish, as the worker runs it.

Train new heads on the atlas's stored features, save them as the next model version, re-embed
every frame into a new index file beside the old one, and only then, in one transaction, make
the version active and the job succeeded. API processes notice the new active version and swap
their in-memory index atomically. A failed or cancelled job removes its files and leaves the
active version as it was.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import asdict
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from service.atlas import model_versions as models_store
from service.config import Settings
from service.index import AtlasIndex
from service.index.builder import add_stored_frames
from service.ml.heads import HeadsConfig
from service.ml.training import TrainingCancelled, TrainingConfig, TrainingData, train_heads
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.feature_store import load_stored_vectors
from service.storage.models import Atlas, Job, JobStatus

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
        if kind != "retrain":
            self._finish(job_id, JobStatus.FAILED, f"unknown job kind {kind!r}")
            log.error("job %d (atlas '%s'): failed, unknown kind %r", job_id, atlas_name, kind)
            return
        files: list[Any] = []
        try:
            version = self._retrain(job_id, atlas_id, params, files)
        except TrainingCancelled as exc:
            self._cleanup(files)
            self._finish(job_id, JobStatus.CANCELLED, str(exc))
            log.info("job %d (atlas '%s'): cancelled (%s)", job_id, atlas_name, exc)
        except Exception as exc:
            log.exception("job %d (atlas '%s'): failed", job_id, atlas_name)
            self._cleanup(files)
            self._finish(
                job_id, JobStatus.FAILED, f"{type(exc).__name__}: {exc}", traceback.format_exc()
            )
        else:
            log.info(
                "job %d (atlas '%s'): succeeded, model version %d is active",
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

    def _retrain(self, job_id: int, atlas_id: int, params: dict[str, Any], files: list[Any]) -> int:
        config = TrainingConfig(**params)
        self._progress(job_id, 1, "loading stored features")
        with self.sessions() as session:
            active = repo.active_model_version(session, atlas_id=atlas_id)
            base = models_store.VersionConfig.of(active).heads
            stored = load_stored_vectors(session, atlas_id)
        if len(stored) == 0:
            raise ValueError("the atlas has no frames to train on")
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

        result = train_heads(
            TrainingData(stored.local, stored.global_, stored.submaps, stored.ids),
            base,
            config,
            progress=on_epoch,
            should_stop=cancelled,
        )
        with self.sessions() as session:
            version = 1 + max(
                v.version for v in repo.list_model_versions(session, atlas_id=atlas_id)
            )
        weights = models_store.weights_file(self.settings.models_dir, atlas_id, version)
        files.append(weights)
        result.heads.save(weights)

        self._progress(job_id, 78, f"re-embedding {len(stored)} frames from stored features")
        if cancelled():
            raise TrainingCancelled("cancelled before re-embedding")
        started = time.perf_counter()
        index = AtlasIndex(result.heads.config.fused_dim)
        last_report = started

        def on_chunk(done: int) -> None:
            """Progress, throttled: it is also the heartbeat that tells a live job from a dead
            worker's (``job_stale_seconds``)."""
            nonlocal last_report
            if time.perf_counter() - last_report >= REPORT_SECONDS:
                last_report = time.perf_counter()
                self._progress(
                    job_id,
                    78 + 16 * done / len(stored),
                    f"re-embedding: {done}/{len(stored)} frames",
                )

        # fp32 like ingest, restore and reconcile: a frame's vector must not depend on which path
        # embedded it (bf16 re-embedding is in the benchmarks, not in the service)
        with self.sessions() as session:
            add_stored_frames(session, atlas_id, result.heads, index, progress=on_chunk)
        reembed_seconds = time.perf_counter() - started
        index_path = models_store.index_file(self.settings.index_dir, atlas_id, version)
        files.append(index_path)
        index.save(index_path)

        metrics = {
            **result.metrics,
            "reembed_seconds": round(reembed_seconds, 3),
            "indexed_frames": index.size,
        }
        self._progress(job_id, 95, "activating the new model version")
        with transaction(self.sessions) as session:
            job = jobs.get_job(session, job_id=job_id)
            if job.cancel_requested:
                raise TrainingCancelled("cancelled before activation")
            repo.create_model_version(
                session,
                atlas_id=atlas_id,
                config=models_store.VersionConfig(
                    result.heads.config, trained=True, training=asdict(config), job_id=job_id
                ).to_json(),
                metrics=metrics,
                weights_path=models_store.row_weights_path(
                    self.settings.models_dir, atlas_id, version
                ),
                activate=True,
            )
            jobs.finish_job(
                session,
                job=job,
                status=JobStatus.SUCCEEDED,
                message=f"model version {version} is active",
                metrics=metrics,
                model_version=version,
            )
        return version
