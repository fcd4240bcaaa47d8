"""Settings from ``LOOPNET_*`` environment variables (pydantic-settings), built on demand."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.fleet.snapshot_archive import ArchiveLimits
from service.ml.image_limits import ImageLimits

if TYPE_CHECKING:  # the ML modules import torch; the keys and snapshot commands must not
    from service.ml.presets import ModelPreset


class Settings(BaseSettings):
    """Everything configurable; the defaults run a single-machine service with no set-up."""

    model_config = SettingsConfigDict(env_prefix="LOOPNET_", env_file=None, extra="ignore")

    data_dir: Path = Field(
        Path("./loopnet-data"),
        description="The database (SQLite by default), FAISS indexes, model versions and the job "
        "queue; created owner-only (0700), the SQLite files 0600.",
    )
    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL of the database, e.g. postgresql+psycopg://user:pass@host/db;"
        " unset: a SQLite file loopnet.sqlite3 in the data directory.",
    )
    model_preset: str = Field(
        "default",
        description="'default' (DISK at 512 px, 1024 keypoints, MobileNetV2 at 224 px), 'fast' "
        "(XFeat at 320 px, 512 keypoints, MobileNetV2 at 160 px: CPU-only robots and servers) or "
        "'paper' (DISK at 1024 px, 2048 keypoints, ResNet-18). An atlas keeps the features it was "
        "built with: a service running other settings answers 409 for it.",
    )
    backbone: str | None = Field(
        None, description="The global backbone, 'mobilenetv2' or 'resnet18'; unset: the preset's."
    )
    long_side: int | None = Field(
        None,
        ge=32,
        le=4096,
        description="The local extractor's working long side in pixels (frames are resized up or "
        "down to it); unset: the preset's.",
    )
    max_keypoints: int | None = Field(
        None, ge=16, le=16384, description="Keypoints kept per frame (top-n); unset: the preset's."
    )
    alpha: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        description="Fusion weight of the local branch in the uncalibrated blend an atlas serves "
        "before its first calibration; unset: the preset's (0.7, the paper's). A calibration "
        "carries its own (default 0.5, on standardised cosines).",
    )
    loop_closure_threshold: float = Field(
        0.90,
        ge=-1.0,
        le=1.0,
        description="On uncalibrated model versions: the cosine similarity at or above which the "
        "best match may be a loop closure (it must also be verified).",
    )
    matcher: str = Field(
        "mnn",
        description="Local-feature matcher of geometric verification: 'mnn' (mutual nearest "
        "neighbours + ratio test, any extractor), 'lightglue' (LightGlue-DISK, DISK only; seconds "
        "a candidate on a CPU) or 'auto' (LightGlue for DISK, MNN otherwise).",
    )
    verify_top: int = Field(
        5,
        ge=0,
        le=100,
        description="Best retrieval candidates verified per query (matches + RANSAC); 0 turns "
        "verification off.",
    )
    loop_score_min: float = Field(
        2.0,
        ge=0.0,
        description="On calibrated model versions: -log10 of the chance that a query with no "
        "true revisit finds a match this good among the atlas's frames (a match is a loop from "
        "score >= this + log10(frames), and only once verification agrees).",
    )
    loop_probability_min: float = Field(
        0.98,
        gt=0.0,
        le=1.0,
        description="With verification on: the loop_probability (service.ml.decision: inliers, "
        "inlier ratio, margin over the best verified rival place, calibrated score, sequence "
        "margin) from which the best match is a loop closure. 0.98 gave no false loop on the "
        "development sets (benchmarks/RESULTS.md, issue 25); lower it for recall, raise it for "
        "safety.",
    )
    calibration_milestones: str = Field(
        "16,32,64,128,256,512,1024,10000,100000",
        pattern=r"^\s*(\d+\s*(,\s*\d+\s*)*)?$",
        description="Frame counts at which an atlas is calibrated automatically (comma-separated;"
        " empty: never). Doubling from 16 (a calibration beats the uncalibrated blend from a "
        "dozen frames on, and its whitening keeps at most half the frame count in axes, up to "
        "512 at 1024 frames), then every tenfold.",
    )
    retrain_activate_worse: bool = Field(
        False,
        description="Activate a retrained version even when it is worse than the active one on "
        "the frames it did not train on.",
    )
    verify_min_inliers: int | None = Field(
        None,
        ge=1,
        description="RANSAC inliers at or above which a candidate is verified; unset: the "
        "atlas calibration's (fitted above its hard impostors), else the matcher's own default "
        "(service.ml.verification.DEFAULT_MIN_INLIERS).",
    )
    verify_ratio: float = Field(0.9, gt=0.0, le=1.0, description="Lowe's ratio of the MNN matcher.")
    ransac_threshold_px: float = Field(
        3.0,
        gt=0.0,
        description="RANSAC inlier threshold in pixels of the decoded image (Sampson distance).",
    )
    ransac_backend: Literal["batched", "kornia"] = Field(
        "batched",
        description="Fundamental-matrix RANSAC of verification: 'batched' (all candidates "
        "vectorised together in numpy, several times faster) or 'kornia' (kornia's RANSAC, one "
        "candidate at a time; inlier counts agree within a few). Essential matrices use kornia.",
    )
    exclude_recent_frames: int = Field(
        20,
        ge=0,
        description="The asking robot's last N frames never count as a loop closure (per request:"
        " exclude_recent_frames).",
    )
    exclude_recent_seconds: float = Field(
        30.0,
        ge=0.0,
        description="Nor do its frames taken within T seconds of the query's timestamp, or of its"
        " latest frame's (per request: exclude_recent_seconds).",
    )
    sequence_length: int = Field(
        10,
        ge=0,
        le=50,
        description="Default frames of a robot's sequence scored with each query/observe that "
        "names the robot (SeqSLAM-like; 0: off). A request's sequence_length overrides it.",
    )
    sequence_max_gap_seconds: float = Field(
        10.0,
        gt=0.0,
        description="A robot's frames further apart in time than this start a new sequence (so "
        "does a timestamp going backwards).",
    )
    sequence_seed_frames: int = Field(
        0,
        ge=0,
        le=50,
        description="Frames of a robot's sequence, newest first, whose best matches propose "
        "places to score (0: all). An observed frame keeps its own search's matches, so it "
        "proposes without a search; a frame stored without one (POST /frames) costs one index "
        "search per request.",
    )
    sequence_margin_min: float = Field(
        6.0,
        ge=0.0,
        description="A robot's sequence is a loop on its own when its best place's score "
        "exceeds that of the best rival place (more than 3 frames away along a trajectory, or "
        "on another) by this many standard deviations and it aligned at least "
        "consistency_frames frames. 6: the largest margin of a wrong sequence answer on the "
        "first half of the development sets' queries at L = 10 (5.86, Nordland).",
    )
    consistency_frames: int = Field(
        3,
        ge=1,
        le=20,
        description="Consecutive agreeing observations of a robot before a loop closure is "
        "accepted (DBoW2's temporal consistency; 1: no check).",
    )
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
    max_snapshot_bytes: int = Field(
        4 * 1024**3,
        ge=1024,
        description="Larger snapshot uploads (POST /v1/snapshots) get 413, by Content-Length or "
        "while streaming.",
    )
    max_k: int = Field(100, ge=1, le=10_000, description="Largest k a query may ask for.")
    model_poll_seconds: float = Field(
        1.0,
        ge=0.0,
        description="How long an atlas that failed to load waits before it is tried again "
        "(a newly activated version arrives through the change feed, every LOOPNET_SYNC_SECONDS).",
    )
    redis_url: str | None = Field(
        None,
        description="Redis URL of the job queue (fleets: workers on other machines); unset: a "
        "SQLite queue file queue.sqlite3 in the data directory.",
    )
    queue_name: str = Field("loopnet", description="Queue name (Redis key prefix / SQLite table).")
    torch_threads: int | None = Field(
        1,
        ge=1,
        description="torch intra-op threads per inference; cores / threads inferences run at "
        "once. One (the default) lets concurrent requests fill the cores and keeps threads from "
        "spinning at barriers beside a busy core; two only shorten a single client's query on "
        "an idle machine (docs/performance.md).",
    )
    offline: bool = Field(
        False,
        description="Never download missing pretrained weights (air-gapped installs); a missing "
        "file is then an error naming where to put it.",
    )
    job_stale_seconds: float = Field(
        600.0,
        gt=0,
        description="A running job with no progress for this long is failed: its worker died.",
    )
    job_requeue_seconds: float = Field(
        30.0, gt=0, description="A queued job missing from the queue this long is enqueued again."
    )
    job_sweep_seconds: float = Field(
        60.0, gt=0, description="How often each worker looks for lost or orphaned jobs."
    )
    inference_workers: int | None = Field(
        None,
        ge=1,
        le=256,
        description="Images decoded and run through the CNNs at once; unset: cores / torch "
        "threads (times max_batch when batching is on, so that a batch can fill).",
    )
    precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto",
        description="CNN arithmetic: 'auto' runs DISK in bf16 (bf16 weights, InstanceNorm "
        "statistics in float32) and re-embedding's products in bf16 where the CPU computes bf16 "
        "natively (AVX512-BF16 or AMX), fp32 elsewhere; 'fp32' forces float32; 'bf16' forces bf16"
        " (fails at start on a CPU without it).",
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
    sync_seconds: float = Field(
        1.0,
        ge=0.05,
        le=3600,
        description="How often each API process applies the frames added or deleted and the "
        "model versions activated through any process: the bound on cross-process delay.",
    )
    change_retention_seconds: float = Field(
        3600.0,
        ge=60,
        description="How long the frame change log is kept; a process further behind "
        "reconciles its whole index instead.",
    )
    auth: Literal["auto", "required", "off"] = Field(
        "auto",
        description="API keys: 'auto' = required as soon as a key has ever been created, for "
        "good (the embedded service runs open until then, and says so at start); 'required' "
        "always (the container image's default; anything listening beyond loopback should run "
        "it); 'off' never.",
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
    log_format: Literal["json", "text"] = Field(
        "json",
        description="One line per request on stderr (logger loopnet.access): a JSON object with "
        "ts, method, route (template), path, status, duration_ms, atlas, robot, request_id; "
        "'text' writes the same fields as key=value.",
    )
    metrics_public: bool = Field(
        True, description="Serve GET /metrics without a key; false: an operator key is needed."
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
    host: str = Field("127.0.0.1", description="The address `loopnet serve` listens on.")
    port: int = Field(8000, ge=1, le=65535, description="The port `loopnet serve` listens on.")

    @model_validator(mode="after")
    def _workers_fill_batches(self) -> Settings:
        if self.inference_workers is None and self.batch_window_ms > 0 and self.max_batch > 1:
            from service.concurrency import default_workers

            self.inference_workers = min(256, default_workers(self.torch_threads) * self.max_batch)
        return self

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'loopnet.sqlite3').resolve()}"

    @property
    def milestones(self) -> tuple[int, ...]:
        """The calibration milestones, ascending (empty: automatic calibration off)."""
        text = self.calibration_milestones.strip()
        return tuple(sorted({int(v) for v in text.split(",")})) if text else ()

    @property
    def index_dir(self) -> Path:
        return self.data_dir / "indexes"

    @property
    def models_dir(self) -> Path:
        return self.data_dir / "models"

    @property
    def queue_path(self) -> Path:
        return self.data_dir / "queue.sqlite3"

    @property
    def host_names(self) -> tuple[str, ...]:
        """The Host names the API answers to (see ``allowed_hosts``), lower case."""
        names = {"localhost", "127.0.0.1", "::1"}
        if self.host not in ("0.0.0.0", "::", ""):
            names.add(self.host.lower())
        names.update(n.strip().lower() for n in self.allowed_hosts.split(",") if n.strip())
        return tuple(sorted(names))

    @property
    def proxies(self) -> list[str]:
        """The trusted proxies as a list (empty: none)."""
        return [p.strip() for p in self.trusted_proxies.split(",") if p.strip()]

    @property
    def image_limits(self) -> ImageLimits:
        return ImageLimits(max_bytes=self.max_upload_bytes, max_pixels=self.max_image_pixels)

    @property
    def snapshot_limits(self) -> ArchiveLimits:
        return ArchiveLimits(self.snapshot_max_member_bytes, self.snapshot_max_total_bytes)

    def pipeline_options(self) -> tuple[str, float, int, Literal["auto", "on", "off"]]:
        """FeaturePipeline's precision, batch_window_ms, max_batch and parallel_branches."""
        return self.precision, self.batch_window_ms, self.max_batch, self.parallel_branches

    def preset(self) -> ModelPreset:
        from service.ml.presets import resolve_preset

        return resolve_preset(
            self.model_preset,
            backbone=self.backbone,
            long_side=self.long_side,
            max_keypoints=self.max_keypoints,
            alpha=self.alpha,
        )
