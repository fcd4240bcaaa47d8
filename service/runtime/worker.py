"""``loopnet worker``: migrate the database, then consume jobs until stopped."""

from __future__ import annotations

import logging

from service.config import Settings
from service.runtime.queue import Queue
from service.runtime.recovery import start_sweeper
from service.storage.db import make_engine, make_session_factory, upgrade_database

log = logging.getLogger(__name__)


def run_worker(settings: Settings, workers: int = 1) -> None:
    """Run a Huey consumer (threads) for LoopNet's queue; SIGTERM/SIGINT stop it gracefully."""
    upgrade_database(settings.resolved_database_url)
    if settings.torch_threads:
        import torch

        torch.set_num_threads(settings.torch_threads)
    queue = Queue(settings)
    storage = f"Redis {settings.redis_url}" if settings.redis_url else str(settings.queue_path)
    log.info("worker consuming from %s with %d thread(s)", storage, workers)
    engine = make_engine(settings.resolved_database_url)
    stop_sweeper = start_sweeper(settings, make_session_factory(engine), queue)
    consumer = queue.huey.create_consumer(workers=workers, worker_type="thread", periodic=False)
    try:
        consumer.run()
    finally:
        stop_sweeper.set()
        engine.dispose()
