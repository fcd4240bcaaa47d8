"""The replayed trajectory's features, from the evaluation's feature cache: every frame's
vectors (D, R) for the retrieval rows, and its keypoints and descriptors for the served row
(verification matches them, a calibration fits on them, a calibrated model embeds from them).

The cache files are ``loopnet eval``'s own (:mod:`service.evaluation.service_pass`), keyed by
the dataset's folder, so a two-traversal trajectory reads what ``loopnet eval`` wrote for that
dataset; frames missing from them are extracted once and added.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from service.evaluation.datasets import Dataset, ReferenceFrame
from service.evaluation.feature_cache import (
    CACHE_ARRAYS,
    CachedFeatures,
    LocalFeatureCache,
    cache_path,
    extract_local_features,
    file_stamp,
)
from service.evaluation.loop_ground_truth import Trajectory
from service.evaluation.served_pass import as_stored
from service.ml.features import LocalFeatures
from service.ml.images import decode_image
from service.ml.pipeline import FeaturePipeline


def trajectory_cache(
    trajectory: Trajectory, pipeline: FeaturePipeline, cache_dir: Path | None
) -> Path | None:
    """The vector cache file of the trajectory's dataset (None without a cache folder)."""
    if cache_dir is None:
        return None
    as_dataset = Dataset(
        name=trajectory.name.removesuffix("-single-trajectory"),
        layout="trajectory",
        root=trajectory.root or trajectory.images[0].parent,
        references=[ReferenceFrame(p, str(i), i) for i, p in enumerate(trajectory.images)],
        queries=[],
        ground_truth=trajectory.ground_truth,
    )
    return cache_path(cache_dir, as_dataset, pipeline)


def trajectory_vectors(
    trajectory: Trajectory, pipeline: FeaturePipeline, cache_dir: Path | None
) -> CachedFeatures:
    """Every frame's stored vectors, from the evaluation's feature cache when it holds them;
    frames extracted here also leave their keypoints in the cache's local file."""
    path = trajectory_cache(trajectory, pipeline, cache_dir)
    cached = CachedFeatures.load(path) if path is not None else None
    if cached is not None:
        rows = cached.rows()
        order = [rows.get(image.resolve()) for image in trajectory.images]
        if all(row is not None for row in order):
            take = np.array(order, np.int64)
            return CachedFeatures(**{name: getattr(cached, name)[take] for name in CACHE_ARRAYS})
    local, global_, keypoints, sizes, stages = [], [], [], [], []
    stored: dict[Path, LocalFeatures] = {}
    for image in tqdm(trajectory.images, desc=f"features: {trajectory.name}", unit="img"):
        start = time.perf_counter()
        rgb = decode_image(image.read_bytes())
        decode_ms = (time.perf_counter() - start) * 1000.0
        features = pipeline.extract(rgb)
        local.append(features.local_vector)
        global_.append(features.global_vector)
        keypoints.append(features.local.count)
        sizes.append(features.image_size)
        stages.append(
            [
                decode_ms,
                features.timings_ms["local_features"],
                features.timings_ms["global_features"],
            ]
        )
        stored[image.resolve()] = as_stored(features.local)
    fresh = CachedFeatures(
        paths=np.array([str(p.resolve()) for p in trajectory.images]),
        stamps=np.array([file_stamp(p) for p in trajectory.images], np.int64),
        local=np.stack(local),
        global_=np.stack(global_),
        keypoints=np.array(keypoints, np.int64),
        image_size=np.array(sizes, np.int64),
        stage_ms=np.array(stages, np.float64),
    )
    if path is not None:
        (cached.merged(fresh) if cached is not None else fresh).save(path)
        local_cache = LocalFeatureCache.for_vectors(path)
        local_cache.save({**local_cache.load(), **stored})
    return fresh


def trajectory_local(
    trajectory: Trajectory, pipeline: FeaturePipeline, cache_dir: Path | None
) -> list[LocalFeatures]:
    """Every frame's keypoints and descriptors as the feature store keeps them (float16
    descriptors), from the cache's local file; the frames it lacks are extracted (the local
    extractor only) and added to it."""
    path = trajectory_cache(trajectory, pipeline, cache_dir)
    local_cache = LocalFeatureCache.for_vectors(path) if path is not None else None
    cached = local_cache.load() if local_cache is not None else {}
    missing = [p for p in trajectory.images if p.resolve() not in cached]
    if missing:
        extracted = extract_local_features(pipeline, missing, f"keypoints: {trajectory.name}")
        cached.update(zip((p.resolve() for p in missing), extracted, strict=True))
        if local_cache is not None:
            local_cache.save(cached)
    return [cached[p.resolve()] for p in trajectory.images]
