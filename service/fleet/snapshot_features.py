"""Decoding a snapshot's ``features.npz`` into plain numeric arrays, without trusting it: the
exact set of arrays export writes, their inflated sizes bounded before any is decompressed,
each decompressed once and never unpickled, of the kinds and shapes the others announce.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass

import numpy as np

from service.errors import InvalidInput
from service.fleet.snapshot_archive import ArchiveLimits
from service.ml.features import as_stored

MAX_DIM = 4096  # widest feature, hidden layer or embedding accepted (RetrainParams.embed_dim)


@dataclass
class Features:
    """Every frame's stored features as flat arrays (ragged keypoints by offsets)."""

    frame_ids: np.ndarray  # int64, n
    offsets: np.ndarray  # int64, n + 1
    descriptor_dim: int
    global_dim: int
    keypoints: np.ndarray  # float32, K x 2
    descriptors: np.ndarray  # float16, K x descriptor_dim
    scores: np.ndarray  # float32, K
    local_vectors: np.ndarray  # float32, n x descriptor_dim
    global_vectors: np.ndarray  # float32, n x global_dim


NPZ_ARRAYS = {
    "frame_ids": ("i", 1),
    "keypoint_counts": ("i", 1),
    "descriptor_dim": ("i", 0),
    "global_dim": ("i", 0),
    "keypoints": ("f", 2),
    "descriptors": ("f", 2),
    "scores": ("f", 1),
    "local_vectors": ("f", 2),
    "global_vectors": ("f", 2),
}


def _load_npz(data: bytes, limits: ArchiveLimits) -> dict[str, np.ndarray]:
    """The arrays of features.npz, each decompressed once, never unpickled."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zipped:
            sizes = {info.filename: info.file_size for info in zipped.infolist()}
        if set(sizes) != {f"{name}.npy" for name in NPZ_ARRAYS}:
            raise InvalidInput("the snapshot's features.npz does not hold the expected arrays")
        if sum(sizes.values()) > limits.max_total_bytes:
            raise InvalidInput(
                "the snapshot's features.npz inflates beyond LOOPNET_SNAPSHOT_MAX_TOTAL_BYTES"
            )
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in NPZ_ARRAYS}
    except InvalidInput:
        raise
    except Exception as exc:  # a bad zip, an object array, a malformed .npy header
        raise InvalidInput(f"the snapshot's features.npz is unreadable: {exc}") from exc
    for name, (kind, ndim) in NPZ_ARRAYS.items():
        array = arrays[name]
        if array.dtype.kind != kind or array.ndim != ndim:
            raise InvalidInput(
                f"the snapshot's features.npz has {name} of type {array.dtype} and "
                f"{array.ndim} dimensions"
            )
    return arrays


def decode_features(data: bytes, limits: ArchiveLimits) -> Features:
    arrays = _load_npz(data, limits)
    descriptor_dim, global_dim = int(arrays["descriptor_dim"]), int(arrays["global_dim"])
    if not (1 <= descriptor_dim <= MAX_DIM and 1 <= global_dim <= MAX_DIM):
        raise InvalidInput("the snapshot's feature sizes are out of range")
    n = len(arrays["frame_ids"])
    counts = arrays["keypoint_counts"].astype(np.int64)
    total = int(counts.sum()) if n else 0
    expected = {
        "keypoint_counts": (n,),
        "keypoints": (total, 2),
        "descriptors": (total, descriptor_dim),
        "scores": (total,),
        "local_vectors": (n, descriptor_dim),
        "global_vectors": (n, global_dim),
    }
    for name, shape in expected.items():
        if arrays[name].shape != shape or (name == "keypoint_counts" and (counts < 0).any()):
            raise InvalidInput(
                f"the snapshot's features.npz has {name} of shape {arrays[name].shape}, "
                f"expected {shape}"
            )
    features = Features(
        frame_ids=arrays["frame_ids"].astype(np.int64),
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        descriptor_dim=descriptor_dim,
        global_dim=global_dim,
        keypoints=arrays["keypoints"].astype("<f4", copy=False),
        descriptors=arrays["descriptors"].astype("<f2", copy=False),
        scores=arrays["scores"].astype("<f4", copy=False),
        local_vectors=arrays["local_vectors"].astype("<f4", copy=False),
        # rounded as the store keeps R, so the restored embedding is the stored frame's
        global_vectors=as_stored(arrays["global_vectors"]),
    )
    for name in ("keypoints", "scores", "local_vectors", "global_vectors"):
        if not np.isfinite(getattr(features, name)).all():
            raise InvalidInput(f"the snapshot's features.npz has non-finite {name}")
    return features
