"""Start-up and shutdown of everything a LoopNet process holds: database, CNNs, indexes.

Shared by the HTTP app (in its lifespan) and the CLI commands that work on the database
directly (``reindex``), so that both build the service the same way.
"""

from __future__ import annotations

import logging
import threading

import torch
from sqlalchemy import Engine, text
from sqlalchemy.orm import Session, sessionmaker

from service.app.catalog import AtlasService
from service.app.change_feed import ChangeFollower
from service.config import Settings
from service.errors import NotReady
from service.fleet.atlas_repair import clean_unfinished_restores
from service.fleet.keys import Authenticator, KeyAdmin
from service.fleet.snapshot_use_case import Snapshots
from service.jobs.operations import Jobs
from service.ml import weights
from service.ml.pipeline import FeaturePipeline
from service.runtime.queue import Queue
from service.storage.db import (
    make_engine,
    make_private_dir,
    make_session_factory,
    upgrade_database,
)

log = logging.getLogger(__name__)


class Runtime:
    """The process's service, built in the background so liveness answers during start-up."""

    def __init__(self, settings: Settings, pipeline: FeaturePipeline | None = None) -> None:
        self.settings = settings
        self._pipeline = pipeline  # an already loaded pipeline (tests share one)
        self.engine: Engine | None = None
        self.sessions: sessionmaker[Session] | None = None
        self._service: AtlasService | None = None
        self.error: str | None = None
        self._thread: threading.Thread | None = None
        self._queue: Queue | None = None
        self._follower: ChangeFollower | None = None
        self._authenticator: Authenticator | None = None

    def start(self, *, background: bool = True) -> None:
        """Migrate the database, then load the CNNs and every atlas's index."""
        make_private_dir(self.settings.data_dir)
        if self.settings.torch_threads:
            torch.set_num_threads(self.settings.torch_threads)
        weights.set_offline(self.settings.offline)
        upgrade_database(self.settings.resolved_database_url)
        self.engine = make_engine(self.settings.resolved_database_url)
        self.sessions = make_session_factory(self.engine)
        if background:
            self._thread = threading.Thread(target=self._load, name="loopnet-load", daemon=True)
            self._thread.start()
        else:
            self._load()
            if self.error:
                raise RuntimeError(self.error)

    def _load(self) -> None:
        try:
            # an injected pipeline (tests, `loopnet eval`) may run other settings than the preset
            preset = self._pipeline.preset if self._pipeline else self.settings.preset()
            log.info("loading model preset %r (%s, %s)", preset.name, preset.local, preset.backbone)
            assert self.sessions is not None
            clean_unfinished_restores(self.settings, self.sessions)  # a restore killed midway
            pipeline = self._pipeline or FeaturePipeline(preset, *self.settings.pipeline_options())
            service = AtlasService(self.settings, self.sessions, pipeline)
            service.frames.enqueue = lambda job_id: self.queue.enqueue(job_id)
            service.load_all()
            self._follower = ChangeFollower(
                self.sessions,
                service.follow,
                interval=self.settings.sync_seconds,
                retention_seconds=self.settings.change_retention_seconds,
            )
            self._follower.start()
            self._service = service
            log.info("ready")
        except Exception as exc:
            log.exception("start-up failed")
            self.error = f"{type(exc).__name__}: {exc}"

    def wait_ready(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def key_admin(self) -> KeyAdmin:
        """Key administration (creating, listing, revoking) on this process's database."""
        return KeyAdmin(self._sessions())

    @property
    def authenticator(self) -> Authenticator:
        """Checks the keys requests show (built once the database is open)."""
        if self._authenticator is None:
            self._authenticator = Authenticator(self.settings, self._sessions())
        return self._authenticator

    @property
    def jobs(self) -> Jobs:
        """Submitting, reading and cancelling jobs (queue opened on first use)."""
        return Jobs(self._sessions(), lambda job_id: self.queue.enqueue(job_id))

    @property
    def snapshots(self) -> Snapshots:
        """Export and restore of whole atlases (archives)."""
        return Snapshots(self.settings, self._sessions())

    def _sessions(self) -> sessionmaker[Session]:
        if self.sessions is None:
            raise NotReady("the service is starting")
        return self.sessions

    @property
    def queue(self) -> Queue:
        """The job queue (opened on first use: most processes never submit a job)."""
        if self._queue is None:
            self._queue = Queue(self.settings)
        return self._queue

    @property
    def ready(self) -> bool:
        return self._service is not None

    @property
    def service(self) -> AtlasService:
        if self._service is None:
            raise NotReady(
                f"start-up failed: {self.error}" if self.error else "the model is still loading"
            )
        return self._service

    @property
    def last_sync(self) -> float | None:
        """When (epoch seconds) this process last caught up with the change feed."""
        return self._follower.last_sync if self._follower is not None else None

    def database_reachable(self) -> bool:
        if self.engine is None:
            return False
        try:
            with self.engine.connect() as connection:
                connection.execute(text("SELECT 1"))
            return True
        except Exception:
            return False

    def stop(self) -> None:
        self.wait_ready(timeout=60)
        if self._follower is not None:
            self._follower.stop()
        if self._service is not None:
            self._service.flush()
        if self.engine is not None:
            self.engine.dispose()
