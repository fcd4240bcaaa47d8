"""The settings of what the service does (storage, model, decision, sequences, jobs), one
class per section of docs/configuration.md; :class:`~service.config.Settings` inherits them
all, and the page's sections are these classes (their docstrings)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings

from service.ml.decision import DEFAULT_RIVAL_GAP
from service.ml.sequences.distinctiveness import CONFIRM_Z, TRACKING_DROPOUT
from service.ml.viewpoint import DEFAULT_SCALE_TOLERANCE


class StorageSettings(BaseSettings):
    """Storage and processes."""

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
    host: str = Field("127.0.0.1", description="The address `loopnet serve` listens on.")
    port: int = Field(8000, ge=1, le=65535, description="The port `loopnet serve` listens on.")
    redis_url: str | None = Field(
        None,
        description="Redis URL of the job queue (fleets: workers on other machines); unset: a "
        "SQLite queue file queue.sqlite3 in the data directory.",
    )
    queue_name: str = Field("loopnet", description="Queue name (Redis key prefix / SQLite table).")
    sync_seconds: float = Field(
        1.0,
        ge=0.05,
        le=3600,
        description="How often each API process applies the frames added or deleted and the "
        "model versions activated through any process: the bound on cross-process delay.",
    )
    vector_store: Literal["auto", "faiss", "pgvector"] = Field(
        "auto",
        description="Where the atlases' embeddings are searched: 'faiss' (an in-process index "
        "per atlas, kept in step by the change feed: one machine), 'pgvector' (a table per "
        "atlas and model version in the PostgreSQL database itself, written in each frame's "
        "transaction and searched by every replica; needs the vector extension), 'auto' "
        "(pgvector when the database is PostgreSQL with the extension available, else faiss).",
    )
    change_retention_seconds: float = Field(
        3600.0,
        ge=60,
        description="How long the frame change log is kept; a process further behind "
        "reconciles its whole index instead.",
    )
    model_poll_seconds: float = Field(
        1.0,
        ge=0.0,
        description="How long an atlas that failed to load waits before it is tried again "
        "(a newly activated version arrives through the change feed, every LOOPNET_SYNC_SECONDS).",
    )


class ModelSettings(BaseSettings):
    """Model."""

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
    precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto",
        description="CNN arithmetic: 'auto' runs DISK in bf16 (bf16 weights, InstanceNorm "
        "statistics in float32) and re-embedding's products in bf16 where the CPU computes bf16 "
        "natively (AVX512-BF16 or AMX), fp32 elsewhere; 'fp32' forces float32; 'bf16' forces bf16"
        " (fails at start on a CPU without it).",
    )
    offline: bool = Field(
        False,
        description="Never download missing pretrained weights (air-gapped installs); a missing "
        "file is then an error naming where to put it.",
    )


class DecisionSettings(BaseSettings):
    """Decision and verification."""

    loop_closure_threshold: float = Field(
        0.90,
        ge=-1.0,
        le=1.0,
        description="On uncalibrated model versions: the cosine similarity at or above which the "
        "best match may be a loop closure (it must also be verified).",
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
    rival_gap_frames: int = Field(
        DEFAULT_RIVAL_GAP,
        ge=0,
        description="Frames of one robot at most this many apart along its route are one "
        "stretch of it: the decision's rival part (the best verified candidate of another "
        "place) looks beyond them; another robot's frame is another place only in another "
        "submap. Larger values close more loops on dense keyframes (gardenspoint_cohog200: "
        "R@100%P 0.49 at 2, 0.61 at 5) but let a match a few frames off pass when its true "
        "neighbours verify as well (benchmarks/RESULTS.md, issue 25, stop 36).",
    )
    matcher: str = Field(
        "mnn",
        description="Local-feature matcher of geometric verification: 'mnn' (mutual nearest "
        "neighbours + ratio test, any extractor), 'lightglue' (LightGlue-DISK, DISK only; "
        "0.3-1 s a candidate on a 2-core CPU; on cohog200 it verifies more right "
        "answers than MNN but also near misses 3-5 frames off, and closed 2 false loops in 140 "
        "at the defaults: benchmarks/RESULTS.md, issue 25, stop 47) or 'auto' (LightGlue for "
        "DISK, MNN otherwise).",
    )
    verify_top: int = Field(
        5,
        ge=0,
        le=100,
        description="Best retrieval candidates verified per query (matches + RANSAC); 0 turns "
        "verification off.",
    )
    verify_min_inliers: int | None = Field(
        None,
        ge=1,
        description="RANSAC inliers at or above which a candidate is verified; unset: the "
        "atlas calibration's (fitted above its hard impostors), else the matcher's own default "
        "(service.ml.verification.DEFAULT_MIN_INLIERS).",
    )
    verify_ratio: float = Field(0.9, gt=0.0, le=1.0, description="Lowe's ratio of the MNN matcher.")
    verify_scale_tolerance: float = Field(
        DEFAULT_SCALE_TOLERANCE,
        ge=0.0,
        description="How verified candidates are ordered: by their inliers, each discounted by e "
        "per this much of |ln zoom| between the query's inliers and the candidate's "
        "(service.ml.verification.support): frames a few metres apart along one view share many "
        "inliers, the zoom says which one was taken where the query was. 0: inliers alone.",
    )
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
    exclude_stay: bool = Field(
        True,
        description="Nor do the frames of its current stay: its newest frames that still show the "
        "query's place (calibrated score at least loop_score_min), back to where two frames in a "
        "row show another place (score below 1) or eight do not show it. A robot that stands "
        "still does not close a loop with itself; one that left and came back does. Needs a "
        "calibrated model version (service.app.stay).",
    )


class SequenceSettings(BaseSettings):
    """Sequences and consistency."""

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
    trajectory_contrast_frames: int = Field(
        10,
        ge=0,
        le=100,
        description="A robot's sequence is scored on trajectory-contrasted vectors: each frame's "
        "vector less the mean of the N frames its robot took just before it in the same "
        "sequence (the query's too), so two traversals under different light or season compare "
        "on what they show (service.ml.sequences.contrast; 0: plain vectors).",
    )
    sequence_margin_min: float = Field(
        4.5,
        ge=0.0,
        description="A robot's sequence is a loop on its own when its best place's score "
        "exceeds that of the best rival place (more than 3 frames away along a trajectory, or "
        "on another) by this many standard deviations and it aligned at least "
        "consistency_frames frames; for a place on another robot's or another sequence's "
        "trajectory (the robot's own current sequence: sequence_margin_min_own_run). The wrong "
        "answers with the largest margins are places 2-3 frames off (a good track slipping): "
        "3.85 on Nordland at L = 10, 4.03 in its replay with adaptation on an AVX2 machine, "
        "while places further off stay below 2.7. 4.5 keeps half a standard deviation above "
        "every wrong answer seen on either machine; 4 cost one false loop there "
        "(benchmarks/RESULTS.md, issue 25, stops 40-42).",
    )
    sequence_margin_min_own_run: float = Field(
        6.0,
        ge=0.0,
        description="The margin a robot's sequence needs when its best place lies on the "
        "robot's own current sequence (a revisit within one run): the same season, light and "
        "camera on both sides make look-alike stretches of one run closer than across runs. "
        "6: above the largest margin of a wrong own-run answer in the first half of the "
        "two-traversal Nordland replay (5.99, eval-online).",
    )
    sequence_margin_min_tracking: float | None = Field(
        2.5,
        ge=0.0,
        description="Loop tracking: the margin a robot's sequence needs when its place continues "
        f"the robot's newest loop within its last {TRACKING_DROPOUT} frames (the same "
        "trajectory, a frame along it per frame driven since); the first loop of a revisit still "
        "needs sequence_margin_min (or the own-run margin). 2.5: above every false loop a wider "
        "window (-1..3 frames) let tracking close on the first half of Nordland's queries "
        "(margins 2.16-2.33); continuing by one frame, "
        "none down to 1.5 added one (benchmarks/decision_headroom.py). Unset: no tracking.",
    )
    sequence_confirm_z: float = Field(
        CONFIRM_Z,
        ge=0.0,
        description="A loop a robot's passed sequence carries while the newest frame's own "
        "evidence (its aligned_z) is below this is not answered at once: the answer is a "
        "candidate with pending_loop_frame_id, and a later observation of the robot confirms it "
        "(its answer's confirmed) when its own loop is answered at once and the same place, "
        "with every frame between pending on that place too. A robot's first frames off the "
        "mapped route look like that; the price is a frame or more of latency on weak loops "
        "(benchmarks/RESULTS.md, issue 25, stops 46-47). 0: every passed sequence is answered "
        "at once.",
    )
    consistency_frames: int = Field(
        3,
        ge=1,
        le=20,
        description="Consecutive agreeing observations of a robot before a loop closure is "
        "accepted (DBoW2's temporal consistency; 1: no check).",
    )


class JobSettings(BaseSettings):
    """Jobs."""

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
    adapt_after_pairs: int = Field(
        500,
        ge=0,
        description="Queue an adaptation job (kind adapt: learned whitening from revisit pairs) "
        "once an atlas has collected this many revisit pairs (verified closures and sequence "
        "loops observe kept, and labelled pairs) since its last one; its gate activates the "
        "new version only when it is not worse on held-out pairs and stretches. 0: never "
        "(operators submit adapt jobs themselves). At 500, Nordland's winter drive over the "
        "summer map closes 0.70 -> 0.78 of its frames as loops, none false, and a drive with "
        "ten unmapped detours none false either (benchmarks/RESULTS.md, issue 25, stop 47).",
    )
    pairs_from_sequence_loops: bool = Field(
        True,
        description="Keep an observation's loop that its robot's sequence decided without "
        "geometric verification as a revisit pair too (source 'sequence'); off: only "
        "geometrically verified closures (source 'observe') and operators' pairs. On Nordland's "
        "winter drive the sequence closes 27x more loops than geometry verifies, all right "
        "(benchmarks/RESULTS.md, issue 26).",
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
