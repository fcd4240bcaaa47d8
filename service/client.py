"""``LoopNetClient``: a typed Python client of the LoopNet HTTP API, for robots and scripts.

Answers come back as the API's own pydantic models (``service.api.schemas``). The key comes
from ``api_key`` or ``LOOPNET_API_KEY``; a 503 (inference saturated, service starting) or 429 is
retried after the server's ``Retry-After``, up to ``retries`` times; any other error raises
:class:`LoopNetError` with the status and the API's ``detail``.

    with LoopNetClient("http://127.0.0.1:8000") as loopnet:
        answer = loopnet.observe("campus", image_bytes, submap="s3", robot_id="husky-1")
        if answer.loop_closure:
            ...
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import httpx
from pydantic import BaseModel, TypeAdapter

from service.api.schemas import (
    AtlasOut,
    FrameOut,
    LoopClosureOut,
    ModelVersionOut,
    ObserveOut,
    QueryOut,
    ReadyOut,
    SubmapOut,
)
from service.api.schemas_admin import ApiKeyOut, JobOut, NewApiKeyOut, PairOut
from service.api.schemas_browse import (
    CallerOut,
    ClosureMatchesOut,
    LoopClosureDetailOut,
    RobotOut,
)

DEFAULT_URL = "http://127.0.0.1:8000"
RETRY_STATUSES = (429, 503)
MAX_RETRY_WAIT_S = 60.0
Model = TypeVar("Model", bound=BaseModel)
Image = bytes | Path


class LoopNetError(Exception):
    """An error answer of the API: ``status`` and the API's ``detail`` (and ``error`` type)."""

    def __init__(self, status: int, detail: str, error: str | None = None) -> None:
        super().__init__(f"error {status}: {detail}")
        self.status, self.detail, self.error = status, detail, error


class LoopNetClient:
    """One connection pool to one LoopNet service; use it as a context manager or ``close()``."""

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        api_key: str | None = None,
        timeout: float = 300.0,
        retries: int = 5,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        key = api_key if api_key is not None else os.environ.get("LOOPNET_API_KEY")
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        self.retries = retries
        self._http = httpx.Client(
            base_url=url.rstrip("/"), timeout=timeout, headers=headers, transport=transport
        )

    def __enter__(self) -> LoopNetClient:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    # ----- transport ---------------------------------------------------------------------

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send a request (``path`` under ``/v1`` unless absolute), retrying 429/503."""
        url = path if path.startswith("/v1") or path == "/metrics" else "/v1" + path
        for attempt in range(self.retries + 1):
            response = self._http.request(method, url, **kwargs)
            if response.status_code not in RETRY_STATUSES or attempt == self.retries:
                break
            time.sleep(retry_after(response, attempt))
        if response.status_code >= 400:
            raise _error(response)
        return response

    def _get(self, model: type[Model], path: str, **params: Any) -> Model:
        return model.model_validate(self.request("GET", path, params=_clean(params)).json())

    def _list(self, model: type[Model], path: str, **params: Any) -> list[Model]:
        data = self.request("GET", path, params=_clean(params)).json()
        return TypeAdapter(list[model]).validate_python(data)  # type: ignore[valid-type]

    def _post(self, model: type[Model], path: str, **kwargs: Any) -> Model:
        return model.model_validate(self.request("POST", path, **kwargs).json())

    # ----- service -----------------------------------------------------------------------

    def ready(self) -> ReadyOut:
        return self._get(ReadyOut, "/ready")

    def whoami(self) -> CallerOut:
        return self._get(CallerOut, "/whoami")

    def wait_ready(self, timeout: float = 120.0) -> ReadyOut:
        """Poll ``/v1/ready`` until the service has loaded its models (or raise TimeoutError)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self.ready()
            except (LoopNetError, httpx.TransportError) as exc:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"LoopNet not ready after {timeout:g} s: {exc}") from exc
                time.sleep(0.3)

    # ----- atlases and submaps -----------------------------------------------------------

    def list_atlases(self) -> list[AtlasOut]:
        return self._list(AtlasOut, "/atlases")

    def get_atlas(self, atlas: str) -> AtlasOut:
        return self._get(AtlasOut, f"/atlases/{atlas}")

    def create_atlas(self, name: str, description: str = "") -> AtlasOut:
        return self._post(AtlasOut, "/atlases", json={"name": name, "description": description})

    def delete_atlas(self, atlas: str) -> None:
        self.request("DELETE", f"/atlases/{atlas}")

    def list_submaps(self, atlas: str) -> list[SubmapOut]:
        return self._list(SubmapOut, f"/atlases/{atlas}/submaps")

    def create_submap(self, atlas: str, name: str) -> SubmapOut:
        return self._post(SubmapOut, f"/atlases/{atlas}/submaps", json={"name": name})

    def delete_submap(self, atlas: str, submap: str) -> None:
        self.request("DELETE", f"/atlases/{atlas}/submaps/{submap}")

    def list_robots(self, atlas: str) -> list[RobotOut]:
        return self._list(RobotOut, f"/atlases/{atlas}/robots")

    # ----- frames ------------------------------------------------------------------------

    def add_frame(
        self,
        atlas: str,
        image: Image,
        *,
        submap: str,
        robot_id: str,
        timestamp: float | None = None,
        pose: Mapping[str, Any] | None = None,
        intrinsics: Mapping[str, float] | None = None,
    ) -> FrameOut:
        """Add a frame; ``pose`` is ``{"rotation": [w,x,y,z], "translation": [x,y,z]}``."""
        form = _form(
            submap=submap, robot_id=robot_id, timestamp=timestamp, pose=pose, intrinsics=intrinsics
        )
        return self._post(FrameOut, f"/atlases/{atlas}/frames", data=form, files=_image(image))

    def get_frame(self, atlas: str, frame_id: int) -> FrameOut:
        return self._get(FrameOut, f"/atlases/{atlas}/frames/{frame_id}")

    def list_frames(
        self,
        atlas: str,
        *,
        robot: str | None = None,
        submap: str | None = None,
        offset: int = 0,
        limit: int = 100,
    ) -> list[FrameOut]:
        return self._list(
            FrameOut,
            f"/atlases/{atlas}/frames",
            robot=robot,
            submap=submap,
            offset=offset,
            limit=limit,
        )

    def thumbnail(self, atlas: str, frame_id: int) -> bytes:
        """The frame's JPEG thumbnail (a placeholder image for frames stored without one)."""
        return self.request("GET", f"/atlases/{atlas}/frames/{frame_id}/thumbnail").content

    def delete_frame(self, atlas: str, frame_id: int) -> None:
        self.request("DELETE", f"/atlases/{atlas}/frames/{frame_id}")

    # ----- queries -----------------------------------------------------------------------

    def query(
        self,
        atlas: str,
        image: Image,
        *,
        k: int = 5,
        robot_id: str | None = None,
        **filters: Any,
    ) -> QueryOut:
        """The frames and submap ``image`` revisits; ``filters`` are the query's form fields
        (robots, submap, since, until, timestamp, intrinsics, exclude_recent_*)."""
        form = _form(k=k, robot_id=robot_id, **filters)
        return self._post(QueryOut, f"/atlases/{atlas}/query", data=form, files=_image(image))

    def observe(
        self,
        atlas: str,
        image: Image,
        *,
        submap: str,
        robot_id: str,
        k: int = 5,
        **fields: Any,
    ) -> ObserveOut:
        """Query with a robot's new keyframe, then add it (one call, one transaction)."""
        form = _form(submap=submap, robot_id=robot_id, k=k, **fields)
        return self._post(ObserveOut, f"/atlases/{atlas}/observe", data=form, files=_image(image))

    def loop_closures(
        self, atlas: str, *, robot: str | None = None, limit: int = 100
    ) -> list[LoopClosureOut]:
        return self._list(
            LoopClosureOut, f"/atlases/{atlas}/loop-closures", robot=robot, limit=limit
        )

    def loop_closure(self, atlas: str, closure_id: int) -> LoopClosureDetailOut:
        return self._get(LoopClosureDetailOut, f"/atlases/{atlas}/loop-closures/{closure_id}")

    def loop_closure_matches(
        self, atlas: str, closure_id: int, *, limit: int = 1000
    ) -> ClosureMatchesOut:
        """The inlier point pairs of a closure an observation found (404 for a query's)."""
        path = f"/atlases/{atlas}/loop-closures/{closure_id}/matches"
        return self._get(ClosureMatchesOut, path, limit=limit)

    def list_pairs(
        self,
        atlas: str,
        *,
        robot: str | None = None,
        submap: str | None = None,
        limit: int = 100,
    ) -> list[PairOut]:
        """Revisit pairs (verified closures and labelled pairs), newest first."""
        return self._list(
            PairOut, f"/atlases/{atlas}/pairs", robot=robot, submap=submap, limit=limit
        )

    def label_pair(self, atlas: str, frame_id: int, other_frame_id: int) -> PairOut:
        """Label two frames of the atlas as one place (a training pair for adapt jobs)."""
        body = {"frame_id": frame_id, "other_frame_id": other_frame_id}
        return self._post(PairOut, f"/atlases/{atlas}/pairs", json=body)

    def delete_pair(self, atlas: str, pair_id: int) -> None:
        self.request("DELETE", f"/atlases/{atlas}/pairs/{pair_id}")

    # ----- jobs and model versions -------------------------------------------------------

    def submit_job(self, atlas: str, **params: Any) -> JobOut:
        """Queue a retraining job; ``params`` are RetrainParams fields (shots, epochs, ...)."""
        body = {"kind": "retrain", "params": params}
        return self._post(JobOut, f"/atlases/{atlas}/jobs", json=body)

    def submit_adaptation(self, atlas: str, **params: Any) -> JobOut:
        """Queue an adaptation job; ``params`` are AdaptParams fields (robots, since, ...)."""
        body = {"kind": "adapt", "adaptation": params}
        return self._post(JobOut, f"/atlases/{atlas}/jobs", json=body)

    def list_jobs(self, atlas: str) -> list[JobOut]:
        return self._list(JobOut, f"/atlases/{atlas}/jobs")

    def get_job(self, atlas: str, job_id: int) -> JobOut:
        return self._get(JobOut, f"/atlases/{atlas}/jobs/{job_id}")

    def cancel_job(self, atlas: str, job_id: int) -> JobOut:
        return self._post(JobOut, f"/atlases/{atlas}/jobs/{job_id}/cancel")

    def wait_job(self, atlas: str, job_id: int, *, timeout: float = 600.0) -> JobOut:
        """Poll a job until it finishes (succeeded, failed or cancelled)."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.get_job(atlas, job_id)
            if job.status in ("succeeded", "failed", "cancelled"):
                return job
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job.status} after {timeout:g} s")
            time.sleep(0.5)

    def list_models(self, atlas: str) -> list[ModelVersionOut]:
        return self._list(ModelVersionOut, f"/atlases/{atlas}/models")

    def activate_model(self, atlas: str, version: int) -> ModelVersionOut:
        return self._post(ModelVersionOut, f"/atlases/{atlas}/models/{version}/activate")

    # ----- keys (admin) ------------------------------------------------------------------

    def create_key(self, name: str, role: str, atlases: list[str] | None = None) -> NewApiKeyOut:
        body = {"name": name, "role": role, "atlases": atlases or []}
        return self._post(NewApiKeyOut, "/keys", json=body)

    def list_keys(self) -> list[ApiKeyOut]:
        return self._list(ApiKeyOut, "/keys")

    def revoke_key(self, key_id: int) -> ApiKeyOut:
        return ApiKeyOut.model_validate(self.request("DELETE", f"/keys/{key_id}").json())


def retry_after(response: httpx.Response, attempt: int) -> float:
    """Seconds to wait before retrying: the server's ``Retry-After`` (seconds), else an
    exponential back-off; never more than :data:`MAX_RETRY_WAIT_S`."""
    try:
        wait = float(response.headers["Retry-After"])
    except (KeyError, ValueError):
        wait = 0.5 * 2**attempt
    return min(max(wait, 0.0), MAX_RETRY_WAIT_S)


def _error(response: httpx.Response) -> LoopNetError:
    try:
        body = response.json()
        return LoopNetError(response.status_code, str(body.get("detail")), body.get("error"))
    except (ValueError, AttributeError):
        return LoopNetError(response.status_code, response.text)


def _clean(params: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in params.items() if v is not None}


def _form(**fields: Any) -> dict[str, str]:
    """Multipart form fields: None left out, mappings as JSON, the rest as text."""
    return {
        name: json.dumps(value) if isinstance(value, Mapping) else str(value)
        for name, value in fields.items()
        if value is not None
    }


def _image(image: Image) -> dict[str, tuple[str, bytes]]:
    if isinstance(image, Path):
        return {"image": (image.name, image.read_bytes())}
    return {"image": ("image", image)}
