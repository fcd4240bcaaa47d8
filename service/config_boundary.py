"""The settings of the service's boundary (inference and admission, limits, keys, logs and
metrics, HTTP), one class per section of docs/configuration.md, as in
:mod:`service.config_sections`."""

from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings

from service.ml.image_limits import ImageLimits


class InferenceSettings(BaseSettings):
    """Inference and admission."""

    torch_threads: int | None = Field(
        1,
        ge=1,
        description="torch intra-op threads per inference; cores / threads inferences run at "
        "once. One (the default) lets concurrent requests fill the cores and keeps threads from "
        "spinning at barriers beside a busy core; two only shorten a single client's query on "
        "an idle machine (docs/performance.md).",
    )
    inference_workers: int | None = Field(
        None,
        ge=1,
        le=256,
        description="Images decoded and run through the CNNs at once; unset: cores / torch "
        "threads (times max_batch when batching is on, so that a batch can fill).",
    )
    inference_queue: int = Field(
        16,
        ge=0,
        le=4096,
        description="Requests that may wait for an inference slot (first come, first served); "
        "one more gets 503 with Retry-After.",
    )
    inference_wait_seconds: float = Field(
        30.0, gt=0, description="Longest wait for an inference slot before answering 503."
    )
    batch_window_ms: float = Field(
        0.0,
        ge=0.0,
        le=1000.0,
        description="Concurrent frames arriving within this window run through the CNNs as one "
        "batch; a request waits at most the window plus its batch's inference; 0: off.",
    )
    max_batch: int = Field(8, ge=1, le=256, description="Most frames in one CNN batch.")
    parallel_branches: Literal["auto", "on", "off"] = Field(
        "auto",
        description="Run a frame's local extractor and global backbone side by side in two "
        "threads while it is the only frame being extracted (same features): 'auto' = when torch"
        " threads x 2 <= cores (e.g. LOOPNET_TORCH_THREADS=1 on 2 cores); 'on' / 'off' force it.",
    )


class LimitSettings(BaseSettings):
    """Limits."""

    max_upload_bytes: int = Field(
        ImageLimits.max_bytes,
        ge=1024,
        description="Larger uploads get 413 (a request body may be 1 MiB larger, for the form "
        "around the file; beyond that, 413 before it is read).",
    )
    max_image_pixels: int = Field(
        ImageLimits.max_pixels,
        ge=1024,
        description="Larger images get 413, checked from the header before decoding.",
    )
    max_k: int = Field(100, ge=1, le=10_000, description="Largest k a query may ask for.")
    max_snapshot_bytes: int = Field(
        4 * 1024**3,
        ge=1024,
        description="Larger snapshot uploads (POST /v1/snapshots) get 413, by Content-Length or "
        "while streaming.",
    )
    snapshot_max_member_bytes: int = Field(
        4 * 1024**3,
        ge=1024,
        description="A snapshot member (uncompressed, by its header) beyond this is refused "
        "(422) before it is read. Members are streamed to a temporary folder (TMPDIR; keep it "
        "on disk, not tmpfs), never held in memory. The default takes the largest member "
        "(features.npz) of any archive within LOOPNET_MAX_SNAPSHOT_BYTES: export writes about "
        "264 KB a frame there at the default preset with 1,024 keypoints, 77 KB at the fast "
        "preset with 512 (benchmarks/snapshot_sizes.py).",
    )
    snapshot_max_total_bytes: int = Field(
        8 * 1024**3,
        ge=1024,
        description="Nor may a snapshot's members, nor the arrays inside features.npz "
        "(inflated: 286 KB and 83 KB a frame), add up to more. The defaults restore any archive"
        " within LOOPNET_MAX_SNAPSHOT_BYTES (about 15,000 default-preset or 46,000 fast-preset "
        "frames); a larger atlas (100,000 frames: about 28 GB at the default preset) needs the "
        "three raised together, and TMPDIR room for about twice the archive.",
    )


class AccessSettings(BaseSettings):
    """Keys, logs and metrics."""

    auth: Literal["auto", "required", "off"] = Field(
        "auto",
        description="API keys: 'auto' = required as soon as a key has ever been created, for "
        "good (the embedded service runs open until then, and says so at start); 'required' "
        "always (the container image's default; anything listening beyond loopback should run "
        "it); 'off' never.",
    )
    auth_failure_limit: int = Field(
        20,
        ge=1,
        description="Failed authentications (401) one client address may make per window; "
        "beyond, 429 with Retry-After (counted per process).",
    )
    auth_failure_window_seconds: float = Field(
        60.0, gt=0, description="The window of auth_failure_limit; beyond it, 429."
    )
    log_format: Literal["json", "text"] = Field(
        "json",
        description="One line per request on stderr (logger loopnet.access): a JSON object with "
        "ts, method, route (template), path, status, duration_ms, atlas, robot, request_id; "
        "'text' writes the same fields as key=value.",
    )
    metrics_public: bool = Field(
        True, description="Serve GET /metrics without a key; false: an operator key is needed."
    )


class BoundarySettings(BaseSettings):
    """HTTP boundary."""

    # ----- the HTTP boundary (issue 24): hosts, proxies, time-outs, decode memory -----------
    allowed_hosts: str = Field(
        "",
        description="Host names (comma-separated) the API answers to besides the loopback names "
        "(localhost, 127.0.0.1, ::1) and LOOPNET_HOST when it names one address: put the public "
        "name clients use here (e.g. loopnet.example.org; '*.example.org' covers subdomains). A "
        "request naming another Host gets 400, so a DNS-rebinding web page cannot reach the "
        "service through a visitor's browser. '*' answers any Host (only behind a proxy that "
        "checks it). GET /v1/health, /v1/ready and /metrics answer any Host: probes and "
        "Prometheus call them by address.",
    )
    trusted_proxies: str = Field(
        "",
        description="Reverse proxies (comma-separated addresses or networks, e.g. "
        "10.0.0.5,172.18.0.0/16; '*' any) whose X-Forwarded-For and X-Forwarded-Proto are "
        "believed; empty: none, so the client address of the logs and of the failed-"
        "authentication limit is always the connection's own.",
    )
    header_timeout_seconds: float = Field(
        10.0,
        gt=0,
        description="A connection must send a request's complete headers within this many "
        "seconds of its first byte (of connecting, for the first request); else it is closed.",
    )
    body_timeout_seconds: float = Field(
        30.0,
        gt=0,
        description="Longest wait for the next part of a request body; then 408 and the "
        "connection is closed.",
    )
    keep_alive_seconds: int = Field(
        5, ge=1, description="An idle keep-alive connection is closed after this many seconds."
    )
    max_connections: int = Field(
        1024,
        ge=1,
        description="Connections and requests `loopnet serve` holds at once (uvicorn's "
        "limit_concurrency); beyond, 503.",
    )
    decode_memory_bytes: int = Field(
        1024**3,
        ge=1024**2,
        description="Memory the image decodes of one process may hold at once (each its "
        "estimated peak: the decoded image before it is shrunk to the networks' working size; "
        "about 4 bytes a pixel for PNG and JPEG, 16 for WebP: 210 MB and 664 MB for 6300 x "
        "6300). An image that alone needs more gets 413; one that does not fit beside the "
        "decodes running waits up to LOOPNET_INFERENCE_WAIT_SECONDS, then 503. Keep it above "
        "16 bytes x LOOPNET_MAX_IMAGE_PIXELS (640 MB at the default) to accept every image the "
        "pixel limit allows.",
    )
