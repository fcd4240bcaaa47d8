"""What the API and the CLI read about atlases: summaries, submaps, model versions, frames and
the loop closures recorded between robots, each in one session."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.app.change_feed import revisions
from service.app.loop_closures import list_loop_closures
from service.app.model_versions import VersionConfig
from service.domain.statuses import CalibrationState
from service.errors import Conflict
from service.ml.presets import FeatureSignature
from service.storage import repository as repo
from service.storage.models import Atlas, Frame, LoopClosure, ModelVersion, Submap

if TYPE_CHECKING:
    from service.app.state import LoadedAtlas

Sessions = sessionmaker[Session]


def summary_of(session: Session, atlas: Atlas) -> dict[str, Any]:
    version = repo.active_model_version(session, atlas_id=atlas.id)
    config = VersionConfig.of(version)
    return {
        "name": atlas.name,
        "description": atlas.description,
        "created_at": atlas.created_at,
        "submaps": repo.count_submaps(session, atlas_id=atlas.id),
        "frames": repo.count_frames(session, atlas_id=atlas.id),
        "active_model_version": version.version,
        "classifier_trained": config.trained,
        "feature_signature": atlas.feature_signature,
        "calibration": calibration_state(config),
    }


def calibration_state(config: VersionConfig) -> dict[str, Any]:
    """Whether the active version is calibrated, by which version's job, on how many frames."""
    if config.calibration is None:
        return {"state": CalibrationState.UNCALIBRATED, "version": None, "frames_at_fit": None}
    return {
        "state": CalibrationState.CALIBRATED,
        "version": config.calibration.get("version"),
        "frames_at_fit": config.calibration.get("frames_at_fit"),
    }


@dataclass(frozen=True)
class FrameRecord:
    atlas: str
    submap: str
    frame: Frame


@dataclass(frozen=True)
class ServedIndex:
    atlas: str
    frames: int  # in this process's index
    revisions_behind: int  # how far the database's change feed is ahead of the index


class Reads:
    """What the API and the CLI read about atlases, each read in one session of its own."""

    def __init__(self, sessions: Sessions) -> None:
        self.sessions = sessions

    def atlas_summary(self, name: str) -> dict[str, Any]:
        with self.sessions() as session:
            return summary_of(session, repo.get_atlas(session, name=name))

    def atlas_summaries(self, visible: Callable[[str], bool]) -> list[dict[str, Any]]:
        """The summaries of the atlases ``visible`` lets the caller see."""
        with self.sessions() as session:
            return [summary_of(session, a) for a in repo.list_atlases(session) if visible(a.name)]

    def unavailable_atlases(self, reasons: dict[int, str]) -> dict[str, str]:
        """Atlas name -> why it cannot be loaded, from ``reasons`` by atlas id (atlases deleted
        since are left out)."""
        if not reasons:
            return {}
        with self.sessions() as session:
            names = {a.id: a.name for a in repo.list_atlases(session)}
        return {names[i]: reason for i, reason in reasons.items() if i in names}

    def feature_signature(self, atlas: str) -> FeatureSignature:
        """The signature of the atlas's features (Conflict when its row holds none)."""
        with self.sessions() as session:
            stored = repo.get_atlas(session, name=atlas).feature_signature
        try:
            return FeatureSignature.from_json(stored)
        except ValueError as exc:
            raise Conflict(f"atlas '{atlas}' records no usable feature signature: {exc}") from exc

    def submaps_with_counts(self, atlas: str) -> list[tuple[Submap, int]]:
        with self.sessions() as session:
            return repo.list_submaps_with_counts(session, atlas=repo.get_atlas(session, name=atlas))

    def model_versions(self, atlas: str) -> list[ModelVersion]:
        with self.sessions() as session:
            found = repo.get_atlas(session, name=atlas)
            return repo.list_model_versions(session, atlas_id=found.id)

    def frame_record(self, atlas: str, frame_id: int) -> FrameRecord:
        with self.sessions() as session:
            found = repo.get_atlas(session, name=atlas)
            frame = repo.get_frame(session, atlas=found, frame_id=frame_id)
            return FrameRecord(found.name, frame.submap.name, frame)

    def loop_closures(
        self,
        atlas: str,
        *,
        robot: str | None = None,
        since: datetime | None = None,
        limit: int = 100,
    ) -> list[tuple[LoopClosure, str]]:
        with self.sessions() as session:
            found = repo.get_atlas(session, name=atlas)
            return list_loop_closures(
                session, atlas_id=found.id, robot=robot, since=since, limit=limit
            )

    def served_indexes(self, serving: list[LoadedAtlas]) -> list[ServedIndex]:
        """Each served atlas's index size and its lag behind the change feed (atlases deleted
        meanwhile are left out)."""
        with self.sessions() as session:
            names = {i: name for i, name in session.execute(select(Atlas.id, Atlas.name))}
            current = revisions(session)
        return [
            ServedIndex(
                names[state.atlas_id],
                state.index.size,
                max(0, current.get(state.atlas_id, 0) - state.revision),
            )
            for state in serving
            if state.atlas_id in names
        ]
