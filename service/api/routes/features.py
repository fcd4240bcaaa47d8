"""Frames and queries from precomputed features (robots that run the extractor on board).

The payload (an ``.npz`` archive) is described in :mod:`service.features_payload` and the
README; the server checks it against the atlas's feature signature, then only aggregates, fuses
and searches: no image is decoded and no CNN runs.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, UploadFile, status

from service.api.auth import RobotAccess, acting_robot
from service.api.deps import ServiceDep
from service.api.forms import (
    FrameIntrinsics,
    FrameRobot,
    PoseField,
    QueryFilterForm,
    QueryIntrinsics,
    RobotId,
    SequenceLength,
    SubmapName,
    Timestamp,
    frame_fields,
    intrinsics_from_form,
)
from service.api.routes.frames import frame_out
from service.api.schemas import ErrorOut, FrameOut, QueryOut
from service.api.uploads import read_image_upload
from service.app import reads
from service.app.catalog import AtlasService
from service.features_payload import decode_features
from service.ml.features import FrameFeatures

router = APIRouter(tags=["features"])
ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorOut, "description": "Unknown atlas or submap"},
    409: {"model": ErrorOut, "description": "The atlas was built with other features"},
    413: {"model": ErrorOut, "description": "Payload over the byte limit"},
    422: {"model": ErrorOut, "description": "Malformed payload or a bad field"},
}
PAYLOAD_DOC = (
    ".npz archive: signature, image_size, keypoints, descriptors, scores, global_vector "
    "(see the README, 'Precomputed features')."
)


def read_features(service: AtlasService, atlas: str, upload: UploadFile) -> FrameFeatures:
    """The checked features of a payload posted for ``atlas`` (a 4xx before any write)."""
    data = read_image_upload(upload, service.settings.max_upload_bytes)
    signature = service.reads.feature_signature(atlas)
    return decode_features(data, signature, max_image_pixels=service.settings.max_image_pixels)


@router.post(
    "/atlases/{atlas}/frames:features",
    response_model=FrameOut,
    status_code=status.HTTP_201_CREATED,
    responses=ERRORS,
    summary="Add a frame described by precomputed features",
)
def add_frame_features(
    atlas: str,
    service: ServiceDep,
    access: RobotAccess,
    features: Annotated[UploadFile, File(description=PAYLOAD_DOC)],
    submap: SubmapName,
    robot_id: FrameRobot = None,
    timestamp: Timestamp = None,
    pose: PoseField = None,
    intrinsics: FrameIntrinsics = None,
) -> FrameOut:
    frame = service.ingest_features(
        atlas_name=atlas,
        fields=frame_fields(access, submap, robot_id, timestamp, pose, intrinsics),
        features=read_features(service, atlas, features),
    )
    return frame_out(reads.FrameRecord(atlas, submap, frame))


@router.post(
    "/atlases/{atlas}/query:features",
    response_model=QueryOut,
    responses=ERRORS,
    summary="Find the frames and submap that precomputed features revisit",
)
def query_features(
    atlas: str,
    service: ServiceDep,
    caller: RobotAccess,
    features: Annotated[UploadFile, File(description=PAYLOAD_DOC)],
    filters: QueryFilterForm,
    k: Annotated[int, Form(ge=1, description="How many candidates to return.")] = 5,
    robot_id: RobotId = None,
    timestamp: Annotated[
        float | None, Form(description="Capture time of the query frame, seconds.")
    ] = None,
    intrinsics: QueryIntrinsics = None,
    sequence_length: SequenceLength = None,
) -> QueryOut:
    robot_id = acting_robot(caller, robot_id)
    query_filter = filters.build(service.settings, robot_id=robot_id, timestamp=timestamp)
    start = time.perf_counter()
    decoded = read_features(service, atlas, features)
    decode_ms = (time.perf_counter() - start) * 1000.0
    result = service.query_features(
        atlas_name=atlas,
        features=decoded,
        k=k,
        robot_id=robot_id or None,
        query_filter=query_filter,
        intrinsics=intrinsics_from_form(intrinsics),
        sequence_length=sequence_length,
        timestamp=timestamp,
    )
    result.timings_ms = {
        "decode_features": round(decode_ms, 3),
        **result.timings_ms,
        "total": round((time.perf_counter() - start) * 1000.0, 3),
    }
    return QueryOut.model_validate(asdict(result))
