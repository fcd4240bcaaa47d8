"""The harness's feature caches: each image's CNN outputs (vectors, stage times) and its local
features (keypoints, float16 descriptors, scores) on disk, keyed by the dataset's folder and
the feature settings, each row checked against its file's size and modification time. The
service pass, ``eval-online`` and the benchmarks share them, so a run extracts each image once.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from service.evaluation.datasets import Dataset
from service.evaluation.served_pass import as_stored
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.images import decode_image
from service.ml.pipeline import FeaturePipeline

EXTRACTION_STAGES = ("decode", "local_features", "global_features")


def cache_path(cache_dir: Path, dataset: Dataset, pipeline: FeaturePipeline) -> Path:
    """The dataset's cache file for these feature settings.

    The key is the dataset's folder and the settings, not its list of files: a run on a subset
    (``--limit``, ``--query-stride``) reads the rows of the files it needs, and each row
    remembers its file's size and modification time, so a changed file is extracted again.
    """
    key = json.dumps(
        {"features": pipeline.signature.to_json(), "root": str(Path(dataset.root).resolve())},
        sort_keys=True,
    )
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    local = pipeline.preset.local
    return cache_dir / f"{dataset.name}-{local.name}{local.long_side}-{digest}.npz"


def file_stamp(path: Path) -> tuple[int, int]:
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


@dataclass
class CachedFeatures:
    """CNN outputs of image files, one row per file (its path and size/mtime stamp)."""

    paths: np.ndarray  # N resolved paths (unicode)
    stamps: np.ndarray  # N x 2: size, mtime_ns
    local: np.ndarray
    global_: np.ndarray
    keypoints: np.ndarray
    image_size: np.ndarray
    stage_ms: np.ndarray  # N x len(EXTRACTION_STAGES)

    def rows(self) -> dict[Path, int]:
        """Row of every file whose stamp still matches the file on disk."""
        found = {}
        for i, (name, stamp) in enumerate(zip(self.paths, self.stamps, strict=True)):
            path = Path(str(name))
            if path.is_file() and file_stamp(path) == tuple(int(v) for v in stamp):
                found[path] = i
        return found

    def frame(self, i: int, descriptor_dim: int) -> tuple[FrameFeatures, float]:
        """The frame's vectors as the pipeline gave them; keypoints themselves are not cached."""
        decode_ms, local_ms, global_ms = (float(v) for v in self.stage_ms[i])
        features = FrameFeatures(
            local=LocalFeatures.empty(descriptor_dim),
            local_vector=self.local[i],
            global_vector=self.global_[i],
            image_size=(int(self.image_size[i, 0]), int(self.image_size[i, 1])),
            timings_ms={"local_features": local_ms, "global_features": global_ms},
        )
        return features, decode_ms

    def merged(self, newer: CachedFeatures) -> CachedFeatures:
        """This cache's rows for other files plus every row of ``newer``."""
        replaced = set(newer.paths.tolist())
        keep = np.array([p not in replaced for p in self.paths.tolist()], dtype=bool)
        return CachedFeatures(
            **{
                name: np.concatenate([getattr(self, name)[keep], getattr(newer, name)])
                for name in CACHE_ARRAYS
            }
        )

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, **{name: getattr(self, name) for name in CACHE_ARRAYS})
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> CachedFeatures | None:
        """The cache at ``path``; None when it is missing or of an older format."""
        if not path.is_file():
            return None
        with np.load(path) as data:
            if set(data.files) != set(CACHE_ARRAYS):
                return None
            return cls(**{name: data[name] for name in CACHE_ARRAYS})


CACHE_ARRAYS = ("paths", "stamps", "local", "global_", "keypoints", "image_size", "stage_ms")


class LocalFeatureCache:
    """Each file's keypoints, descriptors (float16, as the feature store keeps them) and
    scores, by resolved path, beside the vector cache: calibration needs the descriptors
    themselves."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @staticmethod
    def for_vectors(vector_cache: Path) -> LocalFeatureCache:
        return LocalFeatureCache(vector_cache.with_name(vector_cache.stem + "-local.npz"))

    def load(self) -> dict[Path, LocalFeatures]:
        """The cached files' features; empty when the cache is missing or of an older format."""
        if not self.path.is_file():
            return {}
        with np.load(self.path) as data:
            if "paths" not in data.files:
                return {}
            paths, offsets = data["paths"], data["offsets"]
            keypoints, descriptors, scores = data["keypoints"], data["descriptors"], data["scores"]
        return {
            Path(str(name)): LocalFeatures(
                keypoints[a:b], descriptors[a:b].astype(np.float32), scores[a:b]
            )
            for name, a, b in zip(paths, offsets[:-1], offsets[1:], strict=True)
        }

    def save(self, frames: dict[Path, LocalFeatures]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        values = list(frames.values())
        offsets = np.cumsum([0, *(f.count for f in values)])
        tmp = self.path.with_name(self.path.name + ".tmp.npz")
        np.savez(
            tmp,
            paths=np.array([str(p) for p in frames], dtype=np.str_),
            offsets=offsets,
            keypoints=np.concatenate([f.keypoints for f in values]).astype(np.float32),
            descriptors=np.concatenate([f.descriptors for f in values]).astype(np.float16),
            scores=np.concatenate([f.scores for f in values]).astype(np.float32),
        )
        tmp.replace(self.path)


def extract_local_features(
    pipeline: FeaturePipeline, paths: Sequence[Path], desc: str
) -> list[LocalFeatures]:
    """Only the local extractor over ``paths`` (the backbone's vectors are cached already)."""
    frames = []
    for path in tqdm(paths, desc=desc, unit="img", leave=False):
        frames.append(as_stored(pipeline.local.extract(decode_image(path.read_bytes()))))
    return frames
