"""The job kinds, each in one place: how its parameters are read (the same schema the API
validates at submit and the worker runs with), what the atlas must hold before it is queued,
and what runs it. :mod:`service.jobs.submit` and the worker's runner look kinds up here."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError
from sqlalchemy.orm import Session

from service.app.model_versions import VersionConfig
from service.app.revisit_pairs import pair_frames
from service.domain.statuses import JobKind
from service.errors import InvalidInput
from service.jobs.adaptation import run_adaptation
from service.jobs.adaptation_config import AdaptConfig
from service.jobs.calibration import MIN_FRAMES, calibration_config, run_calibration
from service.ml.training import TrainingConfig
from service.storage import repository as repo

if TYPE_CHECKING:
    from service.jobs.retraining import JobRunner

# runner, job id, atlas id, parameters, files written (removed if the job fails) -> version
Run = Callable[["JobRunner", int, int, dict[str, Any], list[Any]], int]


@dataclass(frozen=True)
class Kind:
    """One kind of job."""

    name: JobKind
    parse: Callable[[dict[str, Any]], Any]  # the parameters, or InvalidInput
    check_ready: Callable[[Session, int, str, Any], None]  # session, atlas id, name, parsed
    run: Run


def _invalid(exc: ValidationError) -> InvalidInput:
    problems = "; ".join(
        f"{'.'.join(str(p) for p in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors()
    )
    return InvalidInput(f"invalid job parameters: {problems}")


def _parse_retraining(params: dict[str, Any]) -> TrainingConfig:
    try:
        return TrainingConfig(**params)
    except ValidationError as exc:
        raise _invalid(exc) from exc


def _retraining_ready(session: Session, atlas_id: int, atlas: str, config: Any) -> None:
    """Frames in two submaps, and an ``embed_dim`` the atlas's active heads can fill."""
    active = repo.active_model_version(session, atlas_id=atlas_id)
    try:
        config.check_fits(VersionConfig.of(active).heads)
    except ValueError as exc:
        raise InvalidInput(str(exc)) from exc
    populated = repo.count_populated_submaps(session, atlas_id=atlas_id)
    if populated < 2:
        raise InvalidInput(
            f"retraining needs frames in at least two submaps; atlas '{atlas}' has {populated}"
        )


def _parse_calibration(params: dict[str, Any]) -> Any:
    try:
        return calibration_config(params)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(str(exc)) from exc


def _calibration_ready(session: Session, atlas_id: int, atlas: str, _: Any) -> None:
    frames = repo.count_frames(session, atlas_id=atlas_id)
    if frames < MIN_FRAMES:
        raise InvalidInput(
            f"a calibration needs at least {MIN_FRAMES} frames; atlas '{atlas}' has {frames}"
        )


def _parse_adaptation(params: dict[str, Any]) -> AdaptConfig:
    try:
        return AdaptConfig(**params)
    except ValidationError as exc:
        raise _invalid(exc) from exc
    except TypeError as exc:
        raise InvalidInput(f"invalid job parameters: {exc}") from exc


def _adaptation_ready(session: Session, atlas_id: int, atlas: str, config: Any) -> None:
    """Enough revisit pairs of the job's choice (refused with the reason otherwise)."""
    found = len(pair_frames(session, atlas_id=atlas_id, where=config.pair_filter()))
    if found < config.min_pairs:
        raise InvalidInput(
            f"refused: atlas '{atlas}' has {found} revisit pair(s) matching the job's "
            f"choice; adaptation needs at least {config.min_pairs} (closures observe kept: "
            "verified or its sequence's loops; or pairs labelled with POST "
            "/atlases/{atlas}/pairs)"
        )


def _run_retraining(
    runner: JobRunner, job_id: int, atlas_id: int, params: dict[str, Any], files: list[Any]
) -> int:
    return runner.retrain(job_id, atlas_id, params, files)


KINDS: dict[str, Kind] = {
    kind.name: kind
    for kind in (
        Kind(JobKind.RETRAIN, _parse_retraining, _retraining_ready, _run_retraining),
        Kind(JobKind.CALIBRATE, _parse_calibration, _calibration_ready, run_calibration),
        Kind(JobKind.ADAPT, _parse_adaptation, _adaptation_ready, run_adaptation),
    )
}


def kind_of(name: str) -> Kind:
    """The kind called ``name`` (InvalidInput naming the kinds there are)."""
    try:
        return KINDS[name]
    except KeyError:
        raise InvalidInput(
            f"unknown job kind {name!r}; choose one of {[str(k) for k in KINDS]}"
        ) from None
