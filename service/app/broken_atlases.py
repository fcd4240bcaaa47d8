"""Atlases whose state cannot be loaded, kept apart so that one broken atlas never takes the
service down: its routes answer 503 with the reason, the others serve, ``/v1/ready`` lists it.

A failed load is retried at most once per period (a repair made meanwhile, e.g. another model
version activated, is picked up without a restart), and forgotten once a load succeeds.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from service.errors import AtlasUnavailable, NotFound

log = logging.getLogger(__name__)

T = TypeVar("T")


class BrokenAtlases:
    """The reason each broken atlas failed to load, and when it was last tried."""

    def __init__(self, retry_seconds: float, data_dir: Path) -> None:
        self.retry_seconds = retry_seconds
        self._hide = str(data_dir.resolve())  # reasons never show server paths
        self._failed: dict[int, tuple[str, float]] = {}
        self._lock = threading.Lock()

    def load(self, atlas_id: int, load: Callable[[], T]) -> T:
        """``load()``, or AtlasUnavailable with the reason if it fails or failed just now."""
        with self._lock:
            failed = self._failed.get(atlas_id)
        if failed is not None and time.monotonic() - failed[1] < self.retry_seconds:
            raise AtlasUnavailable(failed[0])
        try:
            value = load()
        except NotFound:
            raise  # the atlas was deleted meanwhile: nothing is broken
        except Exception as exc:
            detail = f"{type(exc).__name__}: {exc}".replace(self._hide, "<data dir>")
            reason = f"atlas {atlas_id} cannot be loaded ({detail[:500]})"
            if failed is None or failed[0] != reason:
                log.error("%s; the other atlases still serve", reason)
            with self._lock:
                self._failed[atlas_id] = (reason, time.monotonic())
            raise AtlasUnavailable(reason) from exc
        if failed is not None:
            log.info("atlas %d loads again", atlas_id)
            with self._lock:
                self._failed.pop(atlas_id, None)
        return value

    def forget(self, atlas_id: int) -> None:
        with self._lock:
            self._failed.pop(atlas_id, None)

    def reasons(self) -> dict[int, str]:
        """Broken atlases by id, with why."""
        with self._lock:
            return {atlas_id: reason for atlas_id, (reason, _) in self._failed.items()}
