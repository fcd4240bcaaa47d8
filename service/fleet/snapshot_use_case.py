"""Export and restore of whole atlases as one use case bound to the process's database, so
that the API and the CLI call it without handling sessions."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.fleet.snapshot_restore import restore_atlas
from service.fleet.snapshots import export_atlas


class Snapshots:
    """Archives of atlases (:mod:`service.fleet.snapshots`, :mod:`~.snapshot_restore`)."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.settings = settings
        self.sessions = sessions

    def export(self, atlas: str, path: Path) -> dict[str, Any]:
        """Write the atlas to one archive at ``path``; returns its manifest."""
        return export_atlas(self.settings, self.sessions, atlas, path)

    def restore(self, path: Path, name: str | None = None) -> str:
        """Restore an archive as a new atlas (named ``name``, default: archived); its name."""
        return restore_atlas(self.settings, self.sessions, path, name=name)
