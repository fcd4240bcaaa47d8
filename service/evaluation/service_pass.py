"""One pass of a dataset through the service's own code path, for one local extractor.

Each image is decoded and run through the CNNs once by :meth:`AtlasService.extract` (or read
back from the feature cache, :mod:`service.evaluation.feature_cache`); references are stored
with :meth:`AtlasService.ingest_features` into a temporary atlas, one submap per protocol
submap; queries are answered by
:meth:`AtlasService.query_features`. The stored vectors D and R of every frame are kept, so the
alpha ablations re-embed them without running a CNN again.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from service.app.catalog import AtlasService
from service.app.ingest import FrameFields
from service.config import Settings
from service.evaluation.datasets import Dataset, all_images
from service.evaluation.feature_cache import (
    EXTRACTION_STAGES,
    CachedFeatures,
    LocalFeatureCache,
    cache_path,
    extract_local_features,
    file_stamp,
)
from service.evaluation.metrics import Ranking
from service.evaluation.served_jobs import run_job_now
from service.evaluation.served_pass import (
    ServedAnswers,
    as_stored,
    at_served_defaults,
    served_answers,
)
from service.ml.calibration import CalibrationInputs
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import ModelPreset
from service.runtime import Runtime
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.feature_store import load_calibration_inputs

ATLAS = "evaluation"
ROBOT = "reference"


@dataclass
class PassResult:
    """What one extractor's pass produced.

    Attributes:
        ranking: the service's answers (``Q x k``, reference indices, cosine similarities).
        reference_vectors, query_vectors: ``(D, R)`` of every frame, for the ablations.
        stored_references: the references' features as the atlas stores them, read back by
            :func:`load_calibration_inputs` (what a calibration job reads).
        query_local: the queries' local features (for calibrated embeddings).
        stage_ms: per-frame milliseconds of each stage (decode, CNNs, ingest, heads, search).
        query_ms: per-query end-to-end milliseconds (decode + CNNs + heads + search).
        keypoints: keypoints found per frame, references then queries.
        cached: whether the CNN outputs came from the feature cache.
    """

    preset: ModelPreset
    ranking: Ranking
    reference_vectors: tuple[np.ndarray, np.ndarray]
    query_vectors: tuple[np.ndarray, np.ndarray]
    stage_ms: dict[str, list[float]]
    query_ms: list[float]
    keypoints: np.ndarray
    image_sizes: list[tuple[int, int]]
    cached: bool
    threshold: float
    signature: dict[str, object] = field(default_factory=dict)
    stored_references: CalibrationInputs | None = None
    query_local: list[LocalFeatures] = field(default_factory=list)
    calibrated: CalibratedAnswers | None = None
    served: ServedAnswers | None = None
    served_sequence: ServedAnswers | None = None
    in_atlas: list[Any] = field(default_factory=list)


# work on the pass's atlas once its queries are served: (service, the queries' features, frame
# id -> reference index, the served answers) -> what PassResult.in_atlas keeps
InAtlas = Callable[
    [AtlasService, Sequence[FrameFeatures], dict[int, int], ServedAnswers], list[Any]
]


@dataclass
class CalibratedAnswers:
    """The service's answers once the atlas is calibrated by the calibration job's own code:
    ranking by calibrated score, the answers' cosines, and heads + search milliseconds."""

    ranking: Ranking
    cosines: np.ndarray
    query_ms: np.ndarray
    job_metrics: dict[str, object]


# ----- the pass ---------------------------------------------------------------------------


def submap_name(index: int) -> str:
    return f"submap-{index:05d}"


def _frames(
    service: AtlasService,
    paths: Sequence[Path],
    cached: CachedFeatures | None,
    rows: dict[Path, int],
    local: dict[Path, LocalFeatures],
    desc: str,
) -> Iterator[tuple[FrameFeatures, float, bool]]:
    """Each image's features and decode time, from the cache where it has the file (its
    keypoints and descriptors from ``local``)."""
    dim = service.pipeline.local.descriptor_dim
    for path in tqdm(paths, desc=desc, unit="img", leave=False):
        row = rows.get(path.resolve())
        if cached is not None and row is not None:
            features, decode_ms = cached.frame(row, dim)
            features.local = local.get(path.resolve(), features.local)
            yield features, decode_ms, True
        else:
            features, decode_ms, _ = service.extract(path.read_bytes())
            yield features, decode_ms, False


def run_service_pass(
    dataset: Dataset,
    submap_of: Sequence[int],
    pipeline: FeaturePipeline,
    *,
    k: int,
    cache_dir: Path | None,
    label: str,
    on_features: Callable[[Path, FrameFeatures], None] | None = None,
    calibration: dict[str, object] | None = None,
    serve: bool = False,
    serve_sequence: int = 0,
    in_atlas: InAtlas | None = None,
) -> PassResult:
    """Ingest the references into a temporary atlas, query every query image, keep the vectors.

    ``on_features`` sees every freshly extracted frame (the verification pass keeps its
    keypoints, which the vector cache does not hold). With ``calibration`` (a calibration job's
    parameters), the atlas is then calibrated by the job and every query asked again. With
    ``serve``, every query is then asked once more as the service serves it (verification and
    the loop decision at the defaults: :mod:`service.evaluation.served_pass`), and with
    ``serve_sequence`` L once more as one robot's observations with sequences of length L,
    with the adaptation the service's defaults queue after their revisit pairs run between
    observations (``LOOPNET_ADAPT_AFTER_PAIRS``; the atlas keeps it off until then).
    ``in_atlas`` runs on the atlas after the served pass, before the sequences' observations
    (it must leave the atlas as it found it).
    """
    path = cache_path(cache_dir, dataset, pipeline) if cache_dir else None
    cached = CachedFeatures.load(path) if path is not None else None
    rows = cached.rows() if cached is not None else {}
    images = list(all_images(dataset))
    from_cache: list[bool] = []
    local_cache = LocalFeatureCache.for_vectors(path) if path is not None else None
    cached_local = local_cache.load() if local_cache is not None else {}
    missing = [p for p in images if p.resolve() in rows and p.resolve() not in cached_local]
    if missing:  # vectors cached by an older run: extract only the keypoints
        extracted = extract_local_features(pipeline, missing, f"{label} keypoints")
        cached_local.update(zip((p.resolve() for p in missing), extracted, strict=True))
    stored_references: CalibrationInputs | None = None
    n_refs = len(dataset.references)
    local_vectors, global_vectors, keypoints, sizes, extraction_ms = [], [], [], [], []
    stage_ms: dict[str, list[float]] = {
        name: [] for name in (*EXTRACTION_STAGES, "ingest", "heads", "search")
    }
    query_ms: list[float] = []
    query_local: list[LocalFeatures] = []
    indices, scores = [], []
    query_features: list[FrameFeatures] = []

    with tempfile.TemporaryDirectory(prefix="loopnet-eval-") as data_dir:
        # Retrieval only: geometric verification has its own pass (verification_pass.py).
        settings = Settings(
            data_dir=Path(data_dir),
            max_k=max(k, 1),
            verify_top=0,
            calibration_milestones="",
            adapt_after_pairs=0,  # the protocols adapt explicitly; the observations as served
            torch_threads=torch.get_num_threads(),  # the harness's own (--threads), kept
        )
        runtime = Runtime(settings, pipeline)
        runtime.start(background=False)
        service = runtime.service
        service.create_atlas(ATLAS, description=f"evaluation of {dataset.name}")
        for submap in sorted(set(submap_of)):
            service.create_submap(ATLAS, submap_name(submap))
        frame_to_reference: dict[int, int] = {}
        frames = _frames(service, images, cached, rows, cached_local, f"{label}: {dataset.name}")
        for i, (features, decode_ms, hit) in enumerate(frames):
            from_cache.append(hit)
            if on_features is not None and not hit:
                on_features(images[i], features)
            if not hit:
                cached_local[images[i].resolve()] = as_stored(features.local)
            if i == n_refs:
                stored_references = _read_back(service)
            local_vectors.append(features.local_vector)
            global_vectors.append(features.global_vector)
            keypoints.append(
                int(cached.keypoints[rows[images[i].resolve()]])
                if hit and cached is not None
                else features.local.count
            )
            sizes.append(features.image_size)
            stages = [decode_ms, *(features.timings_ms[s] for s in EXTRACTION_STAGES[1:])]
            extraction_ms.append(stages)
            for name, ms in zip(EXTRACTION_STAGES, stages, strict=True):
                stage_ms[name].append(ms)
            if i < n_refs:
                start = time.perf_counter()
                frame = service.ingest_features(
                    atlas_name=ATLAS,
                    fields=FrameFields(submap_name(submap_of[i]), ROBOT),
                    features=features,
                )
                stage_ms["ingest"].append((time.perf_counter() - start) * 1000.0)
                frame_to_reference[frame.id] = i
                continue
            query_local.append(as_stored(features.local))
            query_features.append(features)
            answer = service.query_features(atlas_name=ATLAS, features=features, k=k)
            found = [frame_to_reference[c.frame_id] for c in answer.candidates]
            indices.append(found + [-1] * (k - len(found)))
            scores.append([c.similarity for c in answer.candidates] + [-np.inf] * (k - len(found)))
            stage_ms["heads"].append(answer.timings_ms["heads"])
            stage_ms["search"].append(answer.timings_ms["search"])
            query_ms.append(sum(stages) + answer.timings_ms["heads"] + answer.timings_ms["search"])
        if stored_references is None:  # a dataset without queries
            stored_references = _read_back(service)
        calibrated = (
            _calibrated_answers(service, query_features, frame_to_reference, k, calibration)
            if calibration is not None and query_features
            else None
        )
        served = (
            served_answers(
                service, query_features, frame_to_reference, k, ATLAS, pipeline.preset.local.name
            )
            if serve and query_features
            else None
        )
        kept = (
            in_atlas(service, query_features, frame_to_reference, served)
            if in_atlas is not None and served is not None
            else []
        )
        served_sequence = (  # last: the observations join the atlas
            served_answers(
                service,
                query_features,
                frame_to_reference,
                k,
                ATLAS,
                pipeline.preset.local.name,
                sequence_length=serve_sequence,
                adapt_after_pairs=Settings(data_dir=Path(data_dir)).adapt_after_pairs,
            )
            if serve and serve_sequence and query_features
            else None
        )
        threshold = settings.loop_closure_threshold
        runtime.stop()

    all_cached = bool(from_cache) and all(from_cache)
    if path is not None and not all_cached:
        fresh = CachedFeatures(
            paths=np.array([str(p.resolve()) for p in images]),
            stamps=np.array([file_stamp(p) for p in images], np.int64),
            local=np.stack(local_vectors),
            global_=np.stack(global_vectors),
            keypoints=np.array(keypoints, np.int64),
            image_size=np.array(sizes, np.int64),
            stage_ms=np.array(extraction_ms, np.float64),
        )
        (cached.merged(fresh) if cached is not None else fresh).save(path)
    if local_cache is not None and (missing or not all_cached):
        local_cache.save(cached_local)
    local_all, global_all = np.stack(local_vectors), np.stack(global_vectors)
    return PassResult(
        preset=pipeline.preset,
        ranking=Ranking(np.array(indices, np.int64), np.array(scores, np.float64)),
        reference_vectors=(local_all[:n_refs], global_all[:n_refs]),
        query_vectors=(local_all[n_refs:], global_all[n_refs:]),
        stage_ms=stage_ms,
        query_ms=query_ms,
        keypoints=np.array(keypoints, np.int64),
        image_sizes=sizes,
        cached=all_cached,
        threshold=threshold,
        signature=pipeline.signature.to_json(),
        stored_references=stored_references,
        query_local=query_local,
        calibrated=calibrated,
        served=served,
        served_sequence=served_sequence,
        in_atlas=kept,
    )


def _calibrated_answers(
    service: AtlasService,
    queries: Sequence[FrameFeatures],
    frame_to_reference: dict[int, int],
    k: int,
    params: dict[str, object],
) -> CalibratedAnswers:
    """Calibrate the atlas as the service does (a calibration job run by the job runner on the
    stored references, with the served defaults: verification on, so the job fits the atlas's
    minimum inliers as a served atlas's does), then ask every query again through the service
    (the harness's own settings: retrieval only)."""
    with transaction(service.sessions) as session:
        atlas_id = repo.get_atlas(session, name=ATLAS).id
        job_id = jobs.create_job(session, atlas_id=atlas_id, kind="calibrate", params=params).id
    job = run_job_now(service, job_id, at_served_defaults(service.settings))
    if job.status != "succeeded":
        raise RuntimeError(f"the calibration job failed: {job.error}")
    metrics = dict(job.metrics)
    indices, scores, cosines, query_ms = [], [], [], []
    for features in queries:
        # descriptors rounded as the feature cache holds them: a rerun answers the same
        features = replace(features, local=as_stored(features.local))
        answer = service.query_features(atlas_name=ATLAS, features=features, k=k)
        found = [frame_to_reference[c.frame_id] for c in answer.candidates]
        pad = k - len(found)
        indices.append(found + [-1] * pad)
        scores.append([float(c.score or 0.0) for c in answer.candidates] + [-np.inf] * pad)
        cosines.append(answer.candidates[0].similarity if answer.candidates else -1.0)
        query_ms.append(answer.timings_ms["heads"] + answer.timings_ms["search"])
    return CalibratedAnswers(
        Ranking(np.array(indices, np.int64), np.array(scores, np.float64)),
        np.array(cosines, np.float64),
        np.array(query_ms, np.float64),
        metrics,
    )


def _read_back(service: AtlasService) -> CalibrationInputs:
    """The references as a calibration job reads them: from the atlas's feature store."""
    with service.sessions() as session:
        atlas = repo.get_atlas(session, name=ATLAS)
        return load_calibration_inputs(session, atlas.id)
